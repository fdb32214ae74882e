"""Swerve kinematics as pure, immutable values (docs/architecture.md; WPILib's SwerveDriveKinematics is the model).

Module i sits at (x_i, y_i) in base_link. For a body twist (vx, vy, wz):

- inverse:  wheel velocity vector u_i = (vx - wz*y_i, vy + wz*x_i); speed |u_i|, angle atan2(u_i).
- forward:  B (2N x 3) stacks the rows [1 0 -y_i; 0 1 x_i]; A (2N) stacks the measured (v_i cos a_i, v_i sin a_i);
            the least-squares twist is pinv(B) @ A (the paper's (B B^T)^-1 is singular; pinv is (B^T B)^-1 B^T).
            The residual |B t - A| (m/s) is zero for a rigid body: a slip / encoder-fault indicator.

Module optimisation (what production swerve code adds): steer by at most 90 deg and reverse the speed instead,
within the steering angle limits; keep the last angle when the speed is about zero; scale all speeds together
when one exceeds the wheel-speed limit; scale a module's speed by cos(steering error) while it is still turning.

Angles here are unwrapped (absolute) steering angles in rad: the steering motor's position is absolute, so
a module may be commanded to any angle inside [min_angle, max_angle], not only to (-pi, pi].

For N = 2 modules the maths is a handful of floats, so it is written in plain Python (numpy's per-call
overhead would dominate); numpy is only used once to build the pseudo-inverse.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class Twist:
    """A body twist: vx, vy in m/s, wz in rad/s (base_link)."""

    vx: float = 0.0
    vy: float = 0.0
    wz: float = 0.0

    def is_finite(self) -> bool:
        return math.isfinite(self.vx) and math.isfinite(self.vy) and math.isfinite(self.wz)

    def __mul__(self, k: float) -> Twist:
        return Twist(self.vx * k, self.vy * k, self.wz * k)


ZERO_TWIST = Twist()


@dataclass(frozen=True, slots=True)
class ModuleState:
    """One module's wheel speed (m/s, signed) and absolute steering angle (rad)."""

    speed_mps: float = 0.0
    angle_rad: float = 0.0

    @property
    def velocity(self) -> tuple[float, float]:
        """The wheel's velocity vector (m/s) in base_link."""
        return (self.speed_mps * math.cos(self.angle_rad), self.speed_mps * math.sin(self.angle_rad))


@dataclass(frozen=True, slots=True)
class ForwardResult:
    """Least-squares body twist from module states, and the rigid-body residual |B t - A| in m/s."""

    twist: Twist
    residual_mps: float


class SwerveKinematics:
    """Inverse and least-squares forward kinematics for modules at ``positions`` [(x_i, y_i) m] in base_link."""

    __slots__ = ("positions", "_pinv", "_n")

    def __init__(self, positions: Sequence[tuple[float, float]]) -> None:
        if len(positions) < 2:
            raise ValueError(f"swerve kinematics needs at least 2 modules, got {len(positions)}")
        pts = [(float(x), float(y)) for x, y in positions]
        if not all(math.isfinite(x) and math.isfinite(y) for x, y in pts):
            raise ValueError(f"module positions must be finite, got {pts}")
        b = np.zeros((2 * len(pts), 3))
        for i, (x, y) in enumerate(pts):
            b[2 * i] = (1.0, 0.0, -y)
            b[2 * i + 1] = (0.0, 1.0, x)
        if np.linalg.matrix_rank(b) < 3:
            raise ValueError(f"module positions {pts} do not determine a rotation (all at one point)")
        self.positions: tuple[tuple[float, float], ...] = tuple(pts)
        self._pinv: tuple[tuple[float, ...], ...] = tuple(tuple(float(v) for v in row) for row in np.linalg.pinv(b))
        self._n = len(pts)

    @property
    def module_count(self) -> int:
        return self._n

    def module_velocities(self, t: Twist) -> list[tuple[float, float]]:
        """Wheel velocity vectors u_i = (vx - wz*y_i, vy + wz*x_i) in m/s."""
        return [(t.vx - t.wz * y, t.vy + t.wz * x) for x, y in self.positions]

    def to_module_states(self, t: Twist, previous: Sequence[ModuleState] | None = None,
                         hold_speed_mps: float = 0.0) -> tuple[ModuleState, ...]:
        """Inverse kinematics. A module slower than ``hold_speed_mps`` keeps its previous angle with speed 0."""
        out = []
        for i, (ux, uy) in enumerate(self.module_velocities(t)):
            speed = math.hypot(ux, uy)
            if speed <= hold_speed_mps:
                out.append(ModuleState(0.0, previous[i].angle_rad if previous is not None else 0.0))
            else:
                out.append(ModuleState(speed, math.atan2(uy, ux)))
        return tuple(out)

    def to_twist(self, states: Sequence[ModuleState]) -> ForwardResult:
        """Forward kinematics by least squares: t = pinv(B) @ A, with the residual |B t - A| (m/s)."""
        if len(states) != self._n:
            raise ValueError(f"expected {self._n} module states, got {len(states)}")
        a: list[float] = []
        for s in states:
            a.extend(s.velocity)
        return self._solve(a)

    def to_twist_from_vectors(self, vectors: Sequence[tuple[float, float]]) -> ForwardResult:
        """Forward kinematics from wheel velocity (or displacement) vectors, one (x, y) per module."""
        a = [c for v in vectors for c in v]
        return self._solve(a)

    def _solve(self, a: list[float]) -> ForwardResult:
        p = self._pinv
        vx = sum(p[0][k] * a[k] for k in range(len(a)))
        vy = sum(p[1][k] * a[k] for k in range(len(a)))
        wz = sum(p[2][k] * a[k] for k in range(len(a)))
        r2 = 0.0
        for i, (x, y) in enumerate(self.positions):
            ex = vx - wz * y - a[2 * i]
            ey = vy + wz * x - a[2 * i + 1]
            r2 += ex * ex + ey * ey
        return ForwardResult(Twist(vx, vy, wz), math.sqrt(r2))


