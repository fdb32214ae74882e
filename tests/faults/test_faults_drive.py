"""cmd_vel and CAN bus faults against ``zagv up --sim --only sim,drive`` (one stack for the module).

NaN/inf and out-of-range commands, a 10 kHz cmd_vel flood, the end of the cmd_vel stream and the loss of the
simulated CAN bus: the wheels never see a non-finite or over-limit command, the robot stops, and the drive
recovers. Times are measured on the simulator's clock (sim s) and on the wall clock (wall s).
"""

from __future__ import annotations

import math
import os
import signal
import time
from collections.abc import Iterator

import pytest

from proto import codec
from proto.messages import Twist2D
from services.common.robot import RobotSpec
from services.launch.stack_process import Stack
from tests.support.waiting import wait_for_sync
from tests.test_drive_sim import Driver

pytestmark = pytest.mark.integration

SPEED = 2.0  # sim s per wall s
LIMITS = RobotSpec()  # Table 2
STILL_MPS = 0.005
#: tolerance on the Table 2 limits for the simulated motors' tracking
LIMIT_TOLERANCE = 1.05


@pytest.fixture(scope="module")
def driver(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Driver]:
    stack = Stack(tmp_path_factory.mktemp("drive_faults"), ["sim", "drive"], world="empty_room", speed=SPEED)
    try:
        stack.start()
        yield Driver(stack)
    finally:
        stack.stop()


def truth_speeds(d: Driver, since: float) -> list[tuple[float, float, float]]:
    with d.lock:
        return [(abs(g.twist.vx), abs(g.twist.vy), abs(g.twist.wz)) for g in d.truth_log if g.stamp >= since]


def module_commands(d: Driver, since: float) -> list[tuple[float, float]]:
    with d.lock:
        return [(m.speed_cmd_mps, m.steer_cmd_rad) for w in d.wheel_log if w.stamp >= since for m in w.modules]


def assert_within_limits(d: Driver, since: float) -> None:
    speeds = truth_speeds(d, since)
    assert speeds, "no ground truth since the faulty commands"
    for vx, vy, wz in speeds:
        assert math.isfinite(vx + vy + wz)
        assert vx <= LIMITS.vx_max_mps * LIMIT_TOLERANCE and vy <= LIMITS.vy_max_mps * LIMIT_TOLERANCE, (vx, vy)
        assert wz <= LIMITS.wz_max_radps * LIMIT_TOLERANCE, wz
    commands = module_commands(d, since)
    assert commands, "no wheel states since the faulty commands"
    for speed, steer in commands:
        assert math.isfinite(speed) and math.isfinite(steer), "a non-finite command reached a motor"
        assert abs(speed) <= LIMITS.wheel_speed_max_mps + 1e-9


def stop_and_time_standstill(d: Driver) -> tuple[float, float]:
    """Stop sending; (sim s, wall s) from the last cmd_vel to ground-truth standstill."""
    last_sim, last_wall = d.sim_now, time.monotonic()
    wait_for_sync(lambda: d.speed() < STILL_MPS and abs(d.truth.twist.wz) < 0.01, timeout_s=20,
                  message="the robot did not stop after cmd_vel ended")
    with d.lock:
        stopped = [g.stamp for g in d.truth_log
                   if g.stamp > last_sim and math.hypot(g.twist.vx, g.twist.vy) < STILL_MPS and abs(g.twist.wz) < 0.01]
    return stopped[0] - last_sim, time.monotonic() - last_wall


def test_nan_inf_and_out_of_range_cmd_vel_never_reach_a_motor(driver: Driver, fault_figures) -> None:
    d = driver
    d.teleport(-3.0, -2.0, 0.0)
    d.settle(0.5)
    start = d.sim_now
    pid = d.stack.pid("drive")
    poison = [(math.nan, 0.0, 0.0), (0.0, math.inf, 0.0), (0.0, 0.0, -math.inf), (math.nan, math.nan, math.nan),
              (math.inf, -math.inf, math.nan)]
    end = d.sim_now + 1.5
    i = 0
    while d.sim_now < end:
        d.send(*poison[i % len(poison)])
        i += 1
        time.sleep(0.005)
    # non-finite commands move nothing
    assert max(math.hypot(vx, vy) for vx, vy, _ in truth_speeds(d, start)) < STILL_MPS
    assert_within_limits(d, start)

    # far out of range: the robot moves, but no faster than Table 2 allows
    start = d.sim_now
    d.drive(50.0, -50.0, 30.0, 2.0)
    assert max(vx for vx, _, _ in truth_speeds(d, start)) > 0.05, "the clamped command did not move the robot"
    assert_within_limits(d, start)
    sim_s, wall_s = stop_and_time_standstill(d)
    fault_figures("last_cmd_vel_to_standstill_sim", sim_s)
    fault_figures("last_cmd_vel_to_standstill_wall", wall_s)
    # cmd timeout (0.2 s) + the deceleration from 0.5 rad/s at 1 rad/s^2 (0.5 s), + slack for the test's view of
    # the sim clock (clock messages arrive late under load)
    assert sim_s <= 0.2 + 0.5 + 0.8
    assert d.stack.pid("drive") == pid


