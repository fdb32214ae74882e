"""Synthetic runs for AMCL and SLAM tests and benchmarks in the simulator's world model (services.common.world).

``Laser`` is an LMS111-like scan (270 deg at 0.5 deg, 20 m, Gaussian range noise) ray-cast in a ``World`` (a
built-in world such as ``World.load_builtin("corridor")``, or ``World.from_rectangles``; its ``occupancy_map()`` is
the map AMCL gets); ``route`` walks a piecewise-linear path through poses in small steps; ``Odometry`` integrates
the true body motion with scale errors and noise; ``drive`` feeds AMCL along a route and records its errors.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from services.common.se2 import compose, wrap_angle
from services.common.world import World
from services.localization.amcl import Amcl, AmclParams, select_beams

#: Table 3 goals joined by via points that keep the straight legs inside free space
TABLE3_ROUTE = [
    (0.0, 0.0, 0.0), (3.0, 0.1, 1.57), (3.0, 3.5, 0.0), (13.6, 3.2, -1.0), (24.4, 3.5, 1.57), (26.8, 6.6, 1.0),
    (23.5, 7.0, 1.57), (23.1, 13.4, -1.57), (23.5, 7.0, -2.5), (22.5, 3.3, 3.14), (0.0, 3.2, 2.0),
]


class Laser:
    """An LMS111-like laser in a ``World`` (270 deg at 0.5 deg, 20 m by default): the world's ray casting from the
    laser pose plus Gaussian range noise (m); +inf where nothing is within range."""

    def __init__(self, world: World, *, beams: int = 541, fov_rad: float = math.radians(270.0),
                 range_max: float = 20.0, noise_m: float = 0.012, rng: np.random.Generator | None = None) -> None:
        self.world = world
        self.angle_min = -fov_rad / 2.0
        self.angle_increment = fov_rad / (beams - 1)
        self.angles = self.angle_min + np.arange(beams) * self.angle_increment
        self.range_min, self.range_max = 0.05, range_max
        self.noise_m = noise_m
        self.rng = rng or np.random.default_rng(7)

    def scan(self, pose: tuple[float, float, float], mount: tuple[float, float, float]) -> np.ndarray:
        """float32 ranges of one scan from the laser at ``pose`` ∘ ``mount``."""
        lx, ly, lth = compose(pose, mount)
        first = self.world.raycast(lx, ly, lth + self.angles, self.range_max)
        ranges = first + self.rng.normal(0.0, self.noise_m, size=first.shape)
        ranges[first >= self.range_max] = np.inf
        return ranges.astype(np.float32)


def route(poses: list[tuple[float, float, float]], step_m: float = 0.05, step_rad: float = 0.05
          ) -> Iterator[tuple[float, float, float]]:
    """Yield true poses along straight legs between ``poses``; heading turns linearly (shortest way) on each leg."""
    yield poses[0]
    for (x0, y0, t0), (x1, y1, t1) in zip(poses, poses[1:]):
        dth = wrap_angle(t1 - t0)
        steps = max(1, math.ceil(max(math.hypot(x1 - x0, y1 - y0) / step_m, abs(dth) / step_rad)))
        for i in range(1, steps + 1):
            f = i / steps
            yield (x0 + f * (x1 - x0), y0 + f * (y1 - y0), t0 + f * dth)


class Odometry:
    """Dead reckoning from true poses: body-frame increments scaled (1 + scale error) plus Gaussian noise."""

    def __init__(self, start: tuple[float, float, float], *, scale_error: float = 0.01, noise_frac: float = 0.02,
                 rng: np.random.Generator | None = None) -> None:
        self.pose = (0.0, 0.0, 0.0)
        self._last_true = start
        self.scale = 1.0 + scale_error
        self.noise_frac = noise_frac
        self.rng = rng or np.random.default_rng(11)

    def teleported(self, true_pose: tuple[float, float, float]) -> None:
        """The robot was moved without its wheels turning (kidnapping): odometry does not see the jump."""
        self._last_true = true_pose

    def step(self, true_pose: tuple[float, float, float]) -> tuple[float, float, float]:
        x0, y0, t0 = self._last_true
        x1, y1, t1 = true_pose
        c, s = math.cos(t0), math.sin(t0)
        bx, by = c * (x1 - x0) + s * (y1 - y0), -s * (x1 - x0) + c * (y1 - y0)
        bt = wrap_angle(t1 - t0)
        n = self.rng.normal(0.0, self.noise_frac, size=3)
        bx, by = bx * self.scale * (1 + n[0]), by * self.scale * (1 + n[1])
        bt = bt * self.scale * (1 + n[2])
        self.pose = compose(self.pose, (bx, by, bt))
        self._last_true = true_pose
        return self.pose


@dataclass
class RunResult:
    """Errors of the published map pose (map_odom ∘ odom) against the truth at every scan of a run."""

    errors_xy_m: np.ndarray
    errors_theta_rad: np.ndarray
    distance_m: np.ndarray  # distance travelled before each scan
    updates: int

    @property
    def rms_xy_m(self) -> float:
        return float(np.sqrt(np.mean(self.errors_xy_m ** 2)))

    @property
    def rms_theta_rad(self) -> float:
        return float(np.sqrt(np.mean(self.errors_theta_rad ** 2)))

    def settled_after_m(self, threshold_m: float) -> float | None:
        """Distance after which the error stays below ``threshold_m`` to the end (None: it never settles)."""
        above = np.nonzero(self.errors_xy_m >= threshold_m)[0]
        if above.size == 0:
            return float(self.distance_m[0])
        if above[-1] + 1 >= self.errors_xy_m.size:
            return None
        return float(self.distance_m[above[-1] + 1])


MOUNT = (0.45, 0.0, 0.0)


def drive(amcl: Amcl, world: World, truth: list[tuple[float, float, float]], *, seed: int = 1,
          mount: tuple[float, float, float] = MOUNT, odometry: Odometry | None = None,
          stamps_s: list[float] | None = None) -> RunResult:
    """Feed AMCL one scan per true pose (odometry from the true increments) and record its errors. ``stamps_s``:
    each scan's time (default: ``Amcl.DEFAULT_SCAN_PERIOD_S`` apart)."""
    if stamps_s is not None and len(stamps_s) != len(truth):
        raise ValueError(f"{len(stamps_s)} stamps for {len(truth)} poses")
    laser = Laser(world, rng=np.random.default_rng(seed + 10))
    odom = odometry or Odometry(truth[0], rng=np.random.default_rng(seed + 20))
    params: AmclParams = amcl.params
    exy, eth, dist = [], [], []
    travelled = 0.0
    last = truth[0]
    for i, true in enumerate(truth):
        travelled += math.hypot(true[0] - last[0], true[1] - last[1])
        last = true
        o = odom.step(true)
        beams = select_beams(laser.scan(true, mount), laser.angle_min, laser.angle_increment, laser.range_min,
                             laser.range_max, params)
        amcl.process(o, beams, mount, None if stamps_s is None else stamps_s[i])
        if amcl.map_odom is None:
            continue
        est = compose(amcl.map_odom, o)
        exy.append(math.hypot(est[0] - true[0], est[1] - true[1]))
        eth.append(abs(float(wrap_angle(est[2] - true[2]))))
        dist.append(travelled)
    return RunResult(np.array(exy), np.array(eth), np.array(dist), amcl.updates)
