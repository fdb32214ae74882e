"""The CANopen link and the control loop against the simulator's emulated RoboteQ nodes on an in-process bus.

The rig hosts the simulator's RoboteQ node core (services.sim.roboteq) and swerve physics on a python-can
``virtual`` channel, stepping them on wall time in a thread; the drive side is the real link and loop.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Iterator

import can
import pytest

from services.common.robot import RobotSpec
from services.drive.canlink import RPDO1_MAP, TPDO_MAPS, LinkError, LinkSettings, RoboteqLink
from services.drive.config import DriveConfig
from services.drive.kinematics import Twist
from services.drive.loop import DriveLoop, WallTicker
from services.drive.node import build_loop
from services.sim.robot_model import MotorUnits as SimUnits
from services.sim.robot_model import SwerveRobot
from services.sim.roboteq import RoboteqNode, RoboteqSettings
from tests.support.waiting import wait_for_sync

ROBOT = RobotSpec()
_channels = itertools.count()


class Rig:
    """Two emulated controllers driving the simulated chassis, on a virtual CAN channel, in wall time."""

    def __init__(self, channel: str, watchdog_ms: int = 300) -> None:
        self.channel = channel
        self.robot = SwerveRobot([(m.x_m, m.y_m) for m in ROBOT.modules], SimUnits())
        self.nodes = [RoboteqNode(RoboteqSettings(node_id=i + 1, watchdog_ms=watchdog_ms), m.traction, m.steer)
                      for i, m in enumerate(self.robot.modules)]
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.lock = threading.Lock()
        self.rpdo_frames = 0
        self.silent = False  # stop answering and sending (a dead bus segment)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> Rig:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2)
        self.bus.shutdown()

    def _send(self, frames: list[tuple[int, bytes]]) -> None:
        if self.silent:
            return
        for cob, data in frames:
            self.bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))

    def _run(self) -> None:
        t0 = time.monotonic()
        with self.lock:
            for n in self.nodes:
                self._send(n.boot(0.0))
        last = 0.0
        while not self._stop.is_set():
            msg = self.bus.recv(0.0005)
            now = time.monotonic() - t0
            with self.lock:
                if msg is not None and not self.silent:
                    if 0x200 <= msg.arbitration_id < 0x280:
                        self.rpdo_frames += 1
                    for n in self.nodes:
                        self._send(n.on_frame(msg.arbitration_id, bytes(msg.data), now))
                if now - last >= 0.001:
                    self.robot.step(now - last)
                    last = now
                    for n in self.nodes:
                        self._send(n.tick(now))

    def speed(self) -> float:
        return math.hypot(self.robot.vx, self.robot.vy)


@pytest.fixture
def rig() -> Iterator[Rig]:
    with Rig(f"drive_test_{next(_channels)}") as r:
        yield r


def link_settings(rig: Rig, **kw) -> LinkSettings:
    return LinkSettings(interface="virtual", channel=rig.channel, **kw)


def make_loop(rig: Rig, **kw) -> DriveLoop:
    cfg = DriveConfig(can_interface="virtual", can_channel=rig.channel, rate_hz=200.0, spin_s=0.0, **kw)
    return build_loop(ROBOT, cfg, WallTicker(cfg.rate_hz, cfg.spin_s))


def test_link_start_up_maps_pdos_and_reads_feedback(rig: Rig) -> None:
    link = RoboteqLink(link_settings(rig))
    link.open()
    try:
        link.poll()
        assert link.health() == ""
        for n in rig.nodes:
            assert n.state == 0x05  # NMT started
            assert n.rpdos[0].mapping == list(RPDO1_MAP)
            assert [p.mapping for p in n.tpdos] == [list(m) for m in TPDO_MAPS]
        with rig.lock:
            rig.nodes[0].steer.position_counts = rig.nodes[0].steer.target_counts = 51200.0  # a quarter turn
        wait_for_sync(lambda: link.poll() >= 0 and link.feedback()[0].steer_counts == 51200, timeout_s=2)
    finally:
        link.close()


def test_link_open_fails_clearly_without_controllers() -> None:
    link = RoboteqLink(LinkSettings(interface="virtual", channel="drive_test_empty", startup_timeout_s=0.3,
                                    sdo_timeout_s=0.05))
    with pytest.raises(LinkError, match="node 1"):
        link.open()
    assert not link.is_open


def test_loop_drives_and_odometry_follows_the_chassis(rig: Rig) -> None:
    loop = make_loop(rig)
    loop.start()
    try:
        wait_for_sync(lambda: loop.link_ok, timeout_s=5)
        deadline = time.monotonic() + 1.5
        while time.monotonic() < deadline:  # a steady command stream, as nav sends it
            loop.set_command(0.2, 0.0, 0.0)
            time.sleep(0.02)
        assert rig.robot.vx == pytest.approx(0.2, abs=0.01)
        wait_for_sync(lambda: rig.speed() < 1e-3, timeout_s=3)  # cmd_vel stopped: timeout + deceleration
        time.sleep(0.05)
        with rig.lock:
            truth = (rig.robot.x, rig.robot.y, rig.robot.theta)
        pose = loop.odometry.pose
        assert truth[0] > 0.1
        assert math.hypot(pose.x - truth[0], pose.y - truth[1]) < 0.01 * truth[0] + 0.002
        snap = loop.last_snapshot
        assert snap is not None and snap.link_ok and snap.loop_hz > 50
    finally:
        loop.stop()


def test_unchanged_commands_are_refreshed_not_resent_every_cycle(rig: Rig) -> None:
    """RPDO1 is event-driven with an event timer: at rest the 200 Hz loop sends each node one frame per
    ``rpdo_refresh_s`` (not 200 per second), and that keeps the controllers' watchdog fed."""
    loop = make_loop(rig)
    loop.start()
    try:
        wait_for_sync(lambda: loop.link_ok, timeout_s=5)
        cycles_before = loop.stats.cycles
        with rig.lock:
            rig.rpdo_frames = 0
        t0 = time.monotonic()
        wait_for_sync(lambda: loop.stats.cycles - cycles_before >= 200, timeout_s=30)
        with rig.lock:
            frames = rig.rpdo_frames
            tripped = [n.watchdog_tripped for n in rig.nodes]
        elapsed_s = time.monotonic() - t0
        refreshes = len(rig.nodes) * (elapsed_s / loop.settings.rpdo_refresh_s + 2)
        assert 0 < frames <= refreshes < loop.stats.cycles - cycles_before
        assert tripped == [False, False]
    finally:
        loop.stop()


