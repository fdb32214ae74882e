"""The emulated RoboteQ controller's CANopen behaviour (pure core, frames in and out)."""

from __future__ import annotations

import threading

import can
import canopen
import pytest

from services.sim.robot_model import SteerMotor, TractionMotor
from services.sim.roboteq import (
    ABORT_NO_OBJECT,
    ABORT_READ_ONLY,
    FF_ESTOP,
    FM_SAFETY_STOP,
    FS_POWER_OFF,
    NMT_OPERATIONAL,
    NMT_PRE_OPERATIONAL,
    RoboteqNode,
    RoboteqSettings,
)

N = 3


def make(**kw) -> RoboteqNode:
    node = RoboteqNode(RoboteqSettings(node_id=N, **kw), TractionMotor(cpr=4096), SteerMotor(cpr=4096))
    return node


def sdo_write(node: RoboteqNode, index: int, sub: int, value: int, size: int = 4, now: float = 0.0,
              cmd: int | None = None) -> bytes:
    cmd = cmd if cmd is not None else {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
    data = bytes([cmd, index & 0xFF, index >> 8, sub]) + value.to_bytes(size, "little", signed=value < 0) \
        + bytes(4 - size)
    (frame,) = node.on_frame(0x600 + N, data, now)
    assert frame[0] == 0x580 + N
    return frame[1]


def sdo_read(node: RoboteqNode, index: int, sub: int) -> bytes:
    (frame,) = node.on_frame(0x600 + N, bytes([0x40, index & 0xFF, index >> 8, sub, 0, 0, 0, 0]), 0.0)
    return frame[1]


def abort_code(reply: bytes) -> int:
    assert reply[0] == 0x80
    return int.from_bytes(reply[4:8], "little")


def run(node: RoboteqNode, t0: float, t1: float, dt: float = 0.005) -> list[tuple[float, int, bytes]]:
    out = []
    t = t0
    while t < t1 - 1e-9:
        t += dt
        out += [(t, cid, data) for cid, data in node.tick(t)]
        node.traction.step(dt)
        node.steer.step(dt)
    return out


def test_boot_up_then_pre_operational_heartbeat_and_nmt_start() -> None:
    node = make()
    assert node.boot(0.0) == [(0x700 + N, b"\x00")]
    assert node.state == NMT_PRE_OPERATIONAL
    frames = run(node, 0.0, 0.25)
    beats = [(t, d) for t, cid, d in frames if cid == 0x700 + N]
    assert [d for _, d in beats] == [b"\x7f", b"\x7f"]
    assert not [f for f in frames if 0x180 <= f[1] < 0x500], "no PDOs before OPERATIONAL"
    node.on_frame(0x000, bytes([0x01, 0]), 0.25)  # start all
    assert node.state == NMT_OPERATIONAL
    frames = run(node, 0.25, 0.45)
    assert [d for _, cid, d in frames if cid == 0x700 + N] == [b"\x05", b"\x05"]
    tpdo1 = [t for t, cid, _ in frames if cid == 0x180 + N]
    tpdo3 = [t for t, cid, _ in frames if cid == 0x380 + N]
    assert [b - a for a, b in zip(tpdo1, tpdo1[1:])] == pytest.approx([0.02] * (len(tpdo1) - 1), abs=1e-6)
    assert [b - a for a, b in zip(tpdo3, tpdo3[1:])] == pytest.approx([0.1] * (len(tpdo3) - 1), abs=1e-6)
    assert len(tpdo1) >= 9 and len(tpdo3) >= 2
    node.on_frame(0x000, bytes([0x01, N + 1]), 0.5)  # NMT for another node
    node.on_frame(0x000, bytes([0x02, N]), 0.5)
    assert node.state == 0x04
    assert node.on_frame(0x600 + N, bytes([0x40, 0x04, 0x21, 1, 0, 0, 0, 0]), 0.5) == [], "no SDO when STOPPED"
    assert node.on_frame(0x000, bytes([0x81, N]), 0.6) == [(0x700 + N, b"\x00")]


def test_sdo_strict_and_manual_style_frames() -> None:
    node = make()
    node.boot(0.0)
    assert sdo_write(node, 0x2003, 2, 10)[:4] == bytes([0x60, 0x03, 0x20, 0x02])
    reply = sdo_read(node, 0x2104, 2)
    assert reply[0] == 0x43 and int.from_bytes(reply[4:8], "little", signed=True) == 10
    # the manual's frame without e/s bits: "20 03 20 02 0A 00 00 00" loads 10 into the ch2 counter as well
    sdo_write(node, 0x2003, 1, 77, cmd=0x20)
    assert int.from_bytes(sdo_read(node, 0x2104, 1)[4:8], "little", signed=True) == 77
    # manual-style emergency stop "2C 0C 20 00 01"
    sdo_write(node, 0x200C, 0, 1, size=1, cmd=0x2C)
    reply = sdo_read(node, 0x2112, 0)
    assert reply[0] == 0x4B and int.from_bytes(reply[4:6], "little") & FF_ESTOP
    # a shorter value for an S32 object is sign-extended
    sdo_write(node, 0x2002, 1, -300, size=2)
    assert node.traction.target_rpm == 0.0  # still e-stopped
    sdo_write(node, 0x200D, 0, 1, size=1)
    assert node.traction.target_rpm == -300.0
    assert abort_code(sdo_read(node, 0x2222, 0)) == ABORT_NO_OBJECT
    assert abort_code(sdo_write(node, 0x2104, 1, 5)) == ABORT_READ_ONLY
    assert abort_code(sdo_write(node, 0x2104, 9, 5)) == 0x06090011


def test_rpdo1_commands_speed_and_position_only_when_operational() -> None:
    node = make(traction_max_rpm=3000)
    node.boot(0.0)
    payload = (500).to_bytes(4, "little", signed=True) + (-20480).to_bytes(4, "little", signed=True)
    node.on_frame(0x200 + N, payload, 0.0)
    assert node.traction.target_rpm == 0.0 and node.steer.target_counts == 0.0
    node.on_frame(0x000, bytes([0x01, N]), 0.0)
    node.on_frame(0x200 + N, payload, 0.0)
    assert node.traction.target_rpm == 1500.0
    assert node.steer.target_counts == -20480.0
    run(node, 0.0, 0.9)
    assert node.steer.position_counts == -20480.0
    assert node.traction.speed_rpm == pytest.approx(1500.0, abs=1.0)
    # TPDO1 carries the counters, TPDO2 the speeds (little-endian S32 pairs)
    frames = {cid: d for _, cid, d in run(node, 0.9, 1.0)}
    assert int.from_bytes(frames[0x180 + N][4:8], "little", signed=True) == -20480
    assert int.from_bytes(frames[0x280 + N][0:4], "little", signed=True) == 1500
    node.on_frame(0x200 + N, bytes(4) + (-20480).to_bytes(4, "little", signed=True), 1.0)
    frames = {cid: d for _, cid, d in run(node, 1.0, 2.5)}
    counts = int.from_bytes(frames[0x180 + N][0:4], "little", signed=True)
    assert counts == round(node.traction.position_counts) == int.from_bytes(sdo_read(node, 0x2104, 1)[4:8], "little")
    assert counts > 1500 / 60 * 4096 * 0.9


def test_watchdog_stops_motors_and_commands_resume_them() -> None:
    node = make(watchdog_ms=1000)
    node.boot(0.0)
    sdo_write(node, 0x2000, 1, 400, now=0.0)
    sdo_write(node, 0x2001, 2, 300000, now=0.0)  # about 3 s of travel
    run(node, 0.0, 0.99)
    assert node.traction.target_rpm == 1200.0 and not node.watchdog_tripped
    run(node, 0.99, 1.02)
    assert node.watchdog_tripped and node.traction.target_rpm == 0.0
    assert node.steer.target_counts < 300000, "steering holds instead of finishing the move"
    run(node, 1.02, 2.0)
    assert node.traction.speed_rpm == pytest.approx(0.0, abs=0.5)
    sdo_write(node, 0x2000, 1, 100, now=2.0)
    assert node.traction.target_rpm == 300.0


def test_watchdog_off_and_queries_do_not_refresh() -> None:
    node = make(watchdog_ms=0)
    node.boot(0.0)
    sdo_write(node, 0x2000, 1, 400)
    run(node, 0.0, 3.0)
    assert node.traction.target_rpm == 1200.0
    node = make(watchdog_ms=500)
    node.boot(0.0)
    sdo_write(node, 0x2000, 1, 400)
    t = 0.0
    while t < 1.0:
        t += 0.1
        sdo_read(node, 0x2104, 1)
        run(node, t - 0.1, t)
    assert node.watchdog_tripped


def test_estop_release_and_motor_stop_flags() -> None:
    node = make()
    node.boot(0.0)
    sdo_write(node, 0x2000, 1, 500)
    run(node, 0.0, 1.0)
    sdo_write(node, 0x200C, 0, 1, size=1, now=1.0)
    assert node.fault_flags() & FF_ESTOP and node.status_flags() & FS_POWER_OFF
    run(node, 1.0, 1.5)
    assert node.traction.speed_rpm == pytest.approx(0.0, abs=0.5)
    sdo_write(node, 0x2000, 1, 0, now=1.5)
    sdo_write(node, 0x200D, 0, 1, size=1, now=1.5)
    assert node.fault_flags() == 0
    sdo_write(node, 0x2000, 1, 300, now=1.5)
    assert node.traction.target_rpm == 900.0
    sdo_write(node, 0x200E, 0, 1, size=1, now=1.5)
    assert node.traction.target_rpm == 0.0
    assert node.motor_flags(1) & FM_SAFETY_STOP
    sdo_write(node, 0x2000, 1, 300, now=1.6)
    assert node.motor_flags(1) == 0 and node.traction.target_rpm == 900.0


def test_tpdo_remap_by_standard_sequence_and_sync_transmission() -> None:
    node = make()
    node.boot(0.0)
    node.on_frame(0x000, bytes([0x01, 0]), 0.0)
    sdo_write(node, 0x1800, 1, 0x80000180 + N)  # invalidate
    sdo_write(node, 0x1A00, 0, 0, size=1)
    sdo_write(node, 0x1A00, 1, 0x21120010)  # FF, 16 bits
    sdo_write(node, 0x1A00, 2, 0x21040220)  # ch2 counter, 32 bits
    sdo_write(node, 0x1A00, 0, 2, size=1)
    sdo_write(node, 0x1800, 2, 1, size=1)  # every SYNC
    sdo_write(node, 0x1800, 1, 0x180 + N)
    assert int.from_bytes(sdo_read(node, 0x1A00, 2)[4:8], "little") == 0x21040220
    frames = run(node, 0.0, 0.2)
    assert not [f for f in frames if f[1] == 0x180 + N], "SYNC-driven TPDO sent without SYNC"
    node.steer.position_counts = 1234
    (frame,) = [f for f in node.on_frame(0x080, b"", 0.2) if f[0] == 0x180 + N]
    assert frame[1] == (0).to_bytes(2, "little") + (1234).to_bytes(4, "little")
    assert abort_code(sdo_write(node, 0x1A00, 1, 0x99990020)) == 0x06040041


class Bridge:
    """Runs a RoboteqNode on a python-can virtual bus in a thread, for a real canopen master to talk to."""

    def __init__(self, node: RoboteqNode, channel: str) -> None:
        self.node = node
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.t = 0.0

    def _send(self, frames: list[tuple[int, bytes]]) -> None:
        for cid, data in frames:
            self.bus.send(can.Message(arbitration_id=cid, data=data, is_extended_id=False))

    def _run(self) -> None:
        self._send(self.node.boot(0.0))
        while not self.stop.is_set():
            msg = self.bus.recv(0.005)
            if msg is not None:
                self._send(self.node.on_frame(msg.arbitration_id, bytes(msg.data), self.t))
            self.t += 0.005
            self._send(self.node.tick(self.t))

    def __enter__(self) -> Bridge:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join()
        self.bus.shutdown()


def test_python_canopen_master_reads_writes_and_maps_pdos(request) -> None:
    from canopen.objectdictionary import ODArray, ODRecord, ODVariable
    from canopen.objectdictionary import datatypes as dt

    channel = f"roboteq_{request.node.name}"
    od = canopen.ObjectDictionary()

    def var(name: str, index: int, sub: int, typ: int, parent=None):
        v = ODVariable(name, index, sub)
        v.data_type = typ
        v.access_type = "rw"
        if parent is not None:
            parent.add_member(v)
        return v

    for base, kind in ((0x1800, "tx"), (0x1400, "rx")):
        for k in range(4):
            rec = ODRecord(f"{kind} comm {k}", base + k)
            var("count", base + k, 0, dt.UNSIGNED8, rec)
            var("cob", base + k, 1, dt.UNSIGNED32, rec)
            var("type", base + k, 2, dt.UNSIGNED8, rec)
            if kind == "tx":
                var("inhibit", base + k, 3, dt.UNSIGNED16, rec)
                var("timer", base + k, 5, dt.UNSIGNED16, rec)
            od.add_object(rec)
            arr = ODRecord(f"{kind} map {k}", base + 0x200 + k)
            var("count", base + 0x200 + k, 0, dt.UNSIGNED8, arr)
            for s in range(1, 9):
                var(f"e{s}", base + 0x200 + k, s, dt.UNSIGNED32, arr)
            od.add_object(arr)
    for index, typ in ((0x2104, dt.INTEGER32), (0x2000, dt.INTEGER32), (0x2112, dt.UNSIGNED16)):
        arr = ODArray(f"obj {index:x}", index)
        var("n", index, 0, dt.UNSIGNED8, arr)
        var("ch1", index, 1, typ, arr)
        var("ch2", index, 2, typ, arr)
        od.add_object(arr)
    ff = var("FF", 0x2112, 0, dt.UNSIGNED16)
    od.add_object(ff)

    sim = make(tpdo_periods_ms=[20, 0, 0, 0])
    with Bridge(sim, channel), canopen.Network() as net:
        net.connect(interface="virtual", channel=channel)
        node = net.add_node(canopen.RemoteNode(N, od))
        node.sdo.RESPONSE_TIMEOUT = 2.0
        assert node.nmt.wait_for_heartbeat(timeout=3) == "PRE-OPERATIONAL"
        node.sdo[0x2000][1].raw = -250
        assert sim.traction.target_rpm == -750.0
        assert node.sdo[0x2112].raw == 0
        node.tpdo.read()
        assert [(v.index, v.subindex) for v in node.tpdo[1].map] == [(0x2104, 1), (0x2104, 2)]
        assert node.tpdo[1].event_timer == 20
        node.tpdo[1].clear()
        node.tpdo[1].add_variable(0x2104, 2)
        node.tpdo[1].add_variable(0x2112)
        node.tpdo[1].trans_type = 255
        node.tpdo[1].event_timer = 10
        node.tpdo[1].enabled = True
        node.tpdo[1].save()
        assert sim.tpdos[0].mapping == [(0x2104, 2, 32), (0x2112, 0, 16)]
        node.nmt.state = "OPERATIONAL"
        sim.steer.position_counts = 4321
        node.tpdo[1].wait_for_reception(timeout=2)
        assert node.tpdo[1]["obj 2104.ch2"].raw == 4321


def test_rpdo_remapped_to_rpm_speed_and_counters_wrap() -> None:
    node = make()
    node.boot(0.0)
    sdo_write(node, 0x1400, 1, 0x80000200 + N)
    sdo_write(node, 0x1600, 0, 0, size=1)
    sdo_write(node, 0x1600, 1, 0x20020120)  # !S ch1, rpm
    sdo_write(node, 0x1600, 2, 0x20010220)  # !P ch2, counts
    sdo_write(node, 0x1600, 0, 2, size=1)
    sdo_write(node, 0x1400, 1, 0x200 + N)
    node.on_frame(0x000, bytes([0x01, N]), 0.0)
    node.on_frame(0x200 + N, (-1234).to_bytes(4, "little", signed=True) + (777).to_bytes(4, "little"), 0.0)
    assert node.traction.target_rpm == -1234.0 and node.steer.target_counts == 777.0
    node.traction.position_counts = 2**31 + 5.0
    assert node.counter(1) == -(2**31) + 5
    assert int.from_bytes(sdo_read(node, 0x2104, 1)[4:8], "little", signed=True) == -(2**31) + 5


def test_steering_limit_clamps_the_target_and_flags_it() -> None:
    from services.sim.roboteq import FM_FORWARD_LIMIT, FM_REVERSE_LIMIT

    node = make(steer_limit_counts=100000)
    node.boot(0.0)
    sdo_write(node, 0x2001, 2, 150000)
    assert node.steer.target_counts == 100000.0 and node.motor_flags(2) & FM_FORWARD_LIMIT
    sdo_write(node, 0x2001, 2, -150000)
    assert node.steer.target_counts == -100000.0 and node.motor_flags(2) & FM_REVERSE_LIMIT
    sdo_write(node, 0x2001, 2, 5000)
    assert node.motor_flags(2) == 0
