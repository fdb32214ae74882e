"""Scan-to-map matching on a multi-resolution likelihood grid.

``refine``: Gauss-Newton (Kohlbrecher et al. 2011) from coarse to fine level, minimising
    Σ_i (1 - M(T(ξ) p_i))² / σ_M²  +  (ξ - ξ_prior)ᵀ Λ (ξ - ξ_prior)
with ∂M/∂ξ = ∇M · [I₂ | (-s_y + t_y, s_x - t_x)ᵀ] for s = T(ξ) p. The optional prior (odometry) keeps the
estimate in place along directions the scan does not constrain (long corridors).

``correlative_search``: exhaustive search over a window of rotations and cell offsets on a coarse level
(Olson 2009), scoring the mean grid value at the scan's points; ``search_and_refine`` refines its best candidates
and keeps the best-scoring result.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.common.se2 import transform_points, wrap_angle

from .likelihood import LikelihoodGrid, MultiResolutionGrid


@dataclass
class MatchResult:
    """Matched pose (x, y, theta), mean fine-level grid value at the points (0..1), and the Gauss-Newton
    Hessian of the scan term (3x3, per unit residual variance) describing how well each direction is fixed."""

    pose: np.ndarray
    score: float
    hessian: np.ndarray

    def min_translation_eigenvalue(self) -> float:
        return float(np.linalg.eigvalsh(self.hessian[:2, :2])[0])


def score(grid: LikelihoodGrid, points: np.ndarray, pose: np.ndarray) -> float:
    """Mean bilinear grid value of ``points`` placed at ``pose``."""
    value, _ = grid.value_and_gradient(transform_points(pose, points))
    return float(value.mean()) if len(value) else 0.0


def translation_curvature(grid: LikelihoodGrid, points: np.ndarray, pose: np.ndarray,
                          step_m: float = 0.05) -> np.ndarray:
    """Negative curvature C (2x2, per m²) of the mean score under translation, from central differences of
    ``step_m``: C_xx = −(s(+h,0) + s(−h,0) − 2s₀)/h², C_xy = −(s(+h,+h) − s(+h,−h) − s(−h,+h) + s(−h,−h))/4h².
    Unlike the Gauss-Newton JᵀJ, whose squared gradients add up the grid's ripple along a wall, differences one
    cell apart average it out: a corridor's axis shows as a near-zero eigenvalue."""
    s0 = score(grid, points, pose)

    def at(dx: float, dy: float) -> float:
        return score(grid, points, pose + np.array([dx, dy, 0.0]))

    h = step_m
    cxx = (at(h, 0) + at(-h, 0) - 2 * s0) / h**2
    cyy = (at(0, h) + at(0, -h) - 2 * s0) / h**2
    cxy = (at(h, h) - at(h, -h) - at(-h, h) + at(-h, -h)) / (4 * h**2)
    return -np.array([[cxx, cxy], [cxy, cyy]])


def translation_sharpness(grid: LikelihoodGrid, points: np.ndarray, pose: np.ndarray, step_m: float = 0.05) -> float:
    """Smallest eigenvalue of ``translation_curvature``: near zero when the scan slides freely along some
    direction (corridor)."""
    return float(np.linalg.eigvalsh(translation_curvature(grid, points, pose, step_m))[0])


