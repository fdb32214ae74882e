"""Which directions a scan match fixes, and what follows for the pose and for its pose-graph edge.

The shape of the score surface around the match says it: C (2x2) is the negative curvature of the mean score under
translation (``matcher.translation_curvature``, central differences one cell apart), with eigenpairs (λ_k, v_k),
λ_1 ≤ λ_2. Only its *shape* is used (its scale depends on the number of points and on the grid). A direction whose
eigenvalue is a small fraction of the strongest one, r_k = λ_k / λ_2, is barely fixed by the scan (the axis of a
corridor, a wall seen alone). Each direction gets a weight that ramps from 0 at r_k ≤ ``ratio_weak`` to 1 at
r_k ≥ ``ratio_strong``:
    w_k = clip((r_k − r_weak) / (r_strong − r_weak), 0, 1).
Degeneracy-aware estimation (Zhang, Kaess and Singh 2016, "On degeneracy of optimization-based state estimation
problems"): along a direction of weight 0 the pose is the odometry prediction's, along one of weight 1 the scan's,
    t = t_pred + Σ_k w_k v_k v_kᵀ (t_scan − t_pred),   θ = θ_scan,
and the edge information blends the scan match's and the odometry's per direction,
    Ω_t = Σ_k (w_k ω_scan + (1 − w_k) ω_odom) v_k v_kᵀ,   Ω_θ = ω_θ,
so a loop closure in a corridor does not pin the graph along the corridor, and the pose graph may stretch a
dead-reckoned corridor where a well-constrained closure asks for it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MatchConstraint:
    """Eigen-directions ``directions[:, k]`` (unit, x y) of the marginal translation information, their strength
    relative to the strongest (``ratios``, 0..1), and the per-direction weights of the scan (``weights``, 0..1)."""

    directions: np.ndarray
    ratios: np.ndarray
    weights: np.ndarray

    @property
    def weakest_ratio(self) -> float:
        return float(self.ratios[0])

    @property
    def degenerate(self) -> bool:
        """True when some translation direction is not fully fixed by the scan."""
        return bool(self.weights[0] < 1.0)

    def scan_projector(self) -> np.ndarray:
        """P = Σ_k w_k v_k v_kᵀ (2x2): the part of a translation the scan decides."""
        information: np.ndarray = (self.directions * self.weights) @ self.directions.T
        return information

    def remap(self, scan_pose: np.ndarray, predicted_pose: np.ndarray) -> np.ndarray:
        """The scan's pose along the directions it fixes, the prediction's along the others; the scan's heading."""
        scan_pose = np.asarray(scan_pose, float)
        predicted_pose = np.asarray(predicted_pose, float)
        out = scan_pose.copy()
        out[:2] = predicted_pose[:2] + self.scan_projector() @ (scan_pose[:2] - predicted_pose[:2])
        return out

    def information(self, scan_xy: float, odometry_xy: float, theta: float) -> np.ndarray:
        """Ω (3x3): per direction w·``scan_xy`` + (1 − w)·``odometry_xy`` (1/m²); ``theta`` (1/rad²) on heading."""
        per_direction = self.weights * scan_xy + (1.0 - self.weights) * odometry_xy
        info = np.zeros((3, 3))
        info[:2, :2] = (self.directions * per_direction) @ self.directions.T
        info[2, 2] = theta
        return info


#: the constraint of a match that fixes every direction (no remapping, the scan's information everywhere)
FULLY_CONSTRAINED = MatchConstraint(np.eye(2), np.ones(2), np.ones(2))


def match_constraint(curvature: np.ndarray, *, ratio_weak: float, ratio_strong: float) -> MatchConstraint:
    """``MatchConstraint`` of a score surface's translation curvature (2x2; negative eigenvalues count as zero);
    a surface without any curvature counts as fully degenerate."""
    if not 0.0 <= ratio_weak < ratio_strong <= 1.0:
        raise ValueError(f"need 0 <= ratio_weak < ratio_strong <= 1 (got {ratio_weak}, {ratio_strong})")
    c = np.asarray(curvature, float)
    if c.shape != (2, 2) or not np.all(np.isfinite(c)):
        raise ValueError(f"the curvature must be a finite 2x2 matrix (got shape {c.shape})")
    eigenvalues, directions = np.linalg.eigh(0.5 * (c + c.T))
    eigenvalues = np.maximum(eigenvalues, 0.0)
    strongest = float(eigenvalues[-1])
    if strongest <= 0.0:
        return MatchConstraint(directions, np.zeros(2), np.zeros(2))
    ratios = eigenvalues / strongest
    weights = np.clip((ratios - ratio_weak) / (ratio_strong - ratio_weak), 0.0, 1.0)
    return MatchConstraint(directions, ratios, weights)