def test_non_finite_commands_never_reach_the_motors(rig: Rig) -> None:
    loop = make_loop(rig)
    loop.start()
    try:
        wait_for_sync(lambda: loop.link_ok, timeout_s=5)
        for bad in [(math.nan, 0.0, 0.0), (0.0, math.inf, 0.0), (0.0, 0.0, -math.inf)]:
            assert not loop.set_command(*bad)
        assert loop.cmd_rejected == 3
        # even a non-finite twist given to the controller directly becomes a stop
        out = loop.controller.command(Twist(math.nan, math.inf, 0.0), 0.01)
        assert all(m.traction_rpm == 0 for m in out.motors)
        time.sleep(0.1)
        assert all(n.commands.get((0x2002, 1), 0) == 0 for n in rig.nodes)
    finally:
        loop.stop()


def test_heartbeat_loss_stops_reports_and_reconnects(rig: Rig) -> None:
    loop = make_loop(rig, reconnect_initial_s=0.05, reconnect_max_s=0.2)
    loop.start()
    try:
        wait_for_sync(lambda: loop.link_ok, timeout_s=5)
        stop_at = time.monotonic() + 0.8
        while time.monotonic() < stop_at:
            loop.set_command(0.0, 0.2, 0.0)
            time.sleep(0.02)
        odom_before = loop.odometry.pose
        rig.silent = True
        wait_for_sync(lambda: not loop.link_ok, timeout_s=2)
        assert "heartbeat" in loop.link_fault or "feedback" in loop.link_fault
        snap = wait_for_sync(lambda: (s := loop.last_snapshot) and not s.link_ok and s, timeout_s=1)
        assert snap.fault and all(m.speed_mps == 0.0 for m in snap.result.modules)
        # the controllers' RWD watchdog stops the motors while the drive cannot reach them
        wait_for_sync(lambda: rig.speed() < 1e-3, timeout_s=3)
        rig.silent = False
        wait_for_sync(lambda: loop.link_ok, timeout_s=5)
        assert loop.reconnects == 1
        pose = loop.odometry.pose
        assert pose.y >= odom_before.y - 1e-6  # odometry continued from where it was
        deadline = time.monotonic() + 0.8
        while time.monotonic() < deadline:  # and it drives again
            loop.set_command(0.0, 0.2, 0.0)
            time.sleep(0.02)
        assert rig.robot.vy > 0.1
    finally:
        loop.stop()