def refine(grids: MultiResolutionGrid, points: np.ndarray, initial_pose: np.ndarray, *,
           iterations_per_level: int = 6, field_sigma: float = 0.3,
           prior_pose: np.ndarray | None = None, prior_information: np.ndarray | None = None,
           min_step: float = 5e-4, max_damping_tries: int = 5,
           point_weights: np.ndarray | None = None) -> MatchResult:
    """Gauss-Newton from the coarsest to the finest level (see the module docstring) with Levenberg-Marquardt
    damping: a step that raises the cost is re-solved from (H + λ·diag(H)) with λ = 0.1, 1, 10, ... (up to
    ``max_damping_tries`` times) and λ shrinks tenfold after an accepted step. Near a wall's crest ∇M vanishes, so
    JᵀJ underestimates the curvature and plain Gauss-Newton overshoots across the wall; damping shortens the step
    there without giving up the direction along which the scan still pulls (a corridor's axis). ``point_weights``
    (N,) scale each point's residual term (1 when not given)."""
    pose = np.asarray(initial_pose, float).copy()
    weight = np.ones(len(points)) if point_weights is None else np.asarray(point_weights, float)
    inv_var = 1.0 / field_sigma**2
    has_prior = prior_information is not None and prior_pose is not None

    def evaluate(grid: LikelihoodGrid, at: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray | None]:
        world = transform_points(at, points)
        value, grad = grid.value_and_gradient(world)
        residual = 1.0 - value
        cost = inv_var * float(residual @ (weight * residual))
        diff = None
        if has_prior:
            diff = np.asarray(prior_pose, float) - at
            diff[2] = wrap_angle(diff[2])
            cost += float(diff @ prior_information @ diff)
        return world, residual, grad, cost, diff

    hessian = np.zeros((3, 3))
    for grid in reversed(grids.levels):
        world, residual, grad, cost, diff = evaluate(grid, pose)
        damping = 0.0
        for _ in range(iterations_per_level):
            jac = np.empty((len(points), 3))
            jac[:, 0] = grad[:, 0]
            jac[:, 1] = grad[:, 1]
            jac[:, 2] = -grad[:, 0] * (world[:, 1] - pose[1]) + grad[:, 1] * (world[:, 0] - pose[0])
            hessian = inv_var * ((jac.T * weight) @ jac)
            gradient = inv_var * ((jac.T * weight) @ residual)
            system = hessian + np.eye(3) * 1e-6
            if has_prior and prior_information is not None:
                system += prior_information
                gradient = gradient + prior_information @ diff
            accepted = False
            step = np.zeros(3)
            for _ in range(max_damping_tries + 1):
                try:
                    step = np.linalg.solve(system + damping * np.diag(np.diag(system)), gradient)
                except np.linalg.LinAlgError:
                    break
                trial = pose + step
                trial[2] = float(wrap_angle(trial[2]))
                t_world, t_residual, t_grad, t_cost, t_diff = evaluate(grid, trial)
                if t_cost <= cost:
                    pose, world, residual, grad, cost, diff = trial, t_world, t_residual, t_grad, t_cost, t_diff
                    accepted = True
                    damping = 0.0 if damping <= 0.1 else damping / 10.0
                    break
                damping = 0.1 if damping == 0.0 else damping * 10.0
            if not accepted or (abs(step[0]) + abs(step[1]) < min_step and abs(step[2]) < min_step):
                break
    return MatchResult(pose, score(grids.levels[0], points, pose), hessian)


def correlative_search(grid: LikelihoodGrid, points: np.ndarray, center_pose: np.ndarray, *,
                       window_xy_m: float, window_theta_rad: float, theta_step_rad: float,
                       n_best: int = 5) -> list[tuple[float, np.ndarray]]:
    """Best ``n_best`` (score, pose) over x, y in center ± window (steps of one cell) and theta in
    center ± window (steps of ``theta_step_rad``), scores = mean nearest-cell value; distinct rotations."""
    res = grid.resolution_m
    half = int(np.ceil(window_xy_m / res))
    offsets = np.arange(-half, half + 1)
    pad = half + 1
    field = np.pad(grid.field, pad)
    height, width = field.shape
    flat = field.ravel()
    ox, oy = np.meshgrid(offsets, offsets)
    offset_flat = (oy * width + ox).ravel()
    thetas = center_pose[2] + np.arange(-window_theta_rad, window_theta_rad + 1e-9, theta_step_rad)
    best: list[tuple[float, np.ndarray]] = []
    for theta in thetas:
        world = transform_points(np.array([center_pose[0], center_pose[1], theta]), points)
        ix = np.floor((world[:, 0] - grid.origin_xy_m[0]) / res).astype(np.intp) + pad
        iy = np.floor((world[:, 1] - grid.origin_xy_m[1]) / res).astype(np.intp) + pad
        inside = (ix >= pad - 1) & (iy >= pad - 1) & (ix <= width - pad) & (iy <= height - pad)
        if not inside.any():
            continue
        base = iy[inside] * width + ix[inside]
        scores = flat.take(base[:, None] + offset_flat[None, :]).sum(axis=0) / len(points)
        k = int(np.argmax(scores))
        pose = np.array([center_pose[0] + ox.ravel()[k] * res, center_pose[1] + oy.ravel()[k] * res,
                         wrap_angle(theta)])
        best.append((float(scores[k]), pose))
    best.sort(key=lambda item: -item[0])
    return best[:n_best]


def search_and_refine(grids: MultiResolutionGrid, points: np.ndarray, center_pose: np.ndarray, *,
                      window_xy_m: float, window_theta_rad: float, theta_step_rad: float, n_best: int,
                      incumbent: MatchResult | None = None, min_gain: float = 0.0,
                      prior_pose: np.ndarray | None = None, prior_information: np.ndarray | None = None,
                      point_weights: np.ndarray | None = None) -> MatchResult | None:
    """``correlative_search`` on the coarsest level of ``grids``, each of its ``n_best`` candidates ``refine``d
    (with the given prior and weights), and the best kept: a candidate replaces the best so far (``incumbent`` at
    first) only when it scores more than ``min_gain`` higher. None when there was no incumbent and no candidate."""
    best = incumbent
    for _, pose in correlative_search(grids.levels[-1], points, center_pose, window_xy_m=window_xy_m,
                                      window_theta_rad=window_theta_rad, theta_step_rad=theta_step_rad,
                                      n_best=n_best):
        trial = refine(grids, points, pose, prior_pose=prior_pose, prior_information=prior_information,
                       point_weights=point_weights)
        if best is None or trial.score > best.score + min_gain:
            best = trial
    return best
