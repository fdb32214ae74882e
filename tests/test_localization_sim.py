"""Localization acceptance in the simulator: sim (world, emulated LMS111) + lidar + localization via ``zagv up``.

The robot is moved along the route by ``sim/teleport`` in small steps (4 cm / 0.04 rad every 40 ms, about 1 m/s),
and the test publishes ``odom`` from ``sim/ground_truth`` with a 1 % scale error (a kidnapping jump is not seen by
odometry). The map pose the stack reports is ``tf/map_odom`` ∘ odom, compared with the ground truth at each
ground-truth sample.
"""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from proto.messages import Empty, GroundTruth, Odometry, Twist2D
from services.common.node import Node
from services.common.se2 import compose, wrap_angle
from services.localization.synthetic import TABLE3_ROUTE
from tests.support.stats import service_stats
from tests.support.truth_odometry import TruthOdometryHarness
from tests.support.waiting import wait_for

pytestmark = [pytest.mark.integration, pytest.mark.slow]


async def test_amcl_in_the_simulated_corridor(stack_factory):
    stack = stack_factory(services=["sim", "lidar", "localization"], world="corridor").start()
    node = Node("loc-test", stack.session(), stack.keys)
    h = TruthOdometryHarness(node)
    try:
        await wait_for(lambda: h.map_odom is not None, timeout_s=30, message="no tf/map_odom from localization")
        # 1. tracking along the Table 3 route (start, goals 1 to 4)
        h.recording = True
        await h.drive(TABLE3_ROUTE[:5])
        errors = h.take_errors()
        rms_xy = float(np.sqrt(np.mean(errors[:, 1] ** 2)))
        rms_theta = float(np.sqrt(np.mean(errors[:, 2] ** 2)))
        stats = service_stats(stack, "localization")
        print(f"\nsim corridor, {errors[-1, 0] - errors[0, 0]:.1f} m to goal 4: AMCL RMS error {rms_xy:.4f} m, "
              f"{rms_theta:.4f} rad (max {errors[:, 1].max():.3f} m); localization {stats}")
        assert errors[-1, 0] - errors[0, 0] > 25.0
        assert rms_xy <= 0.03 and rms_theta <= 0.02

        # 2. global localization from uniform particles at goal 4 (where corridor and hall meet), then 5 m of travel
        reply = await node.query("localization/global", Empty())
        assert reply.ok, reply.message
        await h.drive([(24.4, 3.5, 1.57), (24.0, 7.0, 1.57), (23.8, 8.5, 1.57)])
        errors = h.take_errors()
        settled = h.settled_after_m(errors)
        print(f"global localization: error < 0.2 m after {settled} m of travel; final {errors[-1, 1]:.3f} m "
              f"after {errors[-1, 0] - errors[0, 0]:.1f} m")
        assert settled is not None and settled <= 5.0, h.describe()

        # 3. kidnapping: from the north corridor 5 m back into the hall, unseen by odometry; then 10 m of travel
        await h.drive([(23.8, 8.5, 1.57), (23.5, 12.5, 1.57)])
        await h.teleport((23.5, 7.5, 1.57))
        await asyncio.sleep(0.5)
        h.take_errors()
        await h.drive([(23.5, 7.5, 1.57), (23.3, 3.3, 3.14), (17.3, 3.3, 3.14)])
        errors = h.take_errors()
        settled = h.settled_after_m(errors)
        print(f"kidnapped 5 m: error < 0.2 m after {settled} m of travel; final {errors[-1, 1]:.3f} m")
        assert errors[-1, 0] - errors[0, 0] >= 9.5
        assert settled is not None and settled <= 10.0, h.describe()
    finally:
        node.close()


def drive_available() -> bool:
    import importlib.util

    return importlib.util.find_spec("services.drive.__main__") is not None


@pytest.mark.skipif(not drive_available(), reason="needs the drive service")
async def test_amcl_tracks_the_robot_driven_along_the_table3_route(stack_factory):
    """sim + drive + lidar + localization: the robot is driven by cmd_vel (a test-side P controller on the ground
    truth, within the Table 2 limits) from the start through goals 1, 2 and 3; odometry is the drive's."""
    from services.common.robot import RobotSpec
    from services.localization.odom_history import OdomHistory

    stack = stack_factory(services=["sim", "drive", "lidar", "localization"], world="corridor", speed=2.0).start()
    node = Node("loc-drive-test", stack.session(), stack.keys)
    spec = RobotSpec()
    odom = OdomHistory(keep_s=5.0)
    state: dict = {"tf": None, "truth": None}
    errors: list[tuple[float, float]] = []

    def on_odom(msg: Odometry) -> None:
        odom.add(msg.stamp, (msg.pose.x, msg.pose.y, msg.pose.theta))

    def on_truth(gt: GroundTruth) -> None:
        state["truth"] = gt
        tf = state["tf"]
        o = odom.at(gt.stamp, 0.05)
        if tf is None or o is None:
            return
        est = compose((tf.x, tf.y, tf.theta), o)
        errors.append((math.hypot(est[0] - gt.pose.x, est[1] - gt.pose.y),
                       abs(float(wrap_angle(est[2] - gt.pose.theta)))))

    node.subscribe("odom", on_odom)
    node.subscribe("sim/ground_truth", on_truth)
    node.subscribe("tf/map_odom", lambda tf: state.__setitem__("tf", tf))
    cmd = node.publisher("cmd_vel")
    try:
        await wait_for(lambda: state["tf"] is not None and state["truth"] is not None, timeout_s=30,
                       message="no tf/map_odom or ground truth")
        errors.clear()
        for goal in TABLE3_ROUTE[1:4]:
            deadline = asyncio.get_running_loop().time() + 240.0
            while True:
                p = state["truth"].pose
                dx, dy = goal[0] - p.x, goal[1] - p.y
                dth = float(wrap_angle(goal[2] - p.theta))
                if math.hypot(dx, dy) < 0.05 and abs(dth) < 0.05:
                    break
                assert asyncio.get_running_loop().time() < deadline, (
                    f"goal {goal} not reached: at ({p.x:.2f}, {p.y:.2f}, {p.theta:.2f}), "
                    f"sim time {state['truth'].stamp:.1f} s")
                c, s = math.cos(p.theta), math.sin(p.theta)
                bx, by = c * dx + s * dy, -s * dx + c * dy  # the error in the body frame
                # one scale for both axes keeps the direction of travel (per-axis clamping would curve the path)
                scale = min(1.0, (spec.vx_max_mps if bx > 0 else -spec.vx_min_mps) / max(abs(bx), 1e-9),
                            spec.vy_max_mps / max(abs(by), 1e-9))
                vx, vy, wz = spec.twist_limits().clamp(scale * bx, scale * by, 1.5 * dth)
                cmd.put(Twist2D(vx=vx, vy=vy, wz=wz))
                await asyncio.sleep(0.05)
        cmd.put(Twist2D())
        e = np.array(errors)
        rms_xy, rms_theta = float(np.sqrt(np.mean(e[:, 0] ** 2))), float(np.sqrt(np.mean(e[:, 1] ** 2)))
        print(f"\ndriven start -> goal 3: AMCL RMS error {rms_xy:.4f} m, {rms_theta:.4f} rad over {len(e)} samples")
        assert not state["truth"].collided
        assert rms_xy <= 0.03 and rms_theta <= 0.02
    finally:
        node.close()
