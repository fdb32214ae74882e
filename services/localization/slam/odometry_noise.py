"""Seeded corruption of a log's odometry, to test SLAM against robots with bad odometry.

The odometry increments u_k = x_{k-1}⁻¹ ⊕ x_k are rewritten and re-integrated (x'_k = x'_{k-1} ⊕ u'_k):
- wheel scale error: the translation of u_k is multiplied by ``1 + scale_error`` (one value per run, its sign drawn
  from the seed, so ±``scale_error``);
- heading drift: the rotation of u_k gains ``drift_rad_per_m · ‖t_k‖`` (a constant bias per metre driven, sign drawn
  from the seed);
- white noise: N(0, ``noise_xy_per_m · ‖t_k‖``) on each translation axis and N(0, ``noise_theta_per_m · ‖t_k‖``)
  on the rotation;
- random jumps: after every exponentially distributed stretch of mean ``jump_every_m`` metres driven, one increment
  gains a uniform jump of up to ``jump_xy_m`` in each translation axis and ``jump_theta_rad`` in rotation (a wheel
  slip or an odometry glitch);
- rotation errors, which the terms above leave out because they grow with distance only: a turn scale error (the
  rotation of u_k multiplied by ``1 + rot_scale_error``, sign drawn from the seed: a wrong track width, wheels that
  slip in turns) and white noise N(0, ``noise_theta_per_rad · |Δθ_k|``), the α1 term of the odometry motion model
  (Thrun et al., Probabilistic Robotics, 5.4). Turning on the spot then costs heading as well. These are drawn
  from a stream of their own, so the other terms of a seed do not change when they are added.
The scans and stamps are unchanged. ``OdometryNoise.degraded()`` is the setting the acceptance tests use.
"""

from __future__ import annotations

import math

import msgspec
import numpy as np

from services.common.se2 import between, compose

from .logs import LaserLog, LaserScanRecord


class OdometryNoise(msgspec.Struct, forbid_unknown_fields=True):
    """Parameters of ``corrupt_odometry`` (all zero = unchanged odometry)."""

    seed: int = 0
    scale_error: float = 0.0
    drift_rad_per_m: float = 0.0
    noise_xy_per_m: float = 0.0
    noise_theta_per_m: float = 0.0
    jump_every_m: float = 0.0
    jump_xy_m: float = 0.0
    jump_theta_rad: float = 0.0
    rot_scale_error: float = 0.0
    noise_theta_per_rad: float = 0.0

    @classmethod
    def degraded(cls, seed: int = 1) -> OdometryNoise:
        """Wheel scale ±5 %, heading drift 2°/m, 2 %/m and 0.5°/m white noise, a jump of up to 0.3 m and 5° every
        50 m on average."""
        return cls(seed=seed, scale_error=0.05, drift_rad_per_m=math.radians(2.0), noise_xy_per_m=0.02,
                   noise_theta_per_m=math.radians(0.5), jump_every_m=50.0, jump_xy_m=0.3,
                   jump_theta_rad=math.radians(5.0))

    @classmethod
    def for_reference(cls, seed: int = 1) -> OdometryNoise:
        """Odometry for a log whose poses are a corrected trajectory: wheel scale ±3 %, heading drift 0.5°/m,
        2 %/m and 0.5°/m white noise, no jumps."""
        return cls(seed=seed, scale_error=0.03, drift_rad_per_m=math.radians(0.5), noise_xy_per_m=0.02,
                   noise_theta_per_m=math.radians(0.5))

    @classmethod
    def turning(cls, seed: int = 1) -> OdometryNoise:
        """``degraded`` and rotation errors on top: turns scaled by ±8 % and 0.05 rad/rad white noise on each
        rotation (turning on the spot drifts, as on a robot whose track width is off)."""
        return msgspec.structs.replace(cls.degraded(seed), rot_scale_error=0.08, noise_theta_per_rad=0.05)

    def describe(self) -> str:
        return (f"seed {self.seed}: wheel scale ±{100 * self.scale_error:g} %, heading drift "
                f"{math.degrees(self.drift_rad_per_m):g}°/m, noise {100 * self.noise_xy_per_m:g} %/m and "
                f"{math.degrees(self.noise_theta_per_m):g}°/m"
                + (f", jumps ≤ {self.jump_xy_m:g} m / {math.degrees(self.jump_theta_rad):g}° every "
                   f"{self.jump_every_m:g} m" if self.jump_every_m > 0 else ", no jumps")
                + (f", turns scaled ±{100 * self.rot_scale_error:g} % with {self.noise_theta_per_rad:g} rad/rad "
                   "noise" if self.rot_scale_error or self.noise_theta_per_rad else ""))


def corrupt_poses(poses: np.ndarray, noise: OdometryNoise) -> tuple[np.ndarray, int]:
    """Corrupted odometry poses (N, 3) for poses (N, 3) in time order, and the number of jumps added."""
    poses = np.asarray(poses, float)
    if len(poses) < 2:
        return poses.copy(), 0
    rng = np.random.default_rng(noise.seed)
    scale = 1.0 + noise.scale_error * rng.choice([-1.0, 1.0])
    drift = noise.drift_rad_per_m * rng.choice([-1.0, 1.0])
    steps = between(poses[:-1], poses[1:])
    turn = steps[:, 2].copy()  # each increment's true rotation, in (-π, π]
    dist = np.hypot(steps[:, 0], steps[:, 1])
    steps[:, :2] *= scale
    steps[:, 2] += drift * dist
    steps[:, :2] += rng.normal(0.0, 1.0, (len(steps), 2)) * (noise.noise_xy_per_m * dist)[:, None]
    steps[:, 2] += rng.normal(0.0, 1.0, len(steps)) * noise.noise_theta_per_m * dist
    jumps = 0
    if noise.jump_every_m > 0:
        travelled = np.cumsum(dist)
        at = rng.exponential(noise.jump_every_m)
        while at < travelled[-1]:
            k = int(np.searchsorted(travelled, at))
            steps[k, :2] += rng.uniform(-noise.jump_xy_m, noise.jump_xy_m, 2)
            steps[k, 2] += rng.uniform(-noise.jump_theta_rad, noise.jump_theta_rad)
            jumps += 1
            at += rng.exponential(noise.jump_every_m)
    if noise.rot_scale_error or noise.noise_theta_per_rad:
        turn_rng = np.random.default_rng([noise.seed, 1])  # a stream of its own: the terms above stay as they were
        turn_scale = noise.rot_scale_error * turn_rng.choice([-1.0, 1.0])
        steps[:, 2] += turn_scale * turn
        steps[:, 2] += turn_rng.normal(0.0, 1.0, len(steps)) * noise.noise_theta_per_rad * np.abs(turn)
    out = np.empty_like(poses)
    out[0] = poses[0]
    for k, step in enumerate(steps):
        out[k + 1] = compose(out[k], step)
    return out, jumps


def corrupt_odometry(log: LaserLog, noise: OdometryNoise) -> tuple[LaserLog, int]:
    """``log`` with its odometry corrupted by ``noise`` (scans, stamps and mount unchanged), and the jump count."""
    odom, jumps = corrupt_poses(np.array([s.odom_pose for s in log.scans]), noise)
    scans = [LaserScanRecord(s.stamp_s, s.ranges_m, s.angles_rad, odom[k], s.min_range_m, s.max_range_m)
             for k, s in enumerate(log.scans)]
    return LaserLog(scans, log.sensor_pose.copy(), log.stamps_from_log), jumps
