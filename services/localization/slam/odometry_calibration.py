"""Online calibration of the odometry's systematic error from scan-matched motion.

The scan match starts from, and is held towards, the odometry prediction (its prior); near a weakly fixed
direction the prediction decides outright (``constraint.py``). A systematic odometry error (a wheel radius off by
a few percent, a heading that drifts per metre driven) therefore leaks a fraction into every match, and those
fractions add up to an open-loop drift that a route revisiting little never gets closed out. Calibrating the
odometry removes the systematic part before it reaches the prior (the type A/B errors of Borenstein's UMBmark).

Model of one odometry increment u = (u_x, u_y, u_θ) over a path of length d (m):
    t_true = s · (u_x, u_y),    θ_true = a · u_θ + b · d
(s: wheel scale, a: rotation scale, b: heading drift in rad/m). Each keyframe edge whose scans all matched cleanly
(every direction fixed, no rescue, no outlier, no fallback) is an observation: the matched relative translation
t_m and heading change θ_m against the raw odometry's t_o, θ_o and path length d over the same scans. Least squares
with exponential forgetting (weight e^{−d/horizon} on what came before) and a prior pulling to s = a = 1, b = 0:
    s = (Σ t_m·t_o + P_t) / (Σ |t_o|² + P_t),
    (a, b) = (Σ φφᵀ + diag(P_a, P_b))⁻¹ (Σ φ θ_m + (P_a, 0)),  φ = (θ_o, d),
each clamped to a plausible range. The estimate is unbiased at its fixed point: once the prediction is calibrated,
the prior holds the match towards the truth, not away from it.
"""

from __future__ import annotations

import math

import numpy as np


class OdometryCalibration:
    """Running (s, a, b) estimate; ``correct`` applies it to an odometry increment, ``observe`` adds a keyframe."""

    def __init__(self, *, horizon_m: float = 200.0, prior_translation_m2: float = 2.0,
                 prior_rotation_rad2: float = 0.5, prior_drift_m2: float = 2.0, max_scale_error: float = 0.2,
                 max_drift_rad_per_m: float = 0.1) -> None:
        if horizon_m <= 0.0 or min(prior_translation_m2, prior_rotation_rad2, prior_drift_m2) <= 0.0:
            raise ValueError("the calibration horizon and prior weights must be > 0")
        self.horizon_m = horizon_m
        self.max_scale_error = max_scale_error
        self.max_drift_rad_per_m = max_drift_rad_per_m
        self._prior = (prior_translation_m2, prior_rotation_rad2, prior_drift_m2)
        self._t_cross = 0.0
        self._t_square = 0.0
        self._phi_phi = np.zeros((2, 2))
        self._phi_theta = np.zeros(2)
        self.scale = 1.0
        self.rotation_scale = 1.0
        self.drift_rad_per_m = 0.0
        self.observations = 0

    def correct(self, step: np.ndarray) -> np.ndarray:
        """The increment ``step`` (x, y, theta) with the systematic error taken out (path length ≈ ‖(x, y)‖)."""
        step = np.asarray(step, float)
        dist = math.hypot(float(step[0]), float(step[1]))
        return np.array([self.scale * step[0], self.scale * step[1],
                         self.rotation_scale * step[2] + self.drift_rad_per_m * dist])

    def observe(self, odom_translation: np.ndarray, odom_turn_rad: float, odom_path_m: float,
                matched_translation: np.ndarray, matched_turn_rad: float) -> None:
        """One clean keyframe edge: the raw odometry's translation (frame of the edge's start), summed heading change
        and path length, and the scan-matched translation and heading change over the same scans."""
        values = (*np.ravel(odom_translation), odom_turn_rad, odom_path_m, *np.ravel(matched_translation),
                  matched_turn_rad)
        if not all(math.isfinite(float(v)) for v in values):
            raise ValueError("odometry calibration needs finite increments")
        keep = math.exp(-max(odom_path_m, 0.0) / self.horizon_m)
        t_o = np.asarray(odom_translation, float)[:2]
        t_m = np.asarray(matched_translation, float)[:2]
        self._t_cross = keep * self._t_cross + float(t_m @ t_o)
        self._t_square = keep * self._t_square + float(t_o @ t_o)
        phi = np.array([odom_turn_rad, odom_path_m])
        self._phi_phi = keep * self._phi_phi + np.outer(phi, phi)
        self._phi_theta = keep * self._phi_theta + phi * matched_turn_rad
        self.observations += 1
        p_t, p_a, p_b = self._prior
        scale = (self._t_cross + p_t) / (self._t_square + p_t)
        a, b = np.linalg.solve(self._phi_phi + np.diag([p_a, p_b]), self._phi_theta + np.array([p_a, 0.0]))
        limit = self.max_scale_error
        self.scale = float(np.clip(scale, 1.0 - limit, 1.0 + limit))
        self.rotation_scale = float(np.clip(a, 1.0 - limit, 1.0 + limit))
        self.drift_rad_per_m = float(np.clip(b, -self.max_drift_rad_per_m, self.max_drift_rad_per_m))
