"""CANopen link to the RoboteQ dual-channel controllers (protocols.md §1, §2): one controller per swerve module,
channel 1 traction (closed-loop speed), channel 2 steering (closed-loop position).

Start-up (``open``): connect the python-can bus, NMT start each node (``000: 01 nn``), map the PDOs by SDO
where the controller allows it (standard CiA 301 sequence: COB-ID invalid -> mapping count 0 -> entries -> count
-> COB-ID valid; a refused write is accepted when the read-back mapping already matches), set the producer
heartbeat (0x1017) and wait for a heartbeat of every node.

PDO layout (protocols.md §1.9, with the paper's units: eq. 7 rpm, eq. 8 counts):

| PDO (COB-ID)      | content                                                        | bytes          |
|-------------------|----------------------------------------------------------------|----------------|
| RPDO1 (0x200+n)   | 0x2002.1 ``!S`` traction speed rpm S32, 0x2001.2 ``!P`` steering position counts S32 | 8 |
| TPDO1 (0x180+n)   | 0x2104.1 / 0x2104.2 ``?C`` encoder counts, S32 each            | 8              |
| TPDO2 (0x280+n)   | 0x2103.1 / 0x2103.2 ``?S`` encoder speed rpm, S32 each         | 8              |
| TPDO3 (0x380+n)   | 0x2100.1 / 0x2100.2 ``?A`` amps x10 S16, 0x2112.0 ``?FF`` U16, 0x2111.0 ``?FS`` U16 | 8 |
| TPDO4 (0x480+n)   | 0x210D.2 battery V x10 U16, 0x2122.1 / 0x2122.2 ``?FM`` U16, 0x210F.1 MCU temp S16 | 8 |

TPDO1/2 are requested every ``tpdo_period_ms`` (20), TPDO3/4 every ``tpdo_slow_period_ms`` (100) with
transmission type 255 and the event timer 0x1800+k.5 (on a real RoboteQ the rate may only be settable by CTPS).
RPDO1 goes to every node when the commands change and at least every ``rpdo_refresh_s`` (0.1 s), so the
controller's command watchdog (``RWD``, 1000 ms) stays fed; when the drive stops sending (crash, lost bus) the
controller stops the motors by itself. E-stop ``!EX`` = SDO write 1 to 0x200C.0, release ``!MG`` = SDO write 1 to
0x200D.0.

Threads: after start-up the control thread does all CAN I/O: ``poll`` dispatches received frames (TPDOs and
heartbeats into per-node snapshots, SDO replies to a waiting SDO client), ``send`` writes RPDOs, ``health`` judges
the link. SDO work from other threads (e-stop, release) is serialised by a lock and answered through ``poll``.
Link health: a heartbeat (or TPDO1) counts as lost when it is older than its timeout both on ``clock`` and on
the monotonic wall clock. On a robot both are wall time. Under ``use_sim_time`` ``clock`` is the simulator's:
its controllers produce heartbeats in sim time, so a simulator that stalls is not taken for a dead controller,
and a simulated bus that relays frames late while the simulator runs faster than real time is not either (a
closed bus still fails at once).
"""

from __future__ import annotations

import contextlib
import logging
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import can
import canopen

from services.drive.controller import ModuleFeedback, MotorCommand

log = logging.getLogger("zagv.drive.can")

NMT_START = 0x01
HEARTBEAT_OPERATIONAL = 0x05
RPDO_COB = (0x200, 0x300, 0x400, 0x500)
TPDO_COB = (0x180, 0x280, 0x380, 0x480)

