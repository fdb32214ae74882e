"""How well the pose is known, per direction: odometry drift grown while driving, shrunk by what the scans pin (core).

The particle cloud's covariance says how the particles disagree, not how far the estimate may be from the truth:
where the scan does not constrain a direction (a long corridor, an open hall with one straight wall in view), the
cloud is resampled onto the pose odometry carried it to and stays a few centimetres wide while the estimate drifts
with the odometry along that direction. This tracker keeps the covariance P (3x3 over x [m], y [m], theta [rad] in
the map frame) an EKF would hold on the same inputs, without estimating a mean:

- motion by the odometry increment (dx, dy, dtheta) in the robot frame (length t = |(dx, dy)|):
  P <- F P F^T + G Q G^T, with F = d(pose')/d(pose) (heading error swings the step: dx'/dtheta = -sin(theta) dx -
  cos(theta) dy, dy'/dtheta = cos(theta) dx - sin(theta) dy), G the robot-to-map rotation, and
  Q = diag(k_xy t, k_xy t, k_th_m t + k_th_rad |dtheta|): random-walk drift whose variance grows with distance;
- a scan at the estimate: P <- (P^-1 + s H)^-1, with H the scan's Gauss-Newton information
  H = sum over inlier beams b of J_b^T J_b / sigma_hit^2, J_b = d d_b / d(x, y, theta) the gradient of the endpoint's
  distance to the map's surfaces (the steeper one-sided difference on the bilinearly interpolated distance field),
  over the filter's subsample of the beams (``information_scale`` s weighs them). A direction no beam constrains gets
  no information: its variance only grows.

This is LOAM's degeneracy test (the smallest eigenvalue of JᵀJ) made a number in metres: ``position_std_m`` is the
standard deviation along the weakest position direction (largest eigenvalue of the marginal xy block), and
``weakest_axis_rad`` its direction in the map frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.localization.refine import beam_rays, interpolated_distance

Pose = tuple[float, float, float]


@dataclass(frozen=True)
class UncertaintyParams:
    """Drift and scan-information weights (see the module docstring)."""

    #: position drift variance per metre driven (m^2/m) along and across: 0.05 m std after 1 m, 0.25 m after 25 m
    #: (the simulated stack's wheel odometry was measured 0.08 to 0.41 m off after legs of 30 to 40 m along one wall)
    drift_xy_m2_per_m: float = 0.05 ** 2
    #: heading drift variance per metre driven (rad^2/m) and per radian turned (rad^2/rad)
    drift_theta_rad2_per_m: float = 0.01 ** 2
    drift_theta_rad2_per_rad: float = 0.02 ** 2
    #: weight of one beam's information. The filter passes its own beam subsample (``max_beams``, 60 of 541), which
    #: already counts a scan as few beams (neighbouring beams share a stretch of wall and its map error)
    information_scale: float = 1.0
    #: a beam counts when its endpoint lies within this of a surface (farther: an outlier, no gradient to trust)
    inlier_m: float = 0.2
    #: finite-difference steps for the Jacobian
    step_m: float = 0.01
    step_rad: float = 0.002
    #: floor on each variance (m^2, rad^2): scan information never claims better than the map's own accuracy
    floor_m2: float = 0.005 ** 2
    floor_rad2: float = 0.002 ** 2


def scan_information(distance_m: np.ndarray, origin: tuple[float, float, float], resolution: float,
                     sigma_hit_m: float, pose: Pose, ranges: np.ndarray, bearings: np.ndarray, mount: Pose,
                     params: UncertaintyParams | None = None) -> np.ndarray:
    """Gauss-Newton information (3x3, unscaled) of one scan at ``pose``: sum of J_b^T J_b / sigma_hit^2 over beams
    whose endpoint lies within ``inlier_m`` of a surface (module docstring)."""
    p = params or UncertaintyParams()
    ranges = np.asarray(ranges, dtype=np.float64)
    bearings = np.asarray(bearings, dtype=np.float64)
    if ranges.size == 0:
        return np.zeros((3, 3))
    steps = np.array([p.step_m, p.step_m, p.step_rad])
    base = np.asarray(pose, dtype=np.float64)
    poses = np.vstack([base] + [base + sign * steps[i] * np.eye(3)[i] for i in range(3) for sign in (1.0, -1.0)])
    lx, ly, ga = beam_rays(poses, bearings, mount)
    ex = lx[:, None] + ranges[None, :] * np.cos(ga)
    ey = ly[:, None] + ranges[None, :] * np.sin(ga)
    d = interpolated_distance(distance_m, origin, resolution, ex, ey, math.nan)  # beyond the map: no gradient
    inlier = (d[0] < p.inlier_m) & np.all(np.isfinite(d), axis=0)
    d = d[:, inlier]
    # one-sided slopes, the steeper kept: an endpoint on a wall sits at the V of the distance (|slope| 1 both ways)
    # or inside a one-cell wall, on the field's zero plateau (flat one way); a central difference halves both
    fwd = np.column_stack([(d[1 + 2 * i] - d[0]) / steps[i] for i in range(3)])
    bwd = np.column_stack([(d[0] - d[2 + 2 * i]) / steps[i] for i in range(3)])
    jac = np.where(np.abs(fwd) >= np.abs(bwd), fwd, bwd)
    return (jac.T @ jac) / (sigma_hit_m ** 2)


def motion_jacobians(theta: float, delta: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """F = d(pose')/d(pose) and G = d(pose')/d(noise in the robot frame) for pose' = pose ⊕ delta."""
    dx, dy, _ = delta
    c, s = math.cos(theta), math.sin(theta)
    f = np.eye(3)
    f[0, 2] = -s * dx - c * dy
    f[1, 2] = c * dx - s * dy
    g = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return f, g


