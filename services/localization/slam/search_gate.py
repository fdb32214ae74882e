"""How far the newest keyframe may be from where the graph puts it: the loop-closure search gate.

Between loop closures a keyframe's pose is the previous one composed with a scan-matched (or dead-reckoned) edge,
so its uncertainty relative to the mapped area grows along the path. First-order propagation of x' = x ⊕ u with
covariances Σ (of x) and Σ_u (of the edge u = (u_x, u_y, u_θ)):
    Σ' = J_x Σ J_xᵀ + J_u Σ_u J_uᵀ,
    J_x = [[1, 0, −sinθ·u_x − cosθ·u_y], [0, 1, cosθ·u_x − sinθ·u_y], [0, 0, 1]],
    J_u = [[cosθ, −sinθ, 0], [sinθ, cosθ, 0], [0, 0, 1]],
starting from the covariance of the last accepted loop closure (the graph is anchored there) or zero at the first
keyframe. A heading error δθ swings every later position by δθ times the distance driven since, so the position
spread grows faster than the path (≈ σ_θ·L^{3/2}/√3 for a heading random walk): on a long route that revisits
little, a fixed search radius misses the place the robot is really back at.

The gate searches old keyframes within ``base_m + n_sigma·σ_max`` of the estimate (σ_max: the square root of the
largest eigenvalue of Σ's position block) and widens the correlative window to ``n_sigma`` σ in position and in
heading, each capped (Karto / slam_toolbox search within the pose uncertainty the same way).
"""

from __future__ import annotations

import math

import numpy as np

from services.localization.uncertainty import motion_jacobians


def propagate(covariance: np.ndarray, pose: np.ndarray, step: np.ndarray, step_covariance: np.ndarray) -> np.ndarray:
    """Σ' (3x3) of ``pose`` ⊕ ``step`` given Σ of ``pose`` (world frame) and Σ_u of ``step`` (frame of ``pose``)."""
    j_pose, j_step = motion_jacobians(float(pose[2]), (float(step[0]), float(step[1]), float(step[2])))
    out: np.ndarray = j_pose @ np.asarray(covariance, float) @ j_pose.T + j_step @ np.asarray(step_covariance,
                                                                                          float) @ j_step.T
    symmetric: np.ndarray = 0.5 * (out + out.T)
    return symmetric


def position_sigma_m(covariance: np.ndarray) -> float:
    """√λ_max of the position block of Σ: the spread along the worst direction (m)."""
    return float(math.sqrt(max(float(np.linalg.eigvalsh(np.asarray(covariance, float)[:2, :2])[-1]), 0.0)))


def heading_sigma_rad(covariance: np.ndarray) -> float:
    return float(math.sqrt(max(float(covariance[2, 2]), 0.0)))


def scaled(base: float, n_sigma: float, sigma: float, cap: float) -> float:
    """``base + n_sigma·sigma``, at most ``cap`` (and never below ``base``)."""
    return max(base, min(base + n_sigma * sigma, cap))