# --------------------------------------------------------------------------- module optimisation


@dataclass(frozen=True, slots=True)
class SteeringLimits:
    """Absolute steering angle range [min_rad, max_rad]; it must span at least pi so every direction fits."""

    min_rad: float = -2.0 * math.pi
    max_rad: float = 2.0 * math.pi

    def __post_init__(self) -> None:
        if not self.max_rad - self.min_rad >= math.pi:
            raise ValueError(f"steering range [{self.min_rad}, {self.max_rad}] rad must span at least pi")


def optimize(target: ModuleState, current_angle_rad: float, limits: SteeringLimits = SteeringLimits()) -> ModuleState:
    """The equivalent state (angle + k*pi, speed * (-1)^k) inside ``limits`` nearest to ``current_angle_rad``.

    Without limits this steers by at most 90 deg (reversing the speed instead). The velocity vector is unchanged.
    """
    a, v = target.angle_rad, target.speed_mps
    # candidates a + k*pi, k integer, nearest to the current angle first
    k0 = round((current_angle_rad - a) / math.pi)
    best: ModuleState | None = None
    best_err = math.inf
    for k in (k0 - 1, k0, k0 + 1):
        cand = a + k * math.pi
        if cand < limits.min_rad or cand > limits.max_rad:
            continue
        err = abs(cand - current_angle_rad)
        if err < best_err:
            best_err = err
            best = ModuleState(-v if k % 2 else v, cand)
    if best is None:
        # the current angle is far outside the limits (e.g. a manual move): take the in-range candidate nearest to it
        ks = range(math.ceil((limits.min_rad - a) / math.pi), math.floor((limits.max_rad - a) / math.pi) + 1)
        k = min(ks, key=lambda k: abs(a + k * math.pi - current_angle_rad))
        best = ModuleState(-v if k % 2 else v, a + k * math.pi)
    return best


def cosine_scale(target: ModuleState, measured_angle_rad: float) -> ModuleState:
    """Scale the speed by cos(steering error), never below 0: no push sideways while the module still turns."""
    return ModuleState(target.speed_mps * max(0.0, math.cos(target.angle_rad - measured_angle_rad)), target.angle_rad)


def desaturate(states: Sequence[ModuleState], max_speed_mps: float) -> tuple[ModuleState, ...]:
    """Scale every module's speed by one factor so the fastest runs at ``max_speed_mps`` (keeps the motion's shape)."""
    fastest = max((abs(s.speed_mps) for s in states), default=0.0)
    if fastest <= max_speed_mps or fastest == 0.0:
        return tuple(states)
    k = max_speed_mps / fastest
    return tuple(ModuleState(s.speed_mps * k, s.angle_rad) for s in states)
