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

What a loop search needs is not Σ_k itself but the uncertainty of keyframe k *relative to the candidate j* it is
matched against. Both were propagated from the same anchor a (the last accepted closure) along one chain, so the
chain's Jacobian from j to k is the lever arm A_jk = [[1, 0, −(y_k − y_j)], [0, 1, x_k − x_j], [0, 0, 1]] and
    Σ_k = A_jk Σ_j A_jkᵀ + Σ_jk   ⇒   Σ_jk = Σ_k − A_jk Σ_j A_jkᵀ   (j at or after a),
    Σ_jk = Σ_k                                                      (j before a: k hangs on the anchor's closure).
A keyframe j driven just before k (same open loop) is therefore only as uncertain as the few edges between them;
the whole drift since the anchor is for places visited before it.

The gate searches old keyframes j within ``base_m + n_sigma·σ_max(Σ_jk)`` of the estimate (σ_max: the square root of
the largest eigenvalue of the position block) and widens the correlative window to ``n_sigma`` σ in position and in
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


def relative_sigmas(covariance: np.ndarray, position_xy_m: np.ndarray, anchor: int, covariances: np.ndarray,
                    positions_xy_m: np.ndarray, anchors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(σ_max position in m, σ_θ in rad) of Σ_jk for every keyframe j, from the newest keyframe's Σ_k
    (``covariance``, at ``position_xy_m``, propagated from keyframe ``anchor``) and each j's own Σ_j (``covariances``
    (N, 3, 3), at ``positions_xy_m`` (N, 2), propagated from ``anchors`` (N,)):
    Σ_jk = Σ_k − A_jk Σ_j A_jkᵀ when j was propagated from the same anchor (and j ≥ anchor), else Σ_k."""
    n = len(covariances)
    lever = np.tile(np.eye(3), (n, 1, 1))
    delta = np.asarray(position_xy_m, float)[None, :] - np.asarray(positions_xy_m, float)
    lever[:, 0, 2] = -delta[:, 1]
    lever[:, 1, 2] = delta[:, 0]
    carried = np.einsum("nij,njk,nlk->nil", lever, covariances, lever)
    same_chain = (np.asarray(anchors) == anchor)[:, None, None]
    rel = np.where(same_chain, np.asarray(covariance, float)[None] - carried, np.asarray(covariance, float)[None])
    a, b, d = rel[:, 0, 0], rel[:, 0, 1], rel[:, 1, 1]
    lam_max = 0.5 * (a + d) + np.sqrt(0.25 * (a - d) ** 2 + b**2)
    sigma_xy_m: np.ndarray = np.sqrt(np.maximum(lam_max, 0.0))
    sigma_theta_rad: np.ndarray = np.sqrt(np.maximum(rel[:, 2, 2], 0.0))
    return sigma_xy_m, sigma_theta_rad