def test_controller_estop_is_taken_over_and_ends_only_by_release(rig: Rig) -> None:
    loop = make_loop(rig)
    loop.start()
    try:
        wait_for_sync(lambda: loop.link_ok, timeout_s=5)
        assert not loop.estopped
        with rig.lock:
            rig.nodes[1]._estop()  # a hardware e-stop on one controller: FF bit 4 without our !EX
        wait_for_sync(lambda: loop.estopped, timeout_s=2, message="the controller's e-stop was not taken over")
        assert loop.flag_fault == ""  # an e-stop is a state, not a fault
        with rig.lock:
            rig.nodes[1]._release()  # the controller lets go on its own: the drive stays e-stopped
        time.sleep(0.2)
        assert loop.estopped
        assert loop.link.estop() == []
        assert all(n.estopped for n in rig.nodes)
        assert loop.link.release() == []
        loop.released()
        assert not any(n.estopped for n in rig.nodes)
        time.sleep(0.3)  # feedback sent before !MG arrived must not e-stop it again
        assert not loop.estopped and loop.flag_fault == ""
    finally:
        loop.stop()


def test_fixed_mapping_is_accepted_only_when_it_already_matches(rig: Rig) -> None:
    from services.sim.roboteq import ABORT_PDO_MAPPING, SdoAbort

    def refuse_mapping(node: RoboteqNode) -> None:
        write = node.write_object

        def fixed(index: int, sub: int, raw: bytes, now_s: float) -> None:
            if index & 0xFF00 in (0x1600, 0x1A00):
                raise SdoAbort(ABORT_PDO_MAPPING)
            write(index, sub, raw, now_s)

        node.write_object = fixed

    with rig.lock:
        for n in rig.nodes:
            refuse_mapping(n)
    # the emulator's fixed TPDOs equal ours, but its RPDO1 carries !G per mille, not !S rpm: refused, clearly
    link = RoboteqLink(link_settings(rig, startup_timeout_s=1.0))
    with pytest.raises(LinkError, match=r"refused the mapping of 0x1600 .* differs"):
        link.open()
    assert not link.is_open
    with rig.lock:
        for n in rig.nodes:
            n.rpdos[0].mapping = list(RPDO1_MAP)  # a controller configured beforehand (Roborun) as we need
    link = RoboteqLink(link_settings(rig, startup_timeout_s=1.0))
    link.open()
    link.close()


def test_sim_ticker_follows_the_clock_and_wall_ticker_wakes_on_poke() -> None:
    from services.drive.loop import SimTicker

    stop = threading.Event()
    sim = SimTicker(100.0)
    out: list[tuple[float, bool]] = []
    t = threading.Thread(target=lambda: [out.append(sim.wait(stop)) for _ in range(3)], daemon=True)
    t.start()
    for stamp in (1.0, 1.005, 1.01, 1.05):  # a 40 ms step: one cycle, re-anchored, counted
        sim.advance(stamp)
        time.sleep(0.05)
    t.join(2)
    assert [round(n, 3) for n, _ in out] == [1.0, 1.01, 1.05] and all(p for _, p in out)
    assert sim.overruns == 1

    wall = WallTicker(10.0, 0.0)
    wall.wait(stop)  # anchors the schedule
    threading.Timer(0.01, wall.poke).start()
    t0 = time.perf_counter()
    _, periodic = wall.wait(stop)
    assert not periodic and time.perf_counter() - t0 < 0.09  # woken by the poke, before the 100 ms deadline


