"""A test-side odometry source for localization tests in the simulator.

The robot is moved by ``sim/teleport`` in small steps (default 4 cm / 0.04 rad every 40 ms, about 1 m/s); the
harness publishes ``odom`` from ``sim/ground_truth`` with a 1 % scale error (a jump over 1 m is a kidnapping: the
wheels did not turn, odometry does not see it). The map pose the stack reports is ``tf/map_odom`` ∘ odom; while
``recording``, each ground-truth sample logs (travelled m, xy error m, |theta error| rad).

Each step waits until ``sim/ground_truth`` shows the robot where it was put before the next one: on a loaded
machine the sim can publish less often than the harness teleports, and odometry interpolated over several jumps
at once would place the scans between them centimetres wrong (a test artefact, not localization's error).
"""

from __future__ import annotations

import asyncio
import math

import numpy as np

from proto.messages import GroundTruth, Odometry, Pose2D, PoseWithCovariance, TeleportRequest, Transform2D
from services.common.node import Node
from services.common.se2 import compose, wrap_angle
from services.localization.synthetic import route

ODOM_SCALE = 1.01
KIDNAP_JUMP_M = 1.0


class TruthOdometryHarness:
    """Odometry from the ground truth, teleport stepping, and the error log."""

    def __init__(self, node: Node, step_m: float = 0.04, step_rad: float = 0.04, step_s: float = 0.04) -> None:
        self.node = node
        self.step_m, self.step_rad, self.step_s = step_m, step_rad, step_s
        self.pub_odom = node.publisher("odom")
        self.odom = (0.0, 0.0, 0.0)
        self.last_truth: tuple[float, float, float] | None = None
        self.map_odom: Transform2D | None = None
        self.pose: PoseWithCovariance | None = None
        self.last_estimate: tuple[float, float, float] | None = None
        self.errors: list[tuple[float, float, float]] = []
        self.travelled_m = 0.0
        self.recording = False
        self._awaited: tuple[float, float, float] | None = None
        self._arrived = asyncio.Event()
        node.subscribe("sim/ground_truth", self.on_truth)
        node.subscribe("tf/map_odom", self.on_tf)
        node.subscribe("pose", self.on_pose)

    def on_tf(self, tf: Transform2D) -> None:
        self.map_odom = tf

    def on_pose(self, pose: PoseWithCovariance) -> None:
        self.pose = pose

    def on_truth(self, gt: GroundTruth) -> None:
        true = (gt.pose.x, gt.pose.y, gt.pose.theta)
        if self.last_truth is not None:
            x0, y0, t0 = self.last_truth
            dx, dy = true[0] - x0, true[1] - y0
            if math.hypot(dx, dy) < KIDNAP_JUMP_M:
                c, s = math.cos(t0), math.sin(t0)
                body = (ODOM_SCALE * (c * dx + s * dy), ODOM_SCALE * (-s * dx + c * dy),
                        float(wrap_angle(true[2] - t0)) * ODOM_SCALE)
                self.odom = compose(self.odom, body)
                self.travelled_m += math.hypot(dx, dy)
        self.last_truth = true
        awaited = self._awaited
        if awaited is not None and math.hypot(true[0] - awaited[0], true[1] - awaited[1]) < 1e-6 and \
                abs(float(wrap_angle(true[2] - awaited[2]))) < 1e-6:
            self._arrived.set()
        self.pub_odom.put(Odometry(stamp=gt.stamp, pose=Pose2D(x=self.odom[0], y=self.odom[1], theta=self.odom[2])))
        if self.map_odom is not None:
            tf = self.map_odom
            est = compose((tf.x, tf.y, tf.theta), self.odom)
            self.last_estimate = est
            if self.recording:
                self.errors.append((self.travelled_m, math.hypot(est[0] - true[0], est[1] - true[1]),
                                    abs(float(wrap_angle(est[2] - true[2])))))

    async def teleport(self, pose: tuple[float, float, float], arrival_timeout_s: float = 10.0) -> None:
        """Move the robot and wait until a ground-truth sample shows it there."""
        self._awaited = pose
        self._arrived.clear()
        request = TeleportRequest(pose=Pose2D(x=pose[0], y=pose[1], theta=pose[2]))
        reply = await self.node.query("sim/teleport", request, timeout_s=10.0)  # generous: a loaded machine
        assert reply.ok, reply.message
        try:
            await asyncio.wait_for(self._arrived.wait(), arrival_timeout_s)
        except TimeoutError:
            raise AssertionError(f"sim/ground_truth did not show the robot at {pose} within "
                                 f"{arrival_timeout_s} s of the teleport; last truth {self.last_truth}") from None
        finally:
            self._awaited = None

    async def drive(self, waypoints: list[tuple[float, float, float]]) -> None:
        for pose in route(waypoints, step_m=self.step_m, step_rad=self.step_rad):
            await self.teleport(pose)
            await asyncio.sleep(self.step_s)

    def take_errors(self) -> np.ndarray:
        """The log since the last call, as an (n, 3) array; the log starts empty again."""
        errors, self.errors = np.array(self.errors, dtype=float).reshape(-1, 3), []
        return errors

    def describe(self) -> str:
        """The last estimate against the last ground truth, for assertion messages."""
        est, true = self.last_estimate, self.last_truth
        if est is None or true is None:
            return "no estimate yet"
        return (f"estimate ({est[0]:.2f}, {est[1]:.2f}, {est[2]:.2f}), "
                f"truth ({true[0]:.2f}, {true[1]:.2f}, {true[2]:.2f})")

    @staticmethod
    def settled_after_m(errors: np.ndarray, threshold_m: float = 0.2) -> float | None:
        """Travel from the first sample after which the error stays below ``threshold_m`` (None: never)."""
        bad = np.nonzero(errors[:, 1] >= threshold_m)[0]
        if bad.size == 0:
            return 0.0
        if bad[-1] + 1 >= len(errors):
            return None
        return float(errors[bad[-1] + 1, 0] - errors[0, 0])
