"""Emulated RoboteQ dual-channel controller in CANopen mode (CiA 301), as one node on the simulated CAN bus.

Pure core: ``RoboteqNode.on_frame(can_id, data, now_s)`` consumes a received frame and ``tick(now_s)`` runs the
timers; both return the frames to send as ``(can_id, bytes)``. Times are simulated seconds (the emulated hardware
lives in sim time). One node drives one swerve module: **channel 1 = traction** (closed-loop speed, MMOD 1),
**channel 2 = steering** (closed-loop count position, MMOD 3). Node ids: module 0 -> ``node_ids[0]`` (default 1),
module 1 -> ``node_ids[1]`` (default 2); modules are ``RobotSpec.modules`` in order (default: front-left (+x,+y)
first, rear-right second).

COB-IDs (pre-defined connection set, node id n)
------------------------------------------------
====================  ===========  =========================================================================
NMT (master -> all)   0x000        [cs, node]; 0x01 start, 0x02 stop, 0x80 pre-op, 0x81 reset node,
                                   0x82 reset communication; node 0 = all
SYNC                  0x080        triggers TPDOs whose transmission type is 0..240
TPDO1..4              0x180/0x280/0x380/0x480 + n
RPDO1..4              0x200/0x300/0x400/0x500 + n
SDO request/response  0x600+n / 0x580+n   expedited only (all objects are <= 4 bytes)
Heartbeat / boot-up   0x700+n      1 byte: 0x00 boot-up, 0x04 stopped, 0x05 operational, 0x7F pre-operational
====================  ===========  =========================================================================

Boot: at start (and after NMT reset) the node sends boot-up ``0x700+n [00]`` and enters PRE-OPERATIONAL
(``autostart=True`` = RoboteQ's CAS option: straight to OPERATIONAL). SDO works in PRE-OPERATIONAL and
OPERATIONAL; PDOs flow only in OPERATIONAL. Heartbeat every ``0x1017`` ms (default 100; writable by SDO).

Default PDO mapping (protocols.md §1.9 suggestion, adapted to a position-mode steering channel)
-----------------------------------------------------------------------------------------------
All payloads little-endian, in the order listed.

========  ========  =====================================================================  ============
PDO       COB-ID    content                                                                 bytes
========  ========  =====================================================================  ============
RPDO1     0x200+n   0x2000.1 S32 traction command, per mille of MXRPM (-1000..1000)          8
                    0x2001.2 S32 steering absolute position target, counts
TPDO1     0x180+n   0x2104.1 S32 traction encoder counter (counts, ``traction_cpr``/motor rev)  8
                    0x2104.2 S32 steering encoder counter (counts, eq. 8: theta=(P-P0)*2pi/N)
TPDO2     0x280+n   0x2103.1 S32 traction motor speed, rpm                                     8
                    0x2103.2 S32 steering motor speed, rpm
TPDO3     0x380+n   0x2100.1 S16 traction motor amps x10, 0x2100.2 S16 steering amps x10,       8
                    0x2112.0 U16 fault flags FF, 0x2111.0 U16 status flags FS
TPDO4     0x480+n   0x210D.2 U16 battery volts x10, 0x2122.1 U16 / 0x2122.2 U16 motor flags FM, 8
                    0x210F.1 S16 MCU temperature degC
========  ========  =====================================================================  ============

TPDOs use transmission type 255 (periodic, RoboteQ's CTPS) with periods from config: default TPDO1 and TPDO2
every 20 ms, TPDO3 and TPDO4 every 100 ms (sim time). A master may change any of this with the standard CiA 301
objects over SDO: comm params ``0x1400+k`` / ``0x1800+k`` (sub1 COB-ID with bit31 = invalid, sub2 transmission
type: 1..240 = every n-th SYNC, 0 = on SYNC, 254/255 = event timer; sub5 event timer ms) and mappings
``0x1600+k`` / ``0x1A00+k`` (sub0 count, entries ``index<<16 | sub<<8 | bits``). Writing a TPDO event timer of 0
with type 254/255 stops that TPDO.

Objects (SDO and PDO)
---------------------
Commands (a write refreshes the RWD watchdog; reading returns the last value written):

- ``0x2000.ch`` S32 ``!G``: ch1 speed command in per mille of MXRPM (``traction_max_rpm``, default 3000 rpm);
  ch2 (position mode) is accepted but has no effect (use 0x2001.2).
- ``0x2001.ch`` S32 ``!P``: ch2 absolute steering target in counts; ch1 ignored (speed mode).
- ``0x2002.ch`` S32 ``!S``: ch1 speed target in rpm (same effect as !G with rpm units); ch2 travel speed of
  position moves in motor rpm (default ``steer_travel_rpm`` 1500).
- ``0x2003.ch`` S32 ``!C``: load encoder counter (counts).
- ``0x2006.ch`` / ``0x2007.ch`` S32 ``!AC`` / ``!DC``: acceleration / deceleration in 0.1 rpm/s.
- ``0x200C.0`` U8 ``!EX`` emergency stop (latched: FF bit4, FS bit3, motors stop); ``0x200D.0`` U8 ``!MG`` release.
- ``0x200E.0`` U8 ``!MS ch``: stop channel ch (FM bit3 until its next command).
- ``0x2005.1..16`` S32 user variables; ``0x2017.0`` U8 ``%EESAV`` (accepted, no effect).

Queries (read-only):

- ``0x2100.ch`` S16 motor amps x10; ``0x2101.ch`` S16 actual command after ramp (per mille of MXRPM / of travel);
  ``0x2102.ch`` S16 applied power per mille; ``0x2103.ch`` S32 motor speed rpm; ``0x2104.ch`` S32 encoder counter
  (wraps at 32 bits);
  ``0x2107.ch`` S16 speed per mille of MXRPM; ``0x210D.1/.2/.3`` U16 internal V x10 / battery V x10 / 5 V out mV;
  ``0x210F.1/.2`` S16 temperatures degC; ``0x2111.0`` U16 FS; ``0x2112.0`` U16 FF; ``0x2114.ch`` S32 closed-loop
  error (ch1 rpm, ch2 counts); ``0x211B.ch`` U8 destination reached; ``0x2122.ch`` U16 FM; ``0x2106.1..16`` S32
  user variables.
- Standard: ``0x1000`` U32 device type, ``0x1001`` U8 error register, ``0x1017`` U16 heartbeat ms (rw),
  ``0x1018.1..4`` U32 identity (vendor 0x469).

SDO downloads accept strict CiA 301 frames (0x23/0x2B/0x2F) and the RoboteQ manual's frames without the e/s bits
(0x20/0x28/0x2C: length from n); a value shorter than the object is sign-/zero-extended, a longer one is aborted
(0x06070012). Uploads answer strictly (0x43/0x4B/0x4F with e and s set). Aborts: 0x06020000 no object,
0x06090011 no sub-index, 0x06010002 read-only, 0x05040001 unsupported command (segmented/block transfers).

Flags (protocols.md §1.7): FF bit4 emergency stop. FS bit0 = commands are arriving (serial/CAN command mode
active within the watchdog period), bit3 power stage off (e-stop). FM bit3 safety stop (``!MS``), bit4/bit5
forward/reverse limit when a steering target was clamped to ``steer_limit_counts``.

Watchdog (RWD, default 1000 ms, ``0`` = off): when no command (SDO write to 0x20xx or RPDO) arrives for the
period, traction ramps to 0 rpm and steering holds where it can stop; commands resuming resume motion.
The watchdog keeps running in every NMT state.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from dataclasses import dataclass, field

from services.sim.robot_model import SteerMotor, TractionMotor

NMT_INITIALISING, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F

ABORT_UNSUPPORTED = 0x05040001
ABORT_READ_ONLY = 0x06010002
ABORT_WRITE_ONLY = 0x06010001
ABORT_NO_OBJECT = 0x06020000
ABORT_NO_SUBINDEX = 0x06090011
ABORT_TOO_LONG = 0x06070012
ABORT_VALUE_RANGE = 0x06090030
ABORT_PDO_MAPPING = 0x06040041

#: struct format, signed, bit length
TYPES: dict[str, tuple[str, bool, int]] = {
    "U8": ("<B", False, 8), "S8": ("<b", True, 8), "U16": ("<H", False, 16), "S16": ("<h", True, 16),
    "U32": ("<I", False, 32), "S32": ("<i", True, 32),
}

FF_ESTOP = 1 << 4
FS_COMMAND_MODE = 1 << 0
FS_POWER_OFF = 1 << 3
FM_SAFETY_STOP = 1 << 3
FM_FORWARD_LIMIT = 1 << 4
FM_REVERSE_LIMIT = 1 << 5

DEFAULT_RPDO_MAPS: list[list[tuple[int, int, int]]] = [
    [(0x2000, 1, 32), (0x2001, 2, 32)], [], [], [],
]
DEFAULT_TPDO_MAPS: list[list[tuple[int, int, int]]] = [
    [(0x2104, 1, 32), (0x2104, 2, 32)],
    [(0x2103, 1, 32), (0x2103, 2, 32)],
    [(0x2100, 1, 16), (0x2100, 2, 16), (0x2112, 0, 16), (0x2111, 0, 16)],
    [(0x210D, 2, 16), (0x2122, 1, 16), (0x2122, 2, 16), (0x210F, 1, 16)],
]


class SdoAbort(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(f"SDO abort 0x{code:08X}")
        self.code = code


@dataclass
class RoboteqSettings:
    """Controller configuration (RoboteQ ``^`` parameters; not reachable over CANopen on the real device)."""

    node_id: int = 1
    watchdog_ms: int = 1000
    heartbeat_ms: int = 100
    autostart: bool = False
    traction_max_rpm: float = 3000.0
    steer_max_rpm: float = 3000.0
    steer_travel_rpm: float = 1500.0
    traction_accel_rpm_s: float = 2000.0
    steer_accel_rpm_s: float = 5000.0
    estop_decel_rpm_s: float = 10000.0
    tpdo_periods_ms: list[int] = field(default_factory=lambda: [20, 20, 100, 100])
    steer_limit_counts: float = 0.0
    battery_v: float = 48.0


@dataclass
class _Pdo:
    cob_id: int
    trans_type: int
    event_timer_ms: int
    mapping: list[tuple[int, int, int]]
    inhibit: int = 0
    next_due_s: float = 0.0
    sync_count: int = 0
    pending: list[tuple[int, int, int]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.pending = list(self.mapping)


class RoboteqNode:
    """One emulated controller: object dictionary, SDO server, NMT slave, heartbeat, PDOs, watchdog, flags."""

    def __init__(self, settings: RoboteqSettings, traction: TractionMotor, steer: SteerMotor,
                 noise: Callable[[], float] | None = None) -> None:
        self.s = settings
        self.n = settings.node_id
        if not 1 <= self.n <= 127:
            raise ValueError(f"CANopen node id must be 1..127, got {self.n}")
        self.traction = traction
        self.steer = steer
        self.noise = noise  # optional encoder count noise (counts), called per counter read
        self.state = NMT_INITIALISING
        self.estopped = False
        self.safety_stop = [False, False]
        self.limit_flags = 0
        self.last_command_s: float | None = None
        self.watchdog_tripped = False
        self.commands: dict[tuple[int, int], int] = {}
        self.user_vars: dict[int, int] = {}
        self.heartbeat_ms = settings.heartbeat_ms
        self._next_heartbeat_s = 0.0
        self.sdo_count = 0
        self.rpdo_count = 0
        self.tpdo_count = 0
        traction.max_rpm = settings.traction_max_rpm
        traction.accel_rpm_s = traction.decel_rpm_s = settings.traction_accel_rpm_s
        steer.max_rpm = settings.steer_max_rpm
        steer.travel_rpm = settings.steer_travel_rpm
        steer.accel_rpm_s = steer.decel_rpm_s = settings.steer_accel_rpm_s
        self._reset_comm()
        self._build_od()

    # ------------------------------------------------------------------ object dictionary

    def _build_od(self) -> None:
        """(index, sub) -> (type, getter or None, setter or None)."""
        od: dict[tuple[int, int], tuple[str, Callable[[], int | None] | None, Callable[..., None] | None]] = {}
        t, st = self.traction, self.steer

        def cmd(index: int, sub: int, typ: str, apply: Callable[[int], None]) -> None:
            def setter(v: int, key: tuple[int, int] = (index, sub), apply: Callable[[int], None] = apply) -> None:
                self.commands[key] = v
                apply(v)

            od[(index, sub)] = (typ, functools.partial(self.commands.get, (index, sub), 0), setter)

        # commands
        cmd(0x2000, 1, "S32", self._go_traction)
        cmd(0x2000, 2, "S32", lambda v: self._command(2))
        cmd(0x2001, 1, "S32", lambda v: self._command(1))
        cmd(0x2001, 2, "S32", self._go_steer)
        cmd(0x2002, 1, "S32", self._speed_traction)
        cmd(0x2002, 2, "S32", self._travel_steer)
        cmd(0x2003, 1, "S32", lambda v: self._load_counter(1, v))
        cmd(0x2003, 2, "S32", lambda v: self._load_counter(2, v))
        cmd(0x2006, 1, "S32", lambda v: self._ramp(t, "accel_rpm_s", v, 1))
        cmd(0x2006, 2, "S32", lambda v: self._ramp(st, "accel_rpm_s", v, 2))
        cmd(0x2007, 1, "S32", lambda v: self._ramp(t, "decel_rpm_s", v, 1))
        cmd(0x2007, 2, "S32", lambda v: self._ramp(st, "decel_rpm_s", v, 2))
        cmd(0x200C, 0, "U8", lambda v: self._estop())
        cmd(0x200D, 0, "U8", lambda v: self._release())
        cmd(0x200E, 0, "U8", self._motor_stop)
        cmd(0x2017, 0, "U8", lambda v: None)
        for k in range(1, 17):
            od[(0x2005, k)] = ("S32", functools.partial(self.user_vars.get, k, 0),
                               functools.partial(self.user_vars.__setitem__, k))
            od[(0x2106, k)] = ("S32", functools.partial(self.user_vars.get, k, 0), None)
        # queries
        od[(0x2100, 1)] = ("S16", lambda: _clamp16(round(t.amps * 10)), None)
        od[(0x2100, 2)] = ("S16", lambda: _clamp16(round(st.amps * 10)), None)
        od[(0x2101, 1)] = ("S16", lambda: _clamp16(round(t.ramped_rpm / t.max_rpm * 1000)), None)
        od[(0x2101, 2)] = ("S16", lambda: _clamp16(round(st.speed_rpm / st.max_rpm * 1000)), None)
        od[(0x2102, 1)] = ("S16", lambda: _clamp16(round(t.speed_rpm / t.max_rpm * 1000)), None)
        od[(0x2102, 2)] = ("S16", lambda: _clamp16(round(st.speed_rpm / st.max_rpm * 1000)), None)
        od[(0x2103, 1)] = ("S32", lambda: round(t.speed_rpm), None)
        od[(0x2103, 2)] = ("S32", lambda: round(st.speed_rpm), None)
        od[(0x2104, 1)] = ("S32", lambda: self.counter(1), None)
        od[(0x2104, 2)] = ("S32", lambda: self.counter(2), None)
        od[(0x2107, 1)] = ("S16", lambda: _clamp16(round(t.speed_rpm / t.max_rpm * 1000)), None)
        od[(0x2107, 2)] = ("S16", lambda: _clamp16(round(st.speed_rpm / st.max_rpm * 1000)), None)
        od[(0x210D, 1)] = ("U16", lambda: round(self.s.battery_v * 10), None)
        od[(0x210D, 2)] = ("U16", lambda: round(self.s.battery_v * 10), None)
        od[(0x210D, 3)] = ("U16", lambda: 5000, None)
        od[(0x210F, 1)] = ("S16", lambda: 35, None)
        od[(0x210F, 2)] = ("S16", lambda: 30, None)
        od[(0x2111, 0)] = ("U16", self.status_flags, None)
        od[(0x2112, 0)] = ("U16", self.fault_flags, None)
        od[(0x2114, 1)] = ("S32", lambda: round(t.target_rpm - t.speed_rpm), None)
        od[(0x2114, 2)] = ("S32", lambda: round(st.target_counts - st.position_counts), None)
        od[(0x211B, 1)] = ("U8", lambda: int(abs(t.target_rpm - t.speed_rpm) < 1.0), None)
        od[(0x211B, 2)] = ("U8", lambda: int(abs(st.target_counts - st.position_counts) < 1.0), None)
        od[(0x2122, 1)] = ("U16", lambda: self.motor_flags(1), None)
        od[(0x2122, 2)] = ("U16", lambda: self.motor_flags(2), None)
        # standard objects
        od[(0x1000, 0)] = ("U32", lambda: 0x00000192, None)
        od[(0x1001, 0)] = ("U8", lambda: 0x00 if not self.estopped else 0x01, None)
        od[(0x1017, 0)] = ("U16", lambda: self.heartbeat_ms, self._set_heartbeat)
        od[(0x1018, 0)] = ("U8", lambda: 4, None)
        for sub, value in ((1, 0x00000469), (2, 0x00002360), (3, 0x00020001), (4, 0x00001000 + self.n)):
            od[(0x1018, sub)] = ("U32", functools.partial(int, value), None)
        self.od = od

    def _pdo_object(self, index: int, sub: int, write: int | None) -> tuple[int, str] | None:
        """The CiA 301 PDO comm (0x14xx/0x18xx) and mapping (0x16xx/0x1Axx) objects; None: not a PDO object.

        Reading returns (value, type); writing applies ``write``. Mapping follows the standard sequence: sub0 = 0,
        entries sub1..k, sub0 = k (the new mapping takes effect when sub0 is written).
        """
        base = index & 0xFF00
        k = index & 0xFF
        if base not in (0x1400, 0x1600, 0x1800, 0x1A00) or k > 3:
            return None
        pdo = (self.rpdos if base in (0x1400, 0x1600) else self.tpdos)[k]
        if base in (0x1400, 0x1800):
            types = {0: "U8", 1: "U32", 2: "U8"} if base == 0x1400 else \
                {0: "U8", 1: "U32", 2: "U8", 3: "U16", 5: "U16"}
            if sub not in types:
                raise SdoAbort(ABORT_NO_SUBINDEX)
            if write is None:
                value = {0: max(types), 1: pdo.cob_id, 2: pdo.trans_type, 3: pdo.inhibit, 5: pdo.event_timer_ms}[sub]
                return value, types[sub]
            if sub == 0:
                raise SdoAbort(ABORT_READ_ONLY)
            if sub == 1:
                pdo.cob_id = write & 0xFFFFFFFF
            elif sub == 2:
                pdo.trans_type = write & 0xFF
                pdo.sync_count = 0
            elif sub == 3:
                pdo.inhibit = write & 0xFFFF
            else:
                pdo.event_timer_ms = write & 0xFFFF
                pdo.next_due_s = 0.0
            return 0, types[sub]
        if not 0 <= sub <= 8:
            raise SdoAbort(ABORT_NO_SUBINDEX)
        if write is None:
            if sub == 0:
                return len(pdo.mapping), "U8"
            return (_entry(*pdo.mapping[sub - 1]) if sub <= len(pdo.mapping) else 0), "U32"
        if sub == 0:
            if write > len(pdo.pending) or any(bits == 0 for _, _, bits in pdo.pending[:write]):
                raise SdoAbort(ABORT_VALUE_RANGE)
            mapping = pdo.pending[:write]
            if sum(bits for _, _, bits in mapping) > 64:
                raise SdoAbort(ABORT_PDO_MAPPING)
            pdo.mapping = list(mapping)
            return 0, "U8"
        entry = (write >> 16, (write >> 8) & 0xFF, write & 0xFF)
        if entry[2] not in (8, 16, 32) or (entry[0], entry[1]) not in self.od:
            raise SdoAbort(ABORT_PDO_MAPPING)
        while len(pdo.pending) < sub:
            pdo.pending.append((0, 0, 0))
        pdo.pending[sub - 1] = entry
        return 0, "U32"

    def read_object(self, index: int, sub: int) -> tuple[int, str]:
        """Current value and type of an object (SDO upload semantics); raises SdoAbort."""
        pdo_value = self._pdo_object(index, sub, None)
        if pdo_value is not None:
            return pdo_value
        entry = self.od.get((index, sub))
        if entry is None:
            raise SdoAbort(ABORT_NO_SUBINDEX if any(i == index for i, _ in self.od) else ABORT_NO_OBJECT)
        typ, getter, _ = entry
        if getter is None:
            raise SdoAbort(ABORT_WRITE_ONLY)
        return int(getter() or 0), typ

    def write_object(self, index: int, sub: int, raw: bytes, now_s: float) -> None:
        """Apply a write (SDO download or RPDO field) of little-endian ``raw``; raises SdoAbort."""
        if index & 0xF000 == 0x1000 and (index & 0xFF00) in (0x1400, 0x1600, 0x1800, 0x1A00):
            self._pdo_object(index, sub, int.from_bytes(raw, "little"))
            return
        entry = self.od.get((index, sub))
        if entry is None:
            raise SdoAbort(ABORT_NO_SUBINDEX if any(i == index for i, _ in self.od) else ABORT_NO_OBJECT)
        typ, _, setter = entry
        if setter is None:
            raise SdoAbort(ABORT_READ_ONLY)
        _, signed, bits = TYPES[typ]
        if len(raw) * 8 > bits:
            raise SdoAbort(ABORT_TOO_LONG)
        value = int.from_bytes(raw, "little", signed=signed)
        if 0x2000 <= index <= 0x20FF:
            self.last_command_s = now_s
            self.watchdog_tripped = False
        setter(value)

    # ------------------------------------------------------------------ command effects

    def _command(self, ch: int) -> None:
        self.safety_stop[ch - 1] = False

    def _go_traction(self, permille: int) -> None:
        self._command(1)
        permille = max(-1000, min(1000, permille))
        self._traction_rpm = permille / 1000.0 * self.s.traction_max_rpm
        self._apply_traction()

    def _speed_traction(self, rpm: int) -> None:
        self._command(1)
        self._traction_rpm = max(-self.s.traction_max_rpm, min(self.s.traction_max_rpm, float(rpm)))
        self._apply_traction()

    def _apply_traction(self) -> None:
        stopped = self.estopped or self.safety_stop[0] or self.watchdog_tripped
        self.traction.target_rpm = 0.0 if stopped else self._traction_rpm

    def _go_steer(self, counts: int) -> None:
        self._command(2)
        lim = self.s.steer_limit_counts
        self.limit_flags = 0
        if lim > 0:
            if counts > lim:
                counts, self.limit_flags = int(lim), FM_FORWARD_LIMIT
            elif counts < -lim:
                counts, self.limit_flags = int(-lim), FM_REVERSE_LIMIT
        self._steer_counts = float(counts)
        if not (self.estopped or self.safety_stop[1] or self.watchdog_tripped):
            self.steer.target_counts = self._steer_counts

    def _travel_steer(self, rpm: int) -> None:
        self._command(2)
        self.steer.travel_rpm = max(1.0, min(self.s.steer_max_rpm, abs(float(rpm))))

    def _ramp(self, motor: TractionMotor | SteerMotor, attr: str, tenth_rpm_s: int, ch: int) -> None:
        self._command(ch)
        if tenth_rpm_s > 0:
            setattr(motor, attr, tenth_rpm_s / 10.0)

    def _load_counter(self, ch: int, counts: int) -> None:
        if ch == 1:
            self.traction.position_counts = float(counts)
        else:
            # re-reference the steering counter: the wheel does not move, target keeps its physical meaning
            delta = counts - self.steer.position_counts
            self.steer.position_counts += delta
            self.steer.target_counts += delta
            self._steer_counts += delta

    def _estop(self) -> None:
        if not self.estopped:
            self._decel_before_estop = self.traction.decel_rpm_s
        self.estopped = True
        self.traction.target_rpm = 0.0
        self.traction.decel_rpm_s = max(self.traction.decel_rpm_s, self.s.estop_decel_rpm_s)
        self.steer.hold()

    def _release(self) -> None:
        """!MG: the live command applies again (the master should command zero before releasing)."""
        if self.estopped:
            self.traction.decel_rpm_s = self._decel_before_estop
        self.estopped = False
        self._apply_traction()
        if not (self.safety_stop[1] or self.watchdog_tripped):
            self.steer.target_counts = self._steer_counts

    def _motor_stop(self, ch: int) -> None:
        if ch not in (1, 2):
            raise SdoAbort(ABORT_VALUE_RANGE)
        self.safety_stop[ch - 1] = True
        if ch == 1:
            self.traction.target_rpm = 0.0
        else:
            self.steer.hold()

    def _set_heartbeat(self, ms: int) -> None:
        self.heartbeat_ms = ms
        self._next_heartbeat_s = 0.0

    # ------------------------------------------------------------------ reads

    def counter(self, ch: int) -> int:
        value = self.traction.position_counts if ch == 1 else self.steer.position_counts
        if self.noise is not None:
            value += self.noise()
        return ((int(round(value)) + 2**31) % 2**32) - 2**31  # a 32-bit counter wraps

    def fault_flags(self) -> int:
        return FF_ESTOP if self.estopped else 0

    def status_flags(self) -> int:
        flags = FS_POWER_OFF if self.estopped else 0
        if self.last_command_s is not None and not self.watchdog_tripped:
            flags |= FS_COMMAND_MODE
        return flags

    def motor_flags(self, ch: int) -> int:
        flags = FM_SAFETY_STOP if self.safety_stop[ch - 1] else 0
        if ch == 2:
            flags |= self.limit_flags
        return flags

    # ------------------------------------------------------------------ CAN

    def _reset_comm(self) -> None:
        self.rpdos = [_Pdo(base + self.n, 255, 0, list(m)) for base, m in
                      zip((0x200, 0x300, 0x400, 0x500), DEFAULT_RPDO_MAPS)]
        for p in self.rpdos:
            if not p.mapping:
                p.cob_id |= 0x80000000
        periods = list(self.s.tpdo_periods_ms) + [0] * 4
        self.tpdos = [_Pdo(base + self.n, 255, periods[i], list(m)) for i, (base, m) in
                      enumerate(zip((0x180, 0x280, 0x380, 0x480), DEFAULT_TPDO_MAPS))]
        self._traction_rpm = 0.0
        self._steer_counts = self.steer.position_counts
        self._decel_before_estop = self.traction.decel_rpm_s

    def boot(self, now_s: float) -> list[tuple[int, bytes]]:
        """Power-up / NMT reset: boot-up message, then PRE-OPERATIONAL (OPERATIONAL with autostart)."""
        self.state = NMT_OPERATIONAL if self.s.autostart else NMT_PRE_OPERATIONAL
        self._next_heartbeat_s = now_s + self.heartbeat_ms / 1000.0
        for p in self.tpdos:
            p.next_due_s = 0.0
        return [(0x700 + self.n, b"\x00")]

    def on_frame(self, can_id: int, data: bytes, now_s: float) -> list[tuple[int, bytes]]:
        """Handle one received frame; returns frames to send."""
        if can_id == 0x600 + self.n:
            if self.state in (NMT_PRE_OPERATIONAL, NMT_OPERATIONAL):
                return [(0x580 + self.n, self._sdo(data, now_s))]
            return []
        if can_id == 0x000:
            return self._nmt(data, now_s)
        if can_id == 0x080:
            return self._sync() if self.state == NMT_OPERATIONAL else []
        if self.state == NMT_OPERATIONAL and 0x200 <= can_id < 0x580:
            for p in self.rpdos:
                if not p.cob_id & 0x80000000 and p.cob_id & 0x7FF == can_id:
                    self._rpdo(p, data, now_s)
                    break
        return []

    def _nmt(self, data: bytes, now_s: float) -> list[tuple[int, bytes]]:
        if len(data) < 2 or data[1] not in (0, self.n):
            return []
        cs = data[0]
        if cs == 0x01:
            self.state = NMT_OPERATIONAL
            for p in self.tpdos:
                p.next_due_s = 0.0
        elif cs == 0x02:
            self.state = NMT_STOPPED
        elif cs == 0x80:
            self.state = NMT_PRE_OPERATIONAL
        elif cs in (0x81, 0x82):
            if cs == 0x81:
                self.commands.clear()
                self.estopped = False
                self.safety_stop = [False, False]
                self.last_command_s = None
                self.traction.target_rpm = 0.0
                self.steer.hold()
            self.heartbeat_ms = self.s.heartbeat_ms
            self._reset_comm()
            return self.boot(now_s)
        return []

    def _sdo(self, data: bytes, now_s: float) -> bytes:
        self.sdo_count += 1
        if len(data) < 8:
            data = bytes(data) + bytes(8 - len(data))
        cmd = data[0]
        index = data[1] | data[2] << 8
        sub = data[3]
        ccs = cmd >> 5
        head = data[1:4]
        try:
            if ccs == 1:  # initiate download
                e, s, n = cmd & 0x02, cmd & 0x01, (cmd >> 2) & 0x03
                if not e and s:
                    raise SdoAbort(ABORT_UNSUPPORTED)  # segmented download: no object needs it
                length = 4 - n if (s or not e) else 4
                self.write_object(index, sub, bytes(data[4:4 + length]), now_s)
                return bytes([0x60]) + head + bytes(4)
            if ccs == 2:  # initiate upload
                value, typ = self.read_object(index, sub)
                fmt, signed, bits = TYPES[typ]
                size = bits // 8
                payload = value.to_bytes(size, "little", signed=signed)
                return bytes([0x43 | ((4 - size) << 2)]) + head + payload + bytes(4 - size)
            if ccs == 4:  # abort from the client
                return bytes([0x80]) + head + ABORT_UNSUPPORTED.to_bytes(4, "little")
            raise SdoAbort(ABORT_UNSUPPORTED)
        except SdoAbort as exc:
            return bytes([0x80]) + head + exc.code.to_bytes(4, "little")
        except (OverflowError, ValueError):
            return bytes([0x80]) + head + ABORT_VALUE_RANGE.to_bytes(4, "little")

    def _rpdo(self, pdo: _Pdo, data: bytes, now_s: float) -> None:
        self.rpdo_count += 1
        offset = 0
        for index, sub, bits in pdo.mapping:
            size = bits // 8
            chunk = bytes(data[offset:offset + size])
            offset += size
            if len(chunk) < size:
                return  # short frame: ignore the rest (a real node would raise an EMCY)
            with contextlib.suppress(SdoAbort):  # a bad field in a PDO has no one to answer to
                self.write_object(index, sub, chunk, now_s)

    def _tpdo_payload(self, pdo: _Pdo) -> bytes:
        out = bytearray()
        for index, sub, bits in pdo.mapping:
            try:
                value, typ = self.read_object(index, sub)
            except SdoAbort:
                value, typ = 0, "U32"
            size = bits // 8
            if TYPES[typ][1]:
                lim = 1 << (bits - 1)
                out += max(-lim, min(lim - 1, value)).to_bytes(size, "little", signed=True)
            else:
                out += (value & ((1 << bits) - 1)).to_bytes(size, "little")
        return bytes(out)

    def _sync(self) -> list[tuple[int, bytes]]:
        out = []
        for p in self.tpdos:
            if p.cob_id & 0x80000000 or not p.mapping or p.trans_type > 240:
                continue
            p.sync_count += 1
            if p.sync_count >= max(1, p.trans_type):
                p.sync_count = 0
                out.append((p.cob_id & 0x7FF, self._tpdo_payload(p)))
        self.tpdo_count += len(out)
        return out

    def tick(self, now_s: float) -> list[tuple[int, bytes]]:
        """Timers: watchdog, heartbeat and periodic TPDOs due at ``now_s``."""
        out: list[tuple[int, bytes]] = []
        if self.state == NMT_INITIALISING:
            return out
        wd = self.s.watchdog_ms
        if wd > 0 and self.last_command_s is not None and not self.watchdog_tripped \
                and now_s - self.last_command_s > wd / 1000.0:
            self.watchdog_tripped = True
            self.traction.target_rpm = 0.0
            self.steer.hold()
        if self.heartbeat_ms > 0 and now_s >= self._next_heartbeat_s:
            out.append((0x700 + self.n, bytes([self.state])))
            self._next_heartbeat_s = max(self._next_heartbeat_s + self.heartbeat_ms / 1000.0, now_s)
        if self.state == NMT_OPERATIONAL:
            for p in self.tpdos:
                if p.trans_type >= 254 and p.event_timer_ms > 0 and now_s >= p.next_due_s \
                        and not p.cob_id & 0x80000000 and p.mapping:
                    out.append((p.cob_id & 0x7FF, self._tpdo_payload(p)))
                    self.tpdo_count += 1
                    period = p.event_timer_ms / 1000.0
                    late = now_s - p.next_due_s
                    # keep the cadence; (re)anchor at this send when starting or when far behind
                    p.next_due_s = p.next_due_s + period if 0.0 <= late < period and p.next_due_s > 0.0 \
                        else now_s + period
        return out


def _entry(index: int, sub: int, bits: int) -> int:
    return index << 16 | sub << 8 | bits


def _clamp16(v: int) -> int:
    return max(-32768, min(32767, v))