#: RPDO1 mapping: (index, sub, bits)
RPDO1_MAP = ((0x2002, 1, 32), (0x2001, 2, 32))
#: TPDO1..4 mappings
TPDO_MAPS = (
    ((0x2104, 1, 32), (0x2104, 2, 32)),
    ((0x2103, 1, 32), (0x2103, 2, 32)),
    ((0x2100, 1, 16), (0x2100, 2, 16), (0x2112, 0, 16), (0x2111, 0, 16)),
    ((0x210D, 2, 16), (0x2122, 1, 16), (0x2122, 2, 16), (0x210F, 1, 16)),
)
RPDO1 = struct.Struct("<ii")
TPDO1 = struct.Struct("<ii")
TPDO2 = struct.Struct("<ii")
TPDO3 = struct.Struct("<hhHH")
TPDO4 = struct.Struct("<HHHh")

ESTOP_INDEX = 0x200C
RELEASE_INDEX = 0x200D

#: FF bit 4: emergency stop active (protocols.md §1.7)
FF_ESTOP = 0x10


class LinkError(RuntimeError):
    """The link cannot be used (bus down, node silent, a refused start-up step); the message says which."""


@dataclass(frozen=True)
class LinkSettings:
    """How to reach the controllers; times in wall seconds."""

    interface: str = "remote"
    channel: str = "ws://127.0.0.1:54701/"
    bitrate: int = 0
    node_ids: tuple[int, ...] = (1, 2)
    heartbeat_period_ms: int = 100
    heartbeat_timeout_s: float = 0.5
    feedback_timeout_s: float = 0.5
    sdo_timeout_s: float = 0.3
    configure_pdos: bool = True
    tpdo_period_ms: int = 20
    tpdo_slow_period_ms: int = 100
    startup_timeout_s: float = 2.0


def mapping_entry(index: int, sub: int, bits: int) -> int:
    """CiA 301 PDO mapping entry: index << 16 | sub << 8 | bit length."""
    return (index << 16) | (sub << 8) | bits


class _NodeState:
    """Latest frames of one node, written where frames are dispatched (each field a tuple swap)."""

    def __init__(self) -> None:
        self.heartbeat_at: float | None = None
        self.heartbeat_wall = 0.0
        self.heartbeat_state: int | None = None
        self.feedback_at: float | None = None
        self.feedback_wall = 0.0
        self.counts = (0, 0)
        self.rpm = (0, 0)
        self.amps_flags = (0, 0, 0, 0)
        self.extra = (0, 0, 0, 0)
        self.bad_frames = 0


