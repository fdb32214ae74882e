"""Convergence at rest: no-motion updates until the estimate settles (core, no I/O).

AMCL updates only after the robot moved (``update_min_d``/``update_min_a``). Right after an initial pose the
particles are a Gaussian cloud; one update at rest collapses it onto the few sampled particles that fit best,
centimetres from the likelihood peak, with a spread of millimetres: a confident, wrong pose. Here, while the
filter is *localizing* and the robot stands still, every scan runs a no-motion update. The estimate has settled
when, over the last ``window`` updates (at least ``min_updates`` in all), its position moved less than
``settle_m`` and its heading less than ``settle_rad``; the verdict then turns from ``localizing`` to ``tracking``.
While the robot moves, plain AMCL runs and the window starts again.

Scans of the same view are not independent evidence. Multiplying the weights by each one's likelihood L makes the
population follow Lᵏ after k scans: it sharpens onto the small bumps a map's cells put along any direction the scan
cannot fix. Along a corridor whose ends the lidar does not see, the pose then came out 5-20 cm off with a spread of
millimetres (a real campus map, start poses given exactly), and a featureless 78 m corridor let it wander by a
metre. So after the first update (which weights the initial Gaussian p₀ by L and resamples), each scan at rest
moves every particle by one Metropolis-Hastings step towards p₀·L (``amcl.RestMove``): a proposal shaped like the
cloud is accepted with probability min(1, p₀(x')L(x') / p₀(x)L(x)), both L on the current scan. The target stays
one scan's worth of likelihood times the initial pose's Gaussian, whatever the number of scans: the scan decides
where it can, the pose given where it cannot, and the spread says which is which.

This holds only while the robot has not moved since the initial pose and the filter has not called itself lost
(recovery then searches without the prior). Without an initial pose to hold to (after a global localization) the
at-rest updates are plain no-motion updates of particles jittered by N(0, σ), σ = clip(``jitter_gain`` · spread,
``jitter_min``, ``jitter_max``) per axis, with random injection as usual.
Random injection is held off while the prior holds: a particle dropped on a look-alike corridor elsewhere (22 m
away on a real map) would otherwise outvote the pose given.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np

from services.common.se2 import wrap_angle
from services.localization.amcl import Amcl, RestMove, ScanBeams

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
    #: β of the at-rest target p₀·Lᵝ: β = min(updates, this); see the module docstring
    max_likelihood_power: float = 10.0


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
        #: the estimate settled: the next scan's update ends with the dense refinement, then the verdict is free
        self._polishing = False

    def restart(self) -> None:
        """Localizing again (a new initial pose, a restart, global localization)."""
        self.converged = False
        self.updates = 0
        self._recent.clear()
        self._last_odom = None
        self._prior_in_force = True
        self._polishing = False

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
            self._polishing = False
            return amcl.process(odom_pose, beams, mount, stamp, dense)
        if amcl.state == "lost":  # the scans disowned the initial pose: recovery searches without it
            self._prior_in_force = False
        p = self.params
        prior = amcl.initial_prior if self._prior_in_force else None
        move = None
        if amcl.estimate is not None:
            if prior is not None:
                move = RestMove(prior_mean=prior[0], prior_covariance=prior[1],
                                likelihood_power=float(min(self.updates + 1, p.max_likelihood_power)))
            else:
                self._jitter(amcl, *self._steps(amcl))
        amcl.request_nomotion_update()
        amcl.pf.suppress_injection = prior is not None
        polished = self._polishing and dense is not None and amcl.refine_pending
        try:
            updated = amcl.process(odom_pose, beams, mount, stamp, dense, rest_move=move)
        finally:
            amcl.pf.suppress_injection = False
        if updated and amcl.estimate is not None:
            self.updates += 1
            self._recent.append(amcl.estimate.pose)
            if polished or (self._polishing and amcl.state != "tracking"):
                self.converged = True
            elif amcl.state == "tracking" and amcl.spread_m > amcl.params.track_spread_m:
                # the cloud spread out again (along a corridor the scan does not fix, it tends to the initial
                # pose's own spread): not settled, whatever the count
                self._polishing = False
            elif self._settled() or self.updates >= p.max_updates:
                if amcl.state == "tracking" and not self._polishing:
                    # the cloud's mean is as good as the subsampled scan makes it: the next update also fits every
                    # beam of its scan to the map (services/localization/refine.py), the cloud as its prior
                    self._polishing = True
                    amcl.request_nomotion_update(refine=True)
                else:
                    self.converged = True
        return updated

    def _steps(self, amcl: Amcl) -> tuple[float, float]:
        """(σ m, σ rad): ``jitter_gain`` times the estimate's spread per axis, clipped."""
        p = self.params
        assert amcl.estimate is not None
        cov = amcl.estimate.covariance
        spread_m = math.sqrt(max(cov[0, 0] + cov[1, 1], 0.0) / 2.0)
        spread_rad = math.sqrt(max(cov[2, 2], 0.0))
        return (min(max(p.jitter_gain * spread_m, p.jitter_min_m), p.jitter_max_m),
                min(max(p.jitter_gain * spread_rad, p.jitter_min_rad), p.jitter_max_rad))

    @staticmethod
    def _jitter(amcl: Amcl, s_xy: float, s_th: float) -> None:
        """Move each particle by N(0, s) per axis before a plain no-motion update."""
        pf = amcl.pf
        n = pf.n
        pf.poses[:n, :2] += pf.rng.standard_normal((n, 2)) * s_xy
        pf.poses[:n, 2] = wrap_angle(pf.poses[:n, 2] + pf.rng.standard_normal(n) * s_th)

    def _settled(self) -> bool:
        p = self.params
        if self.updates < p.min_updates or len(self._recent) < p.window:
            return False
        poses = np.asarray(self._recent)
        xy = poses[:, :2] - poses[-1, :2]
        turn = wrap_angle(poses[:, 2] - poses[-1, 2])
        return bool(np.max(np.hypot(xy[:, 0], xy[:, 1])) < p.settle_m and np.max(np.abs(turn)) < p.settle_rad)