def test_cmd_vel_flood_10khz_for_5s(driver: Driver, fault_figures) -> None:
    d = driver
    d.teleport(-3.0, -2.0, 0.0)
    d.settle(0.5)
    pid = d.stack.pid("drive")
    with d.lock:
        first_wheel = len(d.wheel_log)
    start = d.sim_now
    rate_hz, duration_s = 10_000.0, 5.0
    final = (0.1, 0.05, 0.0)
    sent = 0
    t0 = time.perf_counter()
    for sent in range(int(rate_hz * duration_s)):  # bounded: at most 50 000 messages
        k = sent % 4
        cmd = final if k == 0 else ((-0.1, 0.1, 0.2), (0.2, -0.2, -0.5), (0.0, 0.0, 0.0))[k - 1]
        d.cmd.put(codec.encode(Twist2D(vx=cmd[0], vy=cmd[1], wz=cmd[2], stamp=d.sim_now)))
        ahead = (sent + 1) / rate_hz - (time.perf_counter() - t0)
        if ahead > 0.001:
            time.sleep(ahead)
        if time.perf_counter() - t0 > duration_s + 2.0:
            break
    d.send(*final)
    elapsed = time.perf_counter() - t0
    fault_figures("flood_rate_achieved", (sent + 1) / elapsed, "Hz")
    assert_within_limits(d, start)
    # the drive's loop kept running: wheel states every cycle through the flood
    with d.lock:
        stamps = [w.stamp for w in d.wheel_log[first_wheel:]]
    gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    assert stamps and max(gaps) < 0.5, f"the drive loop stalled for {max(gaps):.2f} sim s during the flood"
    fault_figures("flood_max_wheel_state_gap_sim", max(gaps))
    # the robot follows the last command (streamed on at a normal rate)
    d.drive(*final, 1.5)
    t = d.truth.twist
    assert t.vx == pytest.approx(final[0], abs=0.02) and t.vy == pytest.approx(final[1], abs=0.02)
    assert abs(t.wz) < 0.05
    sim_s, _ = stop_and_time_standstill(d)
    assert sim_s <= 1.0
    assert d.stack.pid("drive") == pid and d.wheels.link_ok


def test_can_bus_dropped_drive_reports_stops_and_recovers(driver: Driver, fault_figures) -> None:
    d = driver
    d.teleport(-3.0, -2.0, 0.0)
    d.drive_until(0.15, lambda: d.speed() > 0.145)
    with d.lock:
        first = len(d.wheel_log)
    mark = d.stack.line_count()
    killed_wall, killed_sim = time.monotonic(), d.sim_now
    os.kill(d.stack.pid("canbus"), signal.SIGKILL)
    fault, stopped_at, back_wall = "", None, None
    deadline = time.monotonic() + 40
    while back_wall is None and time.monotonic() < deadline:
        d.send(0.15, 0.0, 0.0)
        time.sleep(0.01)
        with d.lock:
            recent = d.wheel_log[first:]
        fault = fault or next((w.fault or "link lost" for w in recent if not w.link_ok), "")
        if fault and stopped_at is None and d.speed() < STILL_MPS:
            stopped_at = d.sim_now
        if stopped_at is not None and d.wheels.link_ok:
            back_wall = time.monotonic()
    assert fault, "drive never reported the lost bus in wheels"
    assert stopped_at is not None, "the wheels did not stop while the bus was down"
    assert back_wall is not None, "drive did not reconnect after the bus came back"
    d.stack.wait_line(r"^drive\s+\| .*CAN link lost", timeout_s=2, after=mark)
    fault_figures("can_bus_drop_to_standstill_sim", stopped_at - killed_sim)
    fault_figures("can_bus_recover_wall", back_wall - killed_wall)
    d.drive_until(0.15, lambda: d.speed() > 0.1)  # obeys cmd_vel again
    stop_and_time_standstill(d)
