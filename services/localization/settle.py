"""Convergence at rest: no-motion updates with a shrinking jitter until the estimate settles (core, no I/O).

AMCL updates only after the robot moved (``update_min_d``/``update_min_a``). Right after an initial pose the
particles are a Gaussian cloud; one update at rest collapses it onto the few sampled particles that fit best,
centimetres from the likelihood peak, with a spread of millimetres: a confident, wrong pose. Here, while the
filter is *localizing* and the robot stands still, every scan runs a no-motion update after moving each particle
by N(0, σ), σ = clip(``jitter_gain`` · spread, ``jitter_min``, ``jitter_max``) per axis. Resampling repeated on
the same view sharpens the population towards the likelihood's peak (its density goes as Lᵏ after k updates) while
the jitter keeps exploring around it. The estimate has settled when, over the last ``window`` updates (at least
``min_updates`` in all), its position moved less than ``settle_m`` and its heading less than ``settle_rad``; the
verdict then turns from ``localizing`` to ``tracking``. While the robot moves, plain AMCL runs and the window
starts again.

The initial pose stays part of the answer. Jitter and resampling alone are a random walk wherever the scan's
likelihood is flat: along a featureless corridor the cloud wandered off the given pose (35 cm in 150 updates, with
the pose given to 5 cm). Each jittered particle's weight is therefore also multiplied by p₀(x')/p₀(x), the initial
pose's Gaussian at its new over its old place (the Metropolis ratio of the move), so the population follows
p₀(x)·L(x)ᵏ: the scan decides where it can, the prior where it cannot. Random-particle injection is held off for
these updates: a particle dropped on a look-alike corridor elsewhere (22 m away on a real map) would otherwise
outvote the pose given. The prior holds only while the robot has not moved since the initial pose and the filter
has not called itself lost (recovery then searches without it); after a global localization there is none, and
injection runs as usual.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np

from services.common.se2 import wrap_angle
from services.localization.amcl import Amcl, ScanBeams

Pose = tuple[float, float, float]


@dataclass(frozen=True)
class SettleParams:
    """Jitter and settling thresholds (m, rad); see the module docstring."""

    jitter_gain: float = 0.5
    jitter_min_m: float = 0.002
    jitter_max_m: float = 0.10
    jitter_min_rad: float = 0.002
    jitter_max_rad: float = 0.05
    window: int = 12
    min_updates: int = 20
    #: at most this many at-rest updates hold the verdict at localizing: the jitter can keep a good estimate
    #: wandering by more than settle_m, and nav, which waits for tracking, would then never move the robot
    max_updates: int = 150
    settle_m: float = 0.003
    settle_rad: float = 0.003
    #: odometry moving more than this between scans means the robot is not at rest
    rest_m: float = 0.002
    rest_rad: float = 0.002
    #: the prior's ratio p₀(x')/p₀(x) is clipped to exp(±this) (a particle far out in the tails)
    prior_max_log_ratio: float = 30.0


class AtRestSettler:
    """Drives an ``Amcl`` while it is localizing; ``converged`` once the estimate settled at rest."""

    def __init__(self, params: SettleParams | None = None) -> None:
        self.params = params or SettleParams()
        self.converged = False
        self.updates = 0
        self._recent: collections.deque[Pose] = collections.deque(maxlen=self.params.window)
        self._last_odom: Pose | None = None
        #: the filter's initial pose still describes where the robot is (it has not moved since)
        self._prior_in_force = True

    def restart(self) -> None:
        """Localizing again (a new initial pose, a restart, global localization)."""
        self.converged = False
        self.updates = 0
        self._recent.clear()
        self._last_odom = None
        self._prior_in_force = True

    def at_rest(self, odom_pose: Pose) -> bool:
        last, self._last_odom = self._last_odom, odom_pose
        if last is None:
            return True
        p = self.params
        return (math.hypot(odom_pose[0] - last[0], odom_pose[1] - last[1]) <= p.rest_m
                and abs(float(wrap_angle(odom_pose[2] - last[2]))) <= p.rest_rad)

    def process(self, amcl: Amcl, odom_pose: Pose, beams: ScanBeams, mount: Pose, stamp: float | None = None,
                dense: ScanBeams | None = None) -> bool:
        """One scan (at ``stamp``): a jittered no-motion update at rest, plain AMCL when moving; returns whether
        the filter updated. ``dense`` goes to ``Amcl.process`` on every path (a pending refinement, which runs only
        while tracking: the update a client asked for happens, and is answered, whatever the verdict)."""
        if self.converged:
            return amcl.process(odom_pose, beams, mount, stamp, dense)
        if not self.at_rest(odom_pose):
            self._recent.clear()
            self._prior_in_force = False
            return amcl.process(odom_pose, beams, mount, stamp, dense)
        if amcl.state == "lost":  # the scans disowned the initial pose: recovery searches without it
            self._prior_in_force = False
        if amcl.estimate is not None:
            self._jitter(amcl)
        amcl.request_nomotion_update()
        amcl.pf.suppress_injection = self._prior_in_force and amcl.initial_prior is not None
        try:
            updated = amcl.process(odom_pose, beams, mount, stamp, dense)
        finally:
            amcl.pf.suppress_injection = False
        if updated and amcl.estimate is not None:
            self.updates += 1
            self._recent.append(amcl.estimate.pose)
            self.converged = self._settled() or self.updates >= self.params.max_updates
        return updated

    def _jitter(self, amcl: Amcl) -> None:
        p = self.params
        pf = amcl.pf
        assert amcl.estimate is not None
        cov = amcl.estimate.covariance
        spread_m = math.sqrt(max(cov[0, 0] + cov[1, 1], 0.0) / 2.0)
        spread_rad = math.sqrt(max(cov[2, 2], 0.0))
        s_xy = min(max(p.jitter_gain * spread_m, p.jitter_min_m), p.jitter_max_m)
        s_th = min(max(p.jitter_gain * spread_rad, p.jitter_min_rad), p.jitter_max_rad)
        n = pf.n
        prior = amcl.initial_prior if self._prior_in_force else None
        before = None if prior is None else prior_log_density(pf.poses[:n], *prior)
        pf.poses[:n, :2] += pf.rng.standard_normal((n, 2)) * s_xy
        pf.poses[:n, 2] = wrap_angle(pf.poses[:n, 2] + pf.rng.standard_normal(n) * s_th)
        if prior is not None and before is not None:
            limit = p.prior_max_log_ratio
            pf.weights[:n] *= np.exp(np.clip(prior_log_density(pf.poses[:n], *prior) - before, -limit, limit))

    def _settled(self) -> bool:
        p = self.params
        if self.updates < p.min_updates or len(self._recent) < p.window:
            return False
        poses = np.asarray(self._recent)
        xy = poses[:, :2] - poses[-1, :2]
        turn = wrap_angle(poses[:, 2] - poses[-1, 2])
        return bool(np.max(np.hypot(xy[:, 0], xy[:, 1])) < p.settle_m and np.max(np.abs(turn)) < p.settle_rad)


def prior_log_density(poses: np.ndarray, mean: np.ndarray, covariance: np.ndarray) -> np.ndarray | None:
    """log N(x; μ, Σ) up to a constant, -½ dᵀ Σ⁻¹ d with d = x - μ (heading wrapped), for poses (N, 3); None when
    Σ is not a usable covariance (not finite, or not positive definite once 1e-9 is added to its diagonal)."""
    cov = np.asarray(covariance, dtype=float)
    if not np.all(np.isfinite(cov)):
        return None
    try:
        whitening = np.linalg.inv(np.linalg.cholesky(cov + np.eye(3) * 1e-9))  # L⁻¹, Σ = L Lᵀ
    except np.linalg.LinAlgError:
        return None
    d = poses[:, :3] - mean
    d[:, 2] = wrap_angle(d[:, 2])
    whitened = d @ whitening.T
    result: np.ndarray = -0.5 * np.einsum("ij,ij->i", whitened, whitened)
    return result
