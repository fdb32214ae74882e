"""The drive service against the simulator (``zagv up --sim --only sim,drive``): accuracy and fault handling.

Commands are streamed on ``cmd_vel`` and timed on the simulator's clock; odometry (``odom``, odom frame) is compared
with ``sim/ground_truth`` (map frame) through poses relative to a common starting instant.
"""

from __future__ import annotations

import math
import os
import signal
import threading
import time

import pytest

from proto import codec
from proto.messages import (
    Clock,
    Empty,
    GroundTruth,
    Odometry,
    Pose2D,
    Reply,
    TeleportRequest,
    Twist2D,
    WheelStates,
)
from services.common.se2 import between, wrap_angle
from tests.support.waiting import wait_for_sync

pytestmark = pytest.mark.integration

SPEED = 4.0  # sim seconds per wall second


class Driver:
    """Test-side robot operator: latest clock, odom, ground truth and wheels; streams cmd_vel on the sim clock."""

    def __init__(self, stack) -> None:  # tests.support.stack.Stack
        self.stack = stack
        self.session = stack.session()
        self.keys = stack.keys
        self.lock = threading.Lock()
        self.sim_now = 0.0
        self.odom: Odometry | None = None
        self.truth: GroundTruth | None = None
        self.wheels: WheelStates | None = None
        self.wheel_log: list[WheelStates] = []
        self.truth_log: list[GroundTruth] = []
        self.path_m = 0.0
        self.sends: list[float] = []
        self._subs = [
            self._sub("clock", Clock, self._on_clock),
            self._sub("odom", Odometry, lambda m: setattr(self, "odom", m)),
            self._sub("sim/ground_truth", GroundTruth, self._on_truth),
            self._sub("wheels", WheelStates, self._on_wheels),
        ]
        self.cmd = self.session.declare_publisher(self.keys("cmd_vel"))
        wait_for_sync(lambda: self.odom is not None and self.truth is not None and self.wheels is not None
                      and self.wheels.link_ok, timeout_s=30, message="drive never reported a live CAN link")

    def _sub(self, name: str, t: type, cb):
        key = self.keys(name)
        return self.session.declare_subscriber(key, lambda s: cb(codec.decode_as(t, s.payload.to_bytes(), key)))

    def _on_clock(self, c: Clock) -> None:
        self.sim_now = max(self.sim_now, c.stamp)

    def _on_truth(self, g: GroundTruth) -> None:
        with self.lock:
            if self.truth is not None:
                self.path_m += math.hypot(g.pose.x - self.truth.pose.x, g.pose.y - self.truth.pose.y)
            self.truth = g
            self.truth_log.append(g)

    def _on_wheels(self, w: WheelStates) -> None:
        with self.lock:
            self.wheels = w
            self.wheel_log.append(w)

    def poses(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(odom pose, true pose) at one instant: waits for an odom message newer than the latest truth."""
        with self.lock:
            truth = self.truth
        assert truth is not None
        wait_for_sync(lambda: self.odom is not None and self.odom.stamp >= truth.stamp, timeout_s=5)
        o = self.odom
        return (o.pose.x, o.pose.y, o.pose.theta), (truth.pose.x, truth.pose.y, truth.pose.theta)

    def send(self, vx: float, vy: float, wz: float) -> None:
        self.cmd.put(codec.encode(Twist2D(vx=vx, vy=vy, wz=wz, stamp=self.sim_now)))

    def drive(self, vx: float, vy: float, wz: float, sim_s: float) -> float:
        """Stream the command for ``sim_s`` sim seconds (every 10 ms wall); returns the sim time of the last one."""
        end = self.sim_now + sim_s
        last = self.sim_now
        deadline = time.monotonic() + sim_s / SPEED * 4 + 10
        while self.sim_now < end:
            last = self.sim_now
            self.send(vx, vy, wz)
            self.sends.append(last)
            time.sleep(0.01)
            assert time.monotonic() < deadline, "the simulator clock stalled"
        return last

    def odom_pose(self) -> tuple[float, float, float]:
        o = self.odom
        return (o.pose.x, o.pose.y, o.pose.theta)

    def forward(self, dist_m: float, gain: float = 1.5, axis: int = 0) -> None:
        """Drive straight along the body's x (axis 0) or y (axis 1) by ``dist_m`` as odometry measures it."""
        start = self.odom_pose()
        deadline = time.monotonic() + dist_m / 0.2 / SPEED * 4 + 20
        while (remaining := dist_m - between(start, self.odom_pose())[axis]) > 0.002:
            v = min(0.2, max(0.01, gain * remaining))
            self.send(v, 0.0, 0.0) if axis == 0 else self.send(0.0, v, 0.0)
            time.sleep(0.01)
            assert time.monotonic() < deadline, "forward() did not arrive"
        self.settle(0.8)

    def turn(self, angle_rad: float, gain: float = 2.0) -> None:
        """Turn in place by ``angle_rad`` as odometry measures it."""
        start = self.odom_pose()
        deadline = time.monotonic() + abs(angle_rad) / 0.5 / SPEED * 4 + 20
        while abs(err := angle_rad - between(start, self.odom_pose())[2]) > 0.002:
            self.send(0.0, 0.0, math.copysign(min(0.5, max(0.02, gain * abs(err))), err))
            time.sleep(0.01)
            assert time.monotonic() < deadline, "turn() did not arrive"
        self.settle(0.8)

    def drive_until(self, vx: float, cond, timeout_s: float = 20.0) -> None:
        """Stream (vx, 0, 0) until ``cond()`` holds."""
        deadline = time.monotonic() + timeout_s
        while not cond():
            assert time.monotonic() < deadline, "the robot did not reach the expected motion"
            self.send(vx, 0.0, 0.0)
            time.sleep(0.01)

    def settle(self, sim_s: float = 1.0) -> None:
        self.drive(0.0, 0.0, 0.0, sim_s)

    def wait_sim(self, sim_s: float) -> None:
        end = self.sim_now + sim_s
        wait_for_sync(lambda: self.sim_now >= end, timeout_s=sim_s / SPEED * 4 + 10)

    def speed(self) -> float:
        t = self.truth.twist
        return math.hypot(t.vx, t.vy)

    def query(self, name: str) -> Reply:
        replies = list(self.session.get(self.keys(name), payload=codec.encode(Empty()), timeout=5.0))
        assert replies and replies[0].ok is not None, f"{name} did not answer"
        return codec.decode_as(Reply, replies[0].ok.payload.to_bytes())

    def teleport(self, x: float, y: float, theta: float) -> None:
        key = self.keys("sim/teleport")
        replies = list(self.session.get(key, payload=codec.encode(TeleportRequest(pose=Pose2D(x=x, y=y,
                                                                                              theta=theta))),
                                        timeout=5.0))
        assert replies and replies[0].ok is not None, "sim/teleport did not answer"
        wait_for_sync(lambda: math.hypot(self.truth.pose.x - x, self.truth.pose.y - y) < 0.01, timeout_s=10,
                      message="the teleport never showed in sim/ground_truth")


def slow_down_s(speeds: list[tuple[float, float]]) -> float | None:
    """Time from the first speed below 0.195 m/s to the first below 0.005 m/s in (stamp, speed) samples; None when
    either never happens."""
    slowing = [t for t, v in speeds if v < 0.195]
    stopped = [t for t, v in speeds if v < 0.005]
    return stopped[0] - slowing[0] if slowing and stopped else None


@pytest.mark.slow
def test_square_sideways_spin_and_cmd_timeout_against_ground_truth(stack_factory) -> None:
    stack = stack_factory(services=["sim", "drive"], world="empty_room", speed=SPEED).start()
    d = Driver(stack)
    d.teleport(-3.0, -3.0, 0.0)
    d.settle(0.5)

    # a square of 2.5 m sides (10 m): forward, then turn in place by 90 degrees, four times
    odom0, true0 = d.poses()
    path0 = d.path_m
    for _ in range(4):
        d.forward(2.5)
        d.turn(math.pi / 2)
        odom, true = d.poses()
        assert not d.truth.collided
        ro, rt = between(odom0, odom), between(true0, true)
        travelled = d.path_m - path0
        err = math.hypot(ro[0] - rt[0], ro[1] - rt[1])
        assert err <= 0.01 * travelled, f"odometry off by {err:.3f} m after {travelled:.2f} m: {ro} vs {rt}"
        assert abs(wrap_angle(ro[2] - rt[2])) < 0.02
    assert d.path_m - path0 > 9.5
    assert d.wheels.slip_residual_mps < 0.02  # slip off: the wheels agree with a rigid body

    # pure sideways: the body moves along its y axis without turning
    odom0, true0 = d.poses()
    d.forward(1.0, axis=1)
    odom, true = d.poses()
    rt, ro = between(true0, true), between(odom0, odom)
    # how far past 1 m it coasts depends on this test's command latency (wall time, machine load), not on the
    # drive: the drive is judged by the odometry agreeing with the truth, and by the motion staying sideways
    assert rt[1] >= 0.98 and abs(rt[0]) < 0.02 and abs(rt[2]) < 0.01
    assert math.hypot(ro[0] - rt[0], ro[1] - rt[1]) <= 0.01 * rt[1] + 0.002

    # turning in place: heading changes, position does not
    odom0, true0 = d.poses()
    d.turn(-1.5)
    odom, true = d.poses()
    rt, ro = between(true0, true), between(odom0, odom)
    # as with the sideways run, how far past -1.5 rad it turns depends on this test's wall-clock command loop at 4x
    # sim speed (0.028 rad at load 25), not on the drive: the drive is judged by odometry agreeing with the truth
    # and by the position staying put
    assert math.hypot(rt[0], rt[1]) < 0.02 and -1.6 < rt[2] < -1.48
    assert abs(ro[2] - rt[2]) < 0.01

    # cmd_vel stops: wheels stop within cmd_timeout + the deceleration the limits need. The test knows the sim time
    # of its last command only within [sent_lo, sent_hi] (clock messages arrive late under load); a stream that
    # stuttered (a gap near cmd_timeout, the test process stalled) cannot be judged and is tried again.
    cmd_timeout, decel = 0.2, 0.2 / 0.5
    for _ in range(5):
        d.sends.clear()
        sent_lo = d.drive(0.2, 0.0, 0.0, 2.0)
        time.sleep(0.02)
        sent_hi = d.sim_now
        d.wait_sim(2.0)
        tail = [t for t in d.sends if t > sent_lo - 1.0]
        around = [w for w in d.wheel_log if sent_lo - 0.5 <= w.stamp <= sent_lo + 1.0]
        steady = all(w.modules[0].speed_cmd_mps >= 0.199 for w in around if w.stamp <= sent_lo)
        smooth = max(b.stamp - a.stamp for a, b in zip(around, around[1:])) <= 0.06  # the drive did not stall
        if max(b - a for a, b in zip(tail, tail[1:])) > 0.1 or not steady or not smooth:
            continue
        ramp = [w.stamp for w in d.wheel_log if w.stamp > sent_lo and w.modules[0].speed_cmd_mps < 0.199]
        assert ramp, "the drive never began to decelerate after cmd_vel ended"
        assert ramp[0] - sent_lo >= cmd_timeout - 0.03, f"deceleration began {ramp[0] - sent_lo:.2f} s after the cmd"
        assert ramp[0] - sent_hi <= cmd_timeout + 0.06, f"deceleration began {ramp[0] - sent_hi:.2f} s after the cmd"
        # a controlled deceleration (not a step to zero), finished in the time the acceleration limit needs. The
        # drive is judged on its own commands and its own timeline (``speed_cmd_mps`` of its wheel states, stamped
        # with its view of the sim clock; ``smooth`` above made sure it did not stall). The robot's ground truth must
        # follow as a ramp, never faster; how much longer it takes is the share of the stand-ins for hardware (a
        # starved simulated CAN bus or simulator takes in the drive's frames late while the physics steps on: the
        # truth took 0.74 s instead of 0.38 s once beside a CPU hog), so it is bounded by the window, not the limit.
        expected = decel * (0.195 - 0.005) / 0.2
        cmd_took = slow_down_s([(w.stamp, abs(w.modules[0].speed_cmd_mps)) for w in d.wheel_log if w.stamp > sent_lo])
        assert cmd_took is not None, "the drive never commanded the wheels to a stop after cmd_vel ended"
        assert expected - 0.1 <= cmd_took <= expected + 0.1, (
            f"the drive took {cmd_took:.2f} s (sim) to ramp its wheel command from 0.195 to 0.005 m/s")
        took = slow_down_s([(g.stamp, math.hypot(g.twist.vx, g.twist.vy)) for g in d.truth_log if g.stamp > sent_lo])
        assert took is not None, "the robot never stopped after cmd_vel ended"
        assert took >= expected - 0.1, f"the robot stopped in {took:.2f} s (sim): a step, not a ramp"
        break
    else:
        pytest.fail("the cmd_vel stream or the drive stuttered in every attempt (machine overloaded)")


def test_drive_killed_controllers_stop_through_their_watchdog(stack_factory) -> None:
    stack = stack_factory(services=["sim", "drive"], world="empty_room", speed=2.0).start()
    d = Driver(stack)
    d.teleport(-3.0, 0.0, 0.0)
    d.drive_until(0.2, lambda: d.speed() > 0.195)
    killed_at = d.sim_now  # a lower bound of the kill's sim time
    mark = stack.line_count()
    with d.lock:
        n_wheels = len(d.wheel_log)
    os.kill(stack.pid("drive"), signal.SIGKILL)
    # keep commanding: only the controllers' RWD watchdog (1 s) can stop the wheels until a new drive is up
    deadline = time.monotonic() + 30
    while d.speed() >= 0.005 and time.monotonic() < deadline:
        d.send(0.2, 0.0, 0.0)
        time.sleep(0.01)
    with d.lock:
        stopped = [g.stamp for g in d.truth_log if g.stamp > killed_at and math.hypot(g.twist.vx, g.twist.vy) < 0.005]
        relinked = [w.stamp for w in d.wheel_log[n_wheels:] if w.link_ok and w.stamp > killed_at + 0.1]
    assert stopped, "the wheels kept turning after the drive died"
    # the stop came from the controllers, before any new drive instance could command them
    assert not relinked or stopped[0] < relinked[0]
    assert stopped[0] - killed_at <= 1.0 + 0.3 + 0.7, f"stopped {stopped[0] - killed_at:.2f} s (sim) after the kill"
    # the supervisor restarts the drive: it reconnects disabled and, with cmd_vel still streaming, does not move
    stack.wait_line(r"^zagv\s+\| started drive \(pid \d+\)", timeout_s=10, after=mark)
    stack.wait_line(r"^drive\s+\| .*restarted: the drive stays disabled", timeout_s=30, after=mark)
    relinked_at = keep_sending_until(d, lambda: d.wheels.link_ok and not d.wheels.enabled, timeout_s=30,
                                     message="the restarted drive never reported itself linked and disabled")
    still_until = relinked_at + 3.0  # sim s of cmd_vel at 0.2 m/s that must not move the robot
    keep_sending_until(d, lambda: d.sim_now >= still_until, timeout_s=30, message="the sim clock stalled")
    with d.lock:
        moved = [g for g in d.truth_log if g.stamp >= stopped[0] and math.hypot(g.twist.vx, g.twist.vy) >= 0.005]
    assert not moved, f"the restarted drive moved without an enable ({len(moved)} samples, first at {moved[0].stamp})"
    assert d.query("drive/enable").ok
    keep_sending_until(d, lambda: d.speed() >= 0.15, timeout_s=30, message="no motion after the explicit enable")


def keep_sending_until(d: Driver, cond, *, timeout_s: float, message: str) -> float:
    """Stream cmd_vel (0.2 m/s forward) until ``cond()``; returns the sim time it held."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, message
        d.send(0.2, 0.0, 0.0)
        time.sleep(0.01)
    return d.sim_now


def test_drive_killed_while_estopped_comes_back_estopped(stack_factory) -> None:
    """A SIGKILL while e-stopped: the new drive takes over the e-stop the controllers hold; only an explicit release
    ends it, and the robot moves only after an explicit enable."""
    stack = stack_factory(services=["sim", "drive"], world="empty_room", speed=2.0).start()
    d = Driver(stack)
    d.teleport(-3.0, 0.0, 0.0)
    d.drive_until(0.2, lambda: d.speed() > 0.15)
    assert d.query("drive/estop").ok
    keep_sending_until(d, lambda: d.wheels.estopped and d.speed() < 0.005, timeout_s=30,
                       message="the e-stop did not stop the robot")
    mark = stack.line_count()
    os.kill(stack.pid("drive"), signal.SIGKILL)
    stack.wait_line(r"^zagv\s+\| started drive \(pid \d+\)", timeout_s=10, after=mark)
    stack.wait_line(r"^drive\s+\| .*hold an e-stop: drive e-stopped until drive/release", timeout_s=30, after=mark)
    keep_sending_until(d, lambda: d.wheels.link_ok and d.wheels.estopped and not d.wheels.enabled, timeout_s=30,
                       message="the restarted drive forgot the e-stop")
    refused = d.query("drive/enable")
    assert not refused.ok and "release" in refused.message
    since = d.sim_now
    released = d.query("drive/release")
    assert released.ok and "!MG" in released.message, released.message
    # released but not enabled: cmd_vel still moves nothing
    until = d.sim_now + 2.0
    keep_sending_until(d, lambda: d.sim_now >= until and not d.wheels.estopped, timeout_s=30,
                       message="the release did not end the e-stop")
    with d.lock:
        assert all(math.hypot(g.twist.vx, g.twist.vy) < 0.005 for g in d.truth_log if g.stamp >= since)
    assert d.query("drive/enable").ok
    keep_sending_until(d, lambda: d.speed() >= 0.15, timeout_s=30, message="no motion after release and enable")


def test_can_bus_restart_fault_stop_reconnect_resume(stack_factory) -> None:
    stack = stack_factory(services=["sim", "drive"], world="empty_room", speed=1.0).start()
    d = Driver(stack)
    d.teleport(-4.0, 0.0, 0.0)
    d.drive_until(0.15, lambda: d.speed() > 0.145)
    odom_before, _ = d.poses()
    n_logged = len(d.wheel_log)
    mark = stack.line_count()
    os.kill(stack.pid("canbus"), signal.SIGKILL)

    fault = None
    stopped = False
    back = False
    deadline = time.monotonic() + 40
    while not back and time.monotonic() < deadline:
        d.send(0.15, 0.0, 0.0)
        time.sleep(0.01)
        with d.lock:
            recent = d.wheel_log[n_logged:]
        faulted = [w for w in recent if not w.link_ok]
        if faulted and fault is None:
            fault = faulted[0].fault
        stopped = stopped or (fault is not None and d.speed() < 0.005)
        back = stopped and d.wheels.link_ok and d.speed() > 0.1
    assert fault, "drive never reported the lost bus in wheels"
    assert stopped, "the wheels did not stop while the bus was down"
    assert back, "drive did not reconnect and resume after the bus came back"
    stack.wait_line(r"^zagv\s+\| started canbus \(pid \d+\)", timeout_s=1, after=mark)
    stack.wait_line(r"^drive\s+\| .*CAN link lost", timeout_s=1, after=mark)
    stack.wait_line(r"^drive\s+\| .*CAN link restored", timeout_s=1, after=mark)
    odom_after, _ = d.poses()
    # odometry continued from where it was (no reset to the origin, no jump)
    assert odom_after[0] > odom_before[0]
    assert math.hypot(odom_after[0] - odom_before[0], odom_after[1] - odom_before[1]) < 3.0


def test_estop_release_disable_enable_queries(stack_factory) -> None:
    stack = stack_factory(services=["sim", "drive"], world="empty_room", speed=2.0).start()
    d = Driver(stack)
    d.teleport(-4.0, 0.0, 0.0)

    def keep_driving_until(cond) -> None:
        d.drive_until(0.1, cond)

    keep_driving_until(lambda: d.speed() > 0.09)
    reply = d.query("drive/estop")
    assert reply.ok and "!EX" in reply.message
    # the controllers latch their emergency stop (FF bit 4) and the wheels stop although cmd_vel keeps coming
    keep_driving_until(lambda: d.wheels.estopped and all(m.fault_flags & 0x10 for m in d.wheels.modules)
                       and d.speed() < 0.005)
    assert d.wheels.fault == ""  # our own e-stop is a state, not a fault
    refused = d.query("drive/enable")
    assert not refused.ok and "release" in refused.message
    assert d.query("drive/release").ok
    keep_driving_until(lambda: not d.wheels.estopped and d.speed() > 0.09)
    assert d.query("drive/disable").ok
    keep_driving_until(lambda: not d.wheels.enabled and d.speed() < 0.005)
    assert d.query("drive/enable").ok
    keep_driving_until(lambda: d.wheels.enabled and d.speed() > 0.09)