def test_one_odometry_message_per_stamp_when_the_clock_does_not_advance(rig: Rig) -> None:
    """Sim clock steps (50 ms) longer than the publish period (20 ms), and an extra cycle woken by each command at the
    same clock time with newer feedback: every stamp is published once, stamps strictly increase."""
    from services.drive.loop import SimTicker, Snapshot

    cfg = DriveConfig(can_interface="virtual", can_channel=rig.channel, rate_hz=200.0, spin_s=0.0, publish_hz=50.0)
    ticker = SimTicker(cfg.rate_hz)
    loop = build_loop(ROBOT, cfg, ticker)
    published: list[Snapshot] = []
    loop.publish = published.append
    link = loop.link_factory()
    link.open()
    loop.link, loop.link_ok = link, True
    try:
        now = 0.0
        for _ in range(60):
            now += 0.05
            ticker.advance(now)
            loop.set_command(0.3, 0.0, 0.2)
            loop.cycle(now, periodic=True)
            time.sleep(0.01)  # the controllers move and report (wall time): the next cycle reads newer counts
            loop.cycle(now, periodic=False)
    finally:
        loop.link, loop.link_ok = None, False
        link.close()
    stamps = [s.stamp for s in published]
    assert len(stamps) == 60 and all(b > a for a, b in zip(stamps, stamps[1:])), \
        f"{len(stamps) - len(set(stamps))} stamps published more than once"
    assert published[-1].pose[0] > 0.01  # the chassis moved, so a second message per stamp would carry another pose


def test_wall_clock_odometry_is_stamped_on_the_service_clock(rig: Rig) -> None:
    """The loop times itself on perf_counter; its messages carry Unix time, as scans and every other service do."""
    loop = make_loop(rig)
    snap = loop.cycle(loop.ticker.now())
    assert snap is not None and abs(snap.stamp - time.time()) < 1.0


def test_a_simulator_restart_starts_a_new_epoch_in_the_loop(rig: Rig) -> None:
    """The sim clock jumps back to 0: snapshots go on at once and a command from the old run moves nothing."""
    from services.drive.loop import SimTicker

    cfg = DriveConfig(can_interface="virtual", can_channel=rig.channel, rate_hz=100.0, spin_s=0.0)
    ticker = SimTicker(cfg.rate_hz)
    loop = build_loop(ROBOT, cfg, ticker)
    snaps = []
    loop.publish = snaps.append
    loop.link = RoboteqLink(link_settings(rig))
    loop.link.open()
    loop.link_ok = True
    try:
        ticker.advance(24.0)
        loop.set_command(0.2, 0.0, 0.0)
        for k in range(30):  # 0.3 s of the old run: the wheels are commanded to move
            loop.cycle(24.0 + 0.01 * k)
        assert any(m.traction_rpm != 0 for m in snaps[-1].result.motors)
        published = len(snaps)
        ticker.advance(0.01)  # the simulator restarted
        loop.cycle(0.01)
        assert len(snaps) > published, "no snapshot until the new clock catches up with the old publish time"
        for k in range(2, 200):  # 2 s of the new run, no new command: the wheels ramp down to rest
            loop.cycle(0.01 * k)
        assert snaps[-1].stamp < 2.0
        assert all(m.traction_rpm == 0 for m in snaps[-1].result.motors), "the old run's command still drives"
    finally:
        loop.link.close()


def test_the_sim_clock_wakes_the_control_loop_only_when_a_cycle_is_due() -> None:
    """A 100 Hz clock drives a 50 Hz loop: every other tick finds no cycle due and must not wake its thread."""
    from services.drive.loop import SimTicker

    ticker = SimTicker(50.0)
    woken_at: list[float] = []
    notify_all = ticker._cond.notify_all

    def counting_notify_all() -> None:
        woken_at.append(ticker.now())
        notify_all()

    ticker._cond.notify_all = counting_notify_all  # type: ignore[method-assign]
    stop = threading.Event()
    ticker.advance(0.0)  # the first tick wakes the loop
    assert ticker.wait(stop) == (0.0, True)
    for k in range(1, 7):
        ticker.advance(round(k * 0.01, 2))
        if k % 2 == 0:  # a cycle is due at 0.02, 0.04, 0.06 s: the loop runs it
            assert ticker.wait(stop) == (round(k * 0.01, 2), True)
    assert woken_at == [0.0, 0.02, 0.04, 0.06]
    ticker.advance(0.5)  # a clock that jumped back (a restarted simulator) wakes it at once
    ticker.advance(5.0)
    woken_at.clear()
    ticker.advance(1.0)
    assert woken_at == [1.0]