class RoboteqLink:
    """Both controllers on one bus. ``open`` (blocking, may raise LinkError), then ``send`` each cycle."""

    def __init__(self, settings: LinkSettings, clock: Callable[[], float] = time.monotonic) -> None:
        if not settings.node_ids:
            raise ValueError("at least one node id is needed")
        if len(set(settings.node_ids)) != len(settings.node_ids) or not all(
                1 <= n <= 127 for n in settings.node_ids):
            raise ValueError(f"node ids must be distinct and in 1..127, got {list(settings.node_ids)}")
        self.settings = settings
        self.clock = clock
        self.network: canopen.Network | None = None
        self.nodes: list[canopen.RemoteNode] = []
        self.states = [_NodeState() for _ in settings.node_ids]
        self.frames_sent = 0
        self.send_errors = 0
        self.error_frames = 0
        self._sdo_lock = threading.Lock()
        self._rpdo_ids = [RPDO_COB[0] + n for n in settings.node_ids]
        self._error: str = ""

    # ------------------------------------------------------------------ lifetime

    def open(self) -> None:
        """Connect and start the nodes; raises LinkError naming the failed step (the link is then closed).

        During start-up a python-can notifier thread dispatches the replies; afterwards the link is *polled*:
        the control thread reads every pending frame at the start of its cycle (``poll``), so one thread does all
        CAN I/O and no receive thread competes with it for the interpreter.
        """
        s = self.settings
        try:
            kwargs: dict[str, Any] = {"interface": s.interface, "channel": s.channel}
            if s.bitrate:
                kwargs["bitrate"] = s.bitrate
            bus = can.Bus(**kwargs)
            network = canopen.Network(bus)
            network.notifier = can.Notifier(bus, network.listeners, 0.02)
        except Exception as exc:  # python-can raises many kinds (OSError, CanError, websocket errors)
            raise LinkError(f"cannot open CAN bus {s.interface}:{s.channel}: {type(exc).__name__}: {exc}") from None
        self.network = network
        self.states = [_NodeState() for _ in s.node_ids]
        self._error = ""
        try:
            for i, node_id in enumerate(s.node_ids):
                node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
                network.add_node(node)
                node.sdo.RESPONSE_TIMEOUT = s.sdo_timeout_s
                self.nodes.append(node)
                network.subscribe(0x700 + node_id, self._heartbeat_handler(i))
                for k, cob in enumerate(TPDO_COB):
                    network.subscribe(cob + node_id, self._tpdo_handler(i, k))
            with self._sdo_lock:
                for node in self.nodes:
                    self._configure(node)  # in PRE-OPERATIONAL (or already started: the mapping sequence is safe)
                    node.nmt.send_command(NMT_START)
            self._wait_alive(s.startup_timeout_s)
            notifier, network.notifier = network.notifier, None
            notifier.stop(1.0)
            if notifier.exception is not None:
                raise LinkError(f"CAN bus lost during start-up: {notifier.exception}")
        except LinkError:
            self.close()
            raise
        except Exception as exc:
            self.close()
            raise LinkError(f"CAN start-up failed: {type(exc).__name__}: {exc}") from None
        log.info("CAN link up on %s:%s, nodes %s", s.interface, s.channel, list(s.node_ids))

    def poll(self, max_frames: int = 256) -> int:
        """Dispatch every received frame (TPDOs, heartbeats, SDO replies); raises LinkError when the bus fails."""
        network = self.network
        if network is None:
            raise LinkError("CAN link is closed")
        bus = network.bus
        if bus is None:
            raise LinkError("CAN link has no bus")
        n = 0
        try:
            while n < max_frames:
                msg = bus.recv(0.0)
                if msg is None:
                    break
                n += 1
                if msg.is_error_frame:
                    self.error_frames += 1
                    continue
                if not msg.is_remote_frame:
                    network.notify(msg.arbitration_id, msg.data, msg.timestamp)
        except Exception as exc:
            self._error = f"CAN bus lost: {type(exc).__name__}: {exc}"
            raise LinkError(self._error) from None
        return n

    def close(self) -> None:
        network, self.network = self.network, None
        self.nodes = []
        if network is None:
            return
        if network.notifier is not None:
            with contextlib.suppress(Exception):
                network.notifier.stop(1.0)
        if network.bus is not None:
            with contextlib.suppress(Exception):
                network.bus.shutdown()

    @property
    def is_open(self) -> bool:
        return self.network is not None

    # ------------------------------------------------------------------ start-up

    def _configure(self, node: canopen.RemoteNode) -> None:
        node_id = int(node.id or 0)
        s = self.settings
        sdo = node.sdo
        try:
            sdo.download(0x1017, 0, struct.pack("<H", s.heartbeat_period_ms))
        except canopen.SdoAbortedError as exc:
            log.warning("node %d refused heartbeat period %d ms (abort 0x%08X); using its own",
                        node.id, s.heartbeat_period_ms, exc.code)
        except canopen.SdoCommunicationError as exc:
            raise LinkError(f"node {node.id} does not answer SDO: {exc}") from None
        if not s.configure_pdos:
            return
        self._map_pdo(node, 0x1400, 0x1600, RPDO_COB[0] + node_id, RPDO1_MAP, trans_type=255, timer_ms=0)
        for k, entries in enumerate(TPDO_MAPS):
            self._map_pdo(node, 0x1800 + k, 0x1A00 + k, TPDO_COB[k] + node_id, entries, trans_type=255,
                          timer_ms=s.tpdo_period_ms if k < 2 else s.tpdo_slow_period_ms)

    def _map_pdo(self, node: canopen.RemoteNode, comm: int, mapping: int, cob_id: int,
                 entries: Sequence[tuple[int, int, int]], *, trans_type: int, timer_ms: int) -> None:
        """Write one PDO's mapping (CiA 301 sequence) where the controller allows it.

        A refused comm parameter (read-only on old firmware) is left as the controller has it; a refused mapping is
        accepted only when the read-back already matches ours, else the PDO stays disabled and LinkError says why
        (a traction command in other units than we send must never be enabled).
        """
        sdo = node.sdo
        want = [mapping_entry(*e) for e in entries]
        try:
            try:
                sdo.download(comm, 1, struct.pack("<I", cob_id | 0x80000000))
                comm_writable = True
            except canopen.SdoAbortedError:
                comm_writable = False
            try:
                sdo.download(mapping, 0, b"\x00")
                for j, entry in enumerate(want, start=1):
                    sdo.download(mapping, j, struct.pack("<I", entry))
                sdo.download(mapping, 0, bytes([len(want)]))
            except canopen.SdoAbortedError as exc:
                have = self._read_mapping(node, mapping)
                if have != want:
                    raise LinkError(f"node {node.id} refused the mapping of 0x{mapping:04X} (abort 0x{exc.code:08X}) "
                                    f"and its mapping {[hex(v) for v in have]} differs from {[hex(v) for v in want]}"
                                    ) from None
                log.info("node %d: mapping 0x%04X is fixed but already as needed", node.id, mapping)
            if comm_writable:
                with contextlib.suppress(canopen.SdoAbortedError):
                    sdo.download(comm, 2, bytes([trans_type]))
                if comm >= 0x1800 and timer_ms:
                    with contextlib.suppress(canopen.SdoAbortedError):  # rate may only be settable by CTPS
                        sdo.download(comm, 5, struct.pack("<H", timer_ms))
                sdo.download(comm, 1, struct.pack("<I", cob_id))
        except canopen.SdoCommunicationError as exc:
            raise LinkError(f"node {node.id}: SDO failed while mapping 0x{mapping:04X}: {exc}") from None

    @staticmethod
    def _read_mapping(node: canopen.RemoteNode, mapping: int) -> list[int]:
        try:
            count = node.sdo.upload(mapping, 0)[0]
            return [int.from_bytes(node.sdo.upload(mapping, j)[:4], "little") for j in range(1, count + 1)]
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError):
            return []

    def _wait_alive(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if all(st.heartbeat_state == HEARTBEAT_OPERATIONAL and st.feedback_at is not None for st in self.states):
                return
            time.sleep(0.01)
        silent = [n for n, st in zip(self.settings.node_ids, self.states) if st.heartbeat_at is None]
        stuck = [f"{n} (0x{st.heartbeat_state:02X})" for n, st in zip(self.settings.node_ids, self.states)
                 if st.heartbeat_state is not None and st.heartbeat_state != HEARTBEAT_OPERATIONAL]
        mute = [n for n, st in zip(self.settings.node_ids, self.states) if st.feedback_at is None]
        what = []
        if silent:
            what.append(f"no heartbeat from node(s) {silent}")
        if stuck:
            what.append(f"node(s) {', '.join(stuck)} not OPERATIONAL after NMT start")
        if mute:
            what.append(f"no TPDO feedback from node(s) {mute}")
        raise LinkError(f"{' and '.join(what)} within {timeout_s} s")

    # ------------------------------------------------------------------ frames in (dispatch)

    def _heartbeat_handler(self, i: int):
        state = self.states

        def on_heartbeat(can_id: int, data: bytearray, timestamp: float) -> None:
            st = state[i]
            st.heartbeat_at, st.heartbeat_wall = self.clock(), time.monotonic()
            st.heartbeat_state = data[0] & 0x7F if data else None

        return on_heartbeat

    def _tpdo_handler(self, i: int, k: int):
        layouts = (TPDO1, TPDO2, TPDO3, TPDO4)
        layout = layouts[k]
        field = ("counts", "rpm", "amps_flags", "extra")[k]
        states = self.states

        def on_tpdo(can_id: int, data: bytearray, timestamp: float) -> None:
            st = states[i]
            if len(data) != layout.size:
                st.bad_frames += 1
                return
            setattr(st, field, layout.unpack(data))
            if k == 0:
                st.feedback_at, st.feedback_wall = self.clock(), time.monotonic()

        return on_tpdo

    # ------------------------------------------------------------------ frames out (control thread)

    def send(self, commands: Sequence[MotorCommand]) -> None:
        """Send RPDO1 (traction rpm, steering counts) to every node; raises LinkError when the bus fails."""
        network = self.network
        if network is None:
            raise LinkError("CAN link is closed")
        try:
            for cob, cmd in zip(self._rpdo_ids, commands):
                network.send_message(cob, RPDO1.pack(cmd.traction_rpm, cmd.steer_counts))
                self.frames_sent += 1
        except Exception as exc:
            self.send_errors += 1
            self._error = f"CAN send failed: {type(exc).__name__}: {exc}"
            raise LinkError(self._error) from None

    def feedback(self) -> list[ModuleFeedback]:
        """The latest feedback of each node (module order)."""
        out = []
        for st in self.states:
            (c1, c2), (s1, s2), (a1, a2, ff, fs), (bv, fm1, fm2, _) = st.counts, st.rpm, st.amps_flags, st.extra
            out.append(ModuleFeedback(c1, c2, s1, s2, a1 / 10.0, a2 / 10.0, ff, fs, fm1, fm2, bv / 10.0))
        return out

    def health(self) -> str:
        """'' when the link is usable, else the reason (bus error, heartbeat lost, state not operational, mute)."""
        if self.network is None:
            return "CAN link is closed"
        if self._error:
            return self._error
        notifier = self.network.notifier
        if notifier is not None and notifier.exception is not None:
            return f"CAN bus lost: {type(notifier.exception).__name__}: {notifier.exception}"
        now, wall = self.clock(), time.monotonic()
        s = self.settings
        for node_id, st in zip(s.node_ids, self.states):
            if st.heartbeat_at is None or (now - st.heartbeat_at > s.heartbeat_timeout_s
                                           and wall - st.heartbeat_wall > s.heartbeat_timeout_s):
                return f"node {node_id} heartbeat lost (none for {s.heartbeat_timeout_s} s)"
            if st.heartbeat_state is not None and st.heartbeat_state != HEARTBEAT_OPERATIONAL:
                return f"node {node_id} left OPERATIONAL (heartbeat state 0x{st.heartbeat_state:02X})"
            if st.feedback_at is None or (now - st.feedback_at > s.feedback_timeout_s
                                          and wall - st.feedback_wall > s.feedback_timeout_s):
                return f"node {node_id} feedback (TPDO1) silent for more than {s.feedback_timeout_s} s"
        return ""

    # ------------------------------------------------------------------ SDO commands

    def write_all(self, index: int, sub: int, value: bytes) -> list[str]:
        """Write one object on every node by SDO; returns the per-node failures (empty: all done)."""
        failures = []
        with self._sdo_lock:
            for node_id, node in zip(self.settings.node_ids, list(self.nodes)):
                try:
                    node.sdo.download(index, sub, value)
                except canopen.SdoAbortedError as exc:
                    failures.append(f"node {node_id} refused 0x{index:04X} (abort 0x{exc.code:08X})")
                except Exception as exc:
                    failures.append(f"node {node_id}: {type(exc).__name__}: {exc}")
        if not self.nodes:
            failures.append("CAN link is closed")
        return failures

    def estop(self) -> list[str]:
        """``!EX``: emergency shutdown on every controller (latched until ``release``)."""
        return self.write_all(ESTOP_INDEX, 0, b"\x01")

    def release(self) -> list[str]:
        """``!MG``: release the emergency shutdown on every controller."""
        return self.write_all(RELEASE_INDEX, 0, b"\x01")