class PoseUncertainty:
    """The tracked covariance P and its summaries (module docstring)."""

    def __init__(self, params: UncertaintyParams | None = None) -> None:
        self.params = params or UncertaintyParams()
        self.covariance = np.diag([1.0, 1.0, 0.1])

    def reset(self, covariance: np.ndarray) -> None:
        """Start from ``covariance`` (an initial pose, a filter that converged again), floored."""
        cov = np.asarray(covariance, dtype=np.float64).reshape(3, 3)
        if not np.all(np.isfinite(cov)):
            cov = np.diag([1.0, 1.0, 0.1])
        self.covariance = self._floored(0.5 * (cov + cov.T))

    def predict(self, theta: float, delta: tuple[float, float, float]) -> None:
        """The robot moved by ``delta`` (dx, dy in its frame at heading ``theta``, dtheta)."""
        p = self.params
        t = math.hypot(delta[0], delta[1])
        q = np.diag([p.drift_xy_m2_per_m * t, p.drift_xy_m2_per_m * t,
                     p.drift_theta_rad2_per_m * t + p.drift_theta_rad2_per_rad * abs(delta[2])])
        f, g = motion_jacobians(theta, delta)
        self.covariance = f @ self.covariance @ f.T + g @ q @ g.T

    def update(self, information: np.ndarray) -> None:
        """Fuse one scan's information (unscaled, ``scan_information``)."""
        h = self.params.information_scale * np.asarray(information, dtype=np.float64)
        if not np.all(np.isfinite(h)):
            return
        post = np.linalg.inv(np.linalg.inv(self.covariance) + h)
        self.covariance = self._floored(0.5 * (post + post.T))

    def _floored(self, cov: np.ndarray) -> np.ndarray:
        p = self.params
        floor = np.array([p.floor_m2, p.floor_m2, p.floor_rad2])
        d = np.diag(cov)
        return cov + np.diag(np.maximum(floor - d, 0.0))

    def position_std_m(self) -> float:
        """Standard deviation along the weakest position direction (largest eigenvalue of the xy block), m."""
        return math.sqrt(max(float(np.linalg.eigvalsh(self.covariance[:2, :2])[-1]), 0.0))

    def weakest_axis_rad(self) -> float:
        """Direction of that weakest axis in the map frame (rad, in (-pi/2, pi/2])."""
        w, v = np.linalg.eigh(self.covariance[:2, :2])
        a = math.atan2(float(v[1, 1]), float(v[0, 1]))
        if a <= -math.pi / 2:
            a += math.pi
        elif a > math.pi / 2:
            a -= math.pi
        return a

    def heading_std_rad(self) -> float:
        return math.sqrt(max(float(self.covariance[2, 2]), 0.0))
