"""Adaptive Monte-Carlo localization (AMCL) in numpy: the particle filter of ROS/Nav2 amcl, without I/O.

- Motion: Nav2's omni-corrected odometry model (alpha1..alpha5), applied to every particle per filter update.
- Sensor: the likelihood-field model. Each map cell holds ``pz^3`` with ``pz = z_hit exp(-d^2 / (2 sigma_hit^2)) +
  z_rand / range_max`` (``d`` the distance to the nearest occupied cell, capped at ``laser_likelihood_max_dist``);
  a particle's weight is multiplied by ``1 + sum over beams of pz^3`` (amcl's sum-of-cubes heuristic), or with
  ``laser_model_type = "likelihood_field_prob"`` by the product of the beams' ``pz`` (no beam skipping). Beams are
  subsampled with Nav2's step ``(n - 1) // (max_beams - 1)``; endpoints beyond the map use the capped distance.
- Resampling: low-variance (systematic) resampling every ``resample_interval`` sensor updates, KLD-sampling the
  population between ``min_particles`` and ``max_particles`` (bins 0.5 m x 0.5 m x 10 deg, ``pf_err``, ``pf_z``),
  and random particles over free space with probability ``max(0, 1 - w_fast / w_slow)`` (``recovery_alpha_slow``,
  ``recovery_alpha_fast``; 0 disables it). w_slow/w_fast average the per-beam likelihood; with
  ``recovery_sensor_reset`` the random particles are drawn from many uniform candidates in proportion to their
  likelihood for the current scan (sensor-resetting localization, Lenser & Veloso 2000). After an injection only
  w_fast restarts (from w_slow; amcl zeroes both), so a filter stuck on a wrong pose keeps injecting.
- Global localization: many uniform particles, then annealing: likelihoods raised to 1/T (T cooling to 1) and
  resampled particles roughened by sqrt(T) x jitter; the recovery averages start after the annealing.
- Estimate: the heaviest cluster of adjacent occupied bins; its weighted mean and covariance.
- Gates: a filter update needs ``update_min_d`` (per axis, odom frame) or ``update_min_a`` of odometry motion.

Hot paths use preallocated buffers (``out=``), so an update allocates little beyond small per-particle arrays.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from typing import Literal

import msgspec
import numpy as np

from services.common import gridops
from services.common.grid import YAW_EPS_RAD, axis_aligned
from services.common.map_io import FREE, UNKNOWN, OccupancyMap
from services.common.se2 import compose, inverse, wrap_angle
from services.localization.refine import BeamModel, Refinement, refine_pose
from services.localization.uncertainty import PoseUncertainty, UncertaintyParams, scan_information

#: KLD histogram bin sizes (pf.c): 0.5 m, 0.5 m, 10 deg
BIN_XY_M = 0.5
BIN_THETA_RAD = math.radians(10.0)
OCCUPIED_MIN = 65


class AmclParams(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """AMCL parameters; names follow Nav2's ``amcl`` node (units: m, rad).

    Defaults are tuned for this robot (LMS111, 12 mm range noise; slow omni base) and differ from Nav2's where
    measured accuracy called for it: ``laser_model_type`` likelihood_field_prob (Nav2: likelihood_field),
    ``z_hit``/``z_rand`` 0.9/0.1 (0.5/0.5), ``sigma_hit`` 0.1 (0.2), ``update_min_d``/``update_min_a`` 0.1/0.1
    (0.25/0.2), ``recovery_alpha_slow``/``_fast`` 0.001/0.1 (ROS 1's; Nav2 disables recovery), ``laser_max_range``
    -1 = the scan's range_max (Nav2: 100). ``global_localization_particles``, ``recovery_sensor_reset`` and the
    ``global_localization_temperature``/``_cooling``/``_jitter_*`` annealing are ours.
    """

    min_particles: int = 500
    max_particles: int = 2000
    pf_err: float = 0.05
    pf_z: float = 0.99
    recovery_alpha_slow: float = 0.001
    recovery_alpha_fast: float = 0.1
    update_min_d: float = 0.1
    update_min_a: float = 0.1
    resample_interval: int = 1
    max_beams: int = 60
    laser_model_type: Literal["likelihood_field", "likelihood_field_prob"] = "likelihood_field_prob"
    z_hit: float = 0.9
    z_rand: float = 0.1
    sigma_hit: float = 0.1
    laser_likelihood_max_dist: float = 2.0
    #: beams ending in unknown cells score as if they ended at most this far (m) from an obstacle, and free space's
    #: edge with unknown space is a surface; < 0: as Nav2 (only the distance to occupied cells counts, so a pose
    #: that puts unexplained beams into unknown space is punished for every one of them)
    unknown_distance_m: float = 0.2
    #: where a wall's surface lies in its occupied cells, for the refinement at rest (``refine.py``): ``face``, on the
    #: free face of the cells (a map rendered from geometry, as the simulator renders a map's cells solid); ``cell``,
    #: anywhere in the wall's first layer of cells (a map built from scans: each hit marks the cell it fell in, so
    #: the free face lies up to a cell in front of the surface and ``face`` settles 3.5-5.8 cm off on such a map).
    #: Localization uses ``cell`` on a map it built itself (``localization/mode``)
    map_surface: Literal["face", "cell"] = "face"
    laser_min_range: float = -1.0
    laser_max_range: float = -1.0
    alpha1: float = 0.2
    alpha2: float = 0.2
    alpha3: float = 0.2
    alpha4: float = 0.2
    alpha5: float = 0.2
    random_seed: int = -1
    #: particles for global localization (Nav2 uses max_particles); more hypotheses for the first scan help a
    #: large or self-similar map, and cost only that one update (the sensor model runs in max_particles chunks)
    global_localization_particles: int = 20000
    #: recovery particles are drawn from that many uniform candidates weighted by the current scan (sensor
    #: resetting) rather than uniformly, so that a kidnapped robot is found in a large map
    recovery_sensor_reset: bool = True
    #: annealing after global localization: the first sensor update raises the likelihoods to 1/temperature
    #: (a wider basin, so that hypotheses near the true pose survive next to one that fits a single scan better),
    #: and each update multiplies the temperature by ``global_localization_cooling`` until it reaches 1
    global_localization_temperature: float = 20.0
    global_localization_cooling: float = 0.85
    #: roughening while annealing: each resampled particle moves by N(0, sqrt(temperature) * jitter), so that a few
    #: particles near the true pose but slightly off explore their basin instead of losing to a larger cluster
    #: elsewhere that happens to hold a better-aligned member (without it, 1 start in 300 at goal 4 settled on the
    #: hall seen rotated by 90 deg)
    global_localization_jitter_xy_m: float = 0.05
    global_localization_jitter_theta_rad: float = 0.02
    #: the verdict (``Amcl.state``): a beam is *explained* when its endpoint, seen from the estimate, lies within
    #: ``match_distance_m`` of an obstacle of the map; ``match_score`` is the median over the last
    #: ``match_window`` scans of the fraction of beams explained. Tracking turns lost when that median falls below
    #: ``lost_score`` (and the track no longer fits, ``lost_evidence_*``) or the particles spread beyond
    #: ``lost_spread_m``; localizing (after an initial pose, a global
    #: localization or a recovery) turns tracking when the median reaches ``track_score`` with the spread under
    #: ``track_spread_m``
    match_distance_m: float = 0.15
    match_window: int = 5
    match_min_beams: int = 8
    lost_score: float = 0.5
    track_score: float = 0.8
    lost_spread_m: float = 1.0
    track_spread_m: float = 0.25
    #: recovery once lost: first ``local_recovery_attempts`` sensor resets within ``local_recovery_radius_m`` of the
    #: last pose the filter trusted (each attempt doubles the radius), each given ``recovery_attempt_s`` to converge,
    #: then global localization, repeated every ``global_recovery_s`` while it does not converge (a requested global
    #: localization too: annealing over uniform particles takes more updates than a local reset). While not
    #: tracking the filter updates at least every ``recovery_update_period_s``, moving or not
    local_recovery_attempts: int = 2
    local_recovery_radius_m: float = 2.0
    recovery_attempt_s: float = 4.0
    global_recovery_s: float = 20.0
    recovery_update_period_s: float = 0.2
    #: random-particle injection (recovery_alpha_*) only while the filter is not tracking: a tracking filter is
    #: trusted, and injecting into it on a poorly matching stretch of a real map is what made it jump
    inject_while_tracking: bool = False
    #: ... except when the likelihood collapses: while tracking, an injection probability (1 - w_fast / w_slow) of at
    #: least this still injects. A kidnapping along a self-similar corridor keeps the scans fitting the walls (the
    #: verdict stays tracking) while the likelihood drops well below its tracking level; a poorly matching stretch
    #: of a real map lowers it only a little
    tracking_injection_min: float = 0.1
    #: a re-localisation (convergence after "lost" or a global localization) is trusted only once confirmed: for
    #: ``confirm_updates`` filter updates in a row the filter stays converged and its pose, hill-climbed on the
    #: scan, explains the scan better by at least ``confirm_margin`` (log-likelihood, nats) than any other pose found
    #: for it: the best of ``global_localization_particles`` uniform poses (hill-climbed) and the track held before
    #: the loss, carried by odometry, farther than ``confirm_exclude_m`` or turned by more than
    #: ``confirm_exclude_rad``. Until then the verdict stays lost (nav holds the robot); a clearly better pose
    #: (by the margin) moves the particles there to be confirmed in turn. A self-similar building gives several
    #: poses of about the same likelihood: none is confirmed, and the recovery ends saying it cannot relocalize.
    #: After a loss the pose must also explain the scans nearly as well as the track did: its log-likelihood per beam
    #: (hill-climbed) at most ``fit_drop`` nats below the median over the last ``fit_window`` tracking
    #: updates (a pose in the wrong place fits a scan of a real building loosely, beams centimetres off all round).
    #: The same test guards the spread: particles spread beyond ``lost_spread_m`` (injected ones that found other
    #: poses fitting the scan) make a tracking filter lost only when its pose no longer fits that well
    confirm_updates: int = 5
    confirm_margin: float = 3.0
    fit_drop: float = 0.1
    fit_window: int = 20
    confirm_exclude_m: float = 1.0
    confirm_exclude_rad: float = 0.5
    #: a low scan match alone does not make a tracking filter lost: a scan placed at a pose odometry has already
    #: moved past (stamped or delivered late under load) scores low while the track is right. The score says lost
    #: only when the evidence is sustained and the track itself no longer fits: on every scan while the robot travels
    #: ``lost_evidence_m`` or turns ``lost_evidence_rad`` (standing still: for ``lost_evidence_s``), whichever comes
    #: first, the median score stays below ``lost_score`` and the held pose, hill-climbed on that scan (a local
    #: re-fit), explains it worse by more than ``fit_drop`` nats per beam than the track's median over the last
    #: ``fit_window`` tracking updates. The re-fit also starts from the poses odometry held over the last
    #: ``lost_refit_history_s`` (map_odom ∘ each; a scan that arrived late was taken at one of them, and when a turn
    #: starts the held pose is off by the turn rate times the lag, beyond one climb's reach)
    lost_evidence_m: float = 0.05
    lost_evidence_rad: float = 0.1
    lost_evidence_s: float = 0.2
    lost_refit_history_s: float = 1.5
    #: half of the search's candidates lie within this distance (m) of the pose: a repetitive building (a row of
    #: bays, offices, shelves) repeats itself next door first, and a large map leaves the neighbourhood sparse
    confirm_near_m: float = 15.0
    #: rivals kept from one confirmation check to the next (carried by odometry, climbed again on each scan)
    confirm_rivals: int = 16

    def validate(self) -> None:
        """Raise ValueError naming the first bad parameter."""
        if not 1 <= self.min_particles <= self.max_particles:
            raise ValueError(f"need 1 <= min_particles ({self.min_particles}) <= max_particles ({self.max_particles})")
        checks = {
            "pf_err": self.pf_err > 0, "pf_z": self.pf_z > 0, "resample_interval": self.resample_interval >= 1,
            "max_beams": self.max_beams >= 2, "sigma_hit": self.sigma_hit > 0,
            "laser_likelihood_max_dist": self.laser_likelihood_max_dist > 0,
            "z_hit": self.z_hit >= 0, "z_rand": self.z_rand >= 0,
            "recovery_alpha_slow": 0 <= self.recovery_alpha_slow <= 1,
            "recovery_alpha_fast": 0 <= self.recovery_alpha_fast <= 1,
            "update_min_d": self.update_min_d >= 0, "update_min_a": self.update_min_a >= 0,
            "global_localization_temperature": self.global_localization_temperature >= 1,
            "global_localization_cooling": 0 < self.global_localization_cooling <= 1,
            "global_localization_jitter_xy_m": self.global_localization_jitter_xy_m >= 0,
            "global_localization_jitter_theta_rad": self.global_localization_jitter_theta_rad >= 0,
            "match_distance_m": self.match_distance_m > 0, "match_window": self.match_window >= 1,
            "match_min_beams": self.match_min_beams >= 1,
            "lost_score": 0 <= self.lost_score <= self.track_score, "track_score": self.track_score <= 1,
            "lost_spread_m": self.lost_spread_m >= self.track_spread_m, "track_spread_m": self.track_spread_m > 0,
            "local_recovery_attempts": self.local_recovery_attempts >= 0,
            "local_recovery_radius_m": self.local_recovery_radius_m > 0,
            "recovery_attempt_s": self.recovery_attempt_s > 0, "global_recovery_s": self.global_recovery_s > 0,
            "recovery_update_period_s": self.recovery_update_period_s >= 0,
            "tracking_injection_min": 0 <= self.tracking_injection_min <= 1,
            "confirm_updates": self.confirm_updates >= 0, "confirm_margin": self.confirm_margin >= 0,
            "fit_drop": self.fit_drop >= 0, "fit_window": self.fit_window >= 1,
            "confirm_rivals": self.confirm_rivals >= 0, "confirm_exclude_m": self.confirm_exclude_m > 0,
            "confirm_exclude_rad": self.confirm_exclude_rad > 0, "confirm_near_m": self.confirm_near_m >= 0,
            "lost_evidence_m": self.lost_evidence_m >= 0, "lost_evidence_rad": self.lost_evidence_rad >= 0,
            "lost_evidence_s": self.lost_evidence_s >= 0, "lost_refit_history_s": self.lost_refit_history_s >= 0,
        }
        for i in range(1, 6):
            checks[f"alpha{i}"] = getattr(self, f"alpha{i}") >= 0
        for name, ok in checks.items():
            value = getattr(self, name)
            if not ok or not math.isfinite(value):
                raise ValueError(f"AMCL parameter {name} = {value!r} is out of range")


def beam_indices(n_ranges: int, max_beams: int) -> np.ndarray:
    """Nav2/amcl beam subsampling: every ``step = (n - 1) // (max_beams - 1)`` th beam (at least 1)."""
    step = max(1, (n_ranges - 1) // max(1, max_beams - 1))
    return np.arange(0, n_ranges, step)


def kld_limit(k: int, pf_err: float, pf_z: float, min_particles: int, max_particles: int) -> int:
    """pf.c's ``pf_resample_limit``: particles needed for ``k`` occupied bins (Wilson-Hilferty approximation).

    One bin needs no more than ``min_particles`` (the chi-square bound is 0); pf.c returns ``max_particles`` there,
    which makes a tightly converged filter the most expensive one.
    """
    if k <= 1:
        return min_particles
    b = 2.0 / (9.0 * (k - 1))
    x = 1.0 - b + math.sqrt(b) * pf_z
    n = math.ceil((k - 1) / (2.0 * pf_err) * x * x * x)
    return min(max(n, min_particles), max_particles)


def _corner_any_all(cells: np.ndarray, pad: bool) -> tuple[np.ndarray, np.ndarray]:
    """For each cell corner (height + 1, width + 1): whether any / all of its four cells are set (``pad``: the cells
    beyond the map count as set)."""
    padded = np.pad(cells, 1, constant_values=pad)
    quads = (padded[:-1, :-1], padded[1:, :-1], padded[:-1, 1:], padded[1:, 1:])
    return quads[0] | quads[1] | quads[2] | quads[3], quads[0] & quads[1] & quads[2] & quads[3]


def _surface_distance(surface: np.ndarray, resolution: float, max_dist: float, less_half_cell: bool = True
                      ) -> np.ndarray:
    """Distance (m, capped at ``max_dist``) from each corner to the nearest ``surface`` corner, by default less half a
    cell, as amcl's per-cell field effectively has: the next corners score as a hit half a cell off, which keeps the
    field as forgiving (and a recovering filter as able to find the robot) when looked up at the nearest corner."""
    if not surface.any():
        return np.full(surface.shape, max_dist)
    d = gridops.distance_transform_edt(~surface) * resolution
    if less_half_cell:
        d = np.maximum(d - 0.5 * resolution, 0.0)
    clipped: np.ndarray = np.minimum(d, max_dist)
    return clipped


class LikelihoodField:
    """Per-corner ``pz^3`` (``likelihood_field``) or ``log pz`` (``likelihood_field_prob``), padded by one corner
    that holds the beyond-the-map value.

    The field lives on the lattice of cell *corners*: corner (i, j) sits at origin + (j, i) * resolution, and a beam
    endpoint looks up its nearest corner. An occupied cell's surface is its boundary with a cell that is not
    occupied, i.e. a line through corners, so a corner on it has distance 0 and the lookup's ±res/2 plateau is
    centred on the wall. (A per-cell field puts the minimum at the centre of the wall cell, res/2 behind the
    surface, and pulls every estimate res/2 towards the walls it sees: 2.5 cm on a 5 cm map.) Distances are
    measured to the surface from both sides, so a beam ending deep inside a solid block scores like one ending
    short of it (rendered worlds are solid outside their free space; thin-walled maps give amcl's field).
    """

    def __init__(self, grid: OccupancyMap, params: AmclParams) -> None:
        self.grid = grid
        occupied = grid.data >= OCCUPIED_MIN
        open_ = np.pad(~occupied, 1, constant_values=False)
        #: the occupied cells with an edge on a cell that is not occupied (a wall's first layer, where scans hit it)
        self.first_layer = occupied & (open_[:-2, 1:-1] | open_[2:, 1:-1] | open_[1:-1, :-2] | open_[1:-1, 2:])
        #: the occupied cells behind the first layer: a beam that crosses one went through a wall
        self.wall_interior = occupied & ~self.first_layer
        #: the occupied cells
        self.occupied = occupied
        # the four cells around each corner; beyond the map counts as occupied (no surface along the map edge)
        occupied_any, occupied_all = _corner_any_all(occupied, pad=True)
        #: distance (m) from each corner to the nearest surface of an occupied cell (where it meets a cell that is
        #: not occupied)
        self._occupied_surface = occupied_any & ~occupied_all
        self.obstacle_distance_m = _surface_distance(self._occupied_surface, grid.resolution,
                                                     params.laser_likelihood_max_dist)
        self.max_dist = params.laser_likelihood_max_dist
        free, unknown = grid.data == FREE, grid.data == UNKNOWN
        free_any, _ = _corner_any_all(free, pad=False)
        unknown_any, _ = _corner_any_all(unknown, pad=False)
        #: corners with an unknown cell among their four (map-edge padding excluded)
        self.near_unknown = unknown_any
        #: distance (m) from each corner to the nearest edge of free space where it meets unknown space
        self._edge_surface = free_any & unknown_any
        self.edge_distance_m = _surface_distance(self._edge_surface, grid.resolution, self.max_dist)
        if params.unknown_distance_m >= 0.0:
            # A SLAM map draws a wall as occupied cells only where its beams hit it often enough; elsewhere (grazing
            # angles, dark or thin surfaces, the map's outline) known free space simply ends where the beams ended.
            # That edge is a surface too: a beam ending on it is explained. A beam ending deeper in space the map
            # never saw is no evidence against the pose: it scores as one ending unknown_distance_m from a wall.
            # Without the edge, the few beams that pin a pose along a corridor can prefer a pose 0.15 m off the
            # truth (one beam on such an edge, scored at unknown_distance_m, outweighed the rest).
            d = np.minimum(self.obstacle_distance_m, self.edge_distance_m)
            self.distance_m = np.where(self.near_unknown, np.minimum(d, params.unknown_distance_m), d)
        else:
            self.distance_m = self.obstacle_distance_m
        self.params = params
        self._range_max: float | None = None
        self.table = np.empty((grid.height + 3, grid.width + 3), dtype=np.float32)
        self.flat = self.table.reshape(-1)

    def exact_distance_m(self) -> np.ndarray:
        """The field's distances (m) without the half-cell allowance, for interpolation between corners (computed on
        first use): exact distance to the nearest surface, capped like ``distance_m``."""
        if getattr(self, "_exact", None) is None:
            res, cap, p = self.grid.resolution, self.max_dist, self.params
            d = _surface_distance(self._occupied_surface, res, cap, less_half_cell=False)
            if p.unknown_distance_m >= 0.0:
                d = np.minimum(d, _surface_distance(self._edge_surface, res, cap, less_half_cell=False))
                d = np.where(self.near_unknown, np.minimum(d, p.unknown_distance_m), d)
            self._exact = d.astype(np.float32)
        return self._exact

    def band_distance_m(self) -> np.ndarray:
        """Like ``exact_distance_m``, but zero over the whole first layer of every wall (the ``first_layer`` cells)
        instead of only on its free face: the refinement's field (computed on first use). A map built from scans marks
        the cell a hit fell in, so the surface lies somewhere inside that cell, not on its free face. Refinement on a
        map built from scans at the true poses (the corridor world, 7 goal poses), free faces -> first layer:
        3.5-5.8 cm -> 0-0.4 cm from the truth; on the rendered world itself 0.4-1.1 cm -> 0.3-1.1 cm."""
        if getattr(self, "_band", None) is None:
            res, cap, p = self.grid.resolution, self.max_dist, self.params
            layer_corners, _ = _corner_any_all(self.first_layer, pad=False)
            d = _surface_distance(layer_corners, res, cap, less_half_cell=False)
            if p.unknown_distance_m >= 0.0:
                d = np.minimum(d, _surface_distance(self._edge_surface, res, cap, less_half_cell=False))
                d = np.where(self.near_unknown, np.minimum(d, p.unknown_distance_m), d)
            self._band = d.astype(np.float32)
        return self._band

    def refinement_fields(self, map_surface: str) -> tuple[np.ndarray, np.ndarray]:
        """The refinement's distance field and the cells its pass-through check counts as a wall's inside, for
        ``AmclParams.map_surface``: ``face``, the distance to the occupied cells' free faces and every occupied cell;
        ``cell``, the distance to a wall's first layer and the cells behind it (a beam may end anywhere in the first
        layer, which on a map built from scans is one to two cells deep)."""
        if map_surface == "cell":
            return self.band_distance_m(), self.wall_interior
        return self.exact_distance_m(), self.occupied

    def prepare(self, range_max: float) -> None:
        """(Re)build the table for a sensor whose maximum range is ``range_max`` m (z_rand's density)."""
        if self._range_max == range_max:
            return
        p = self.params
        rand = p.z_rand / range_max if range_max > 0 else 0.0
        pz = p.z_hit * np.exp(-(self.distance_m ** 2) / (2.0 * p.sigma_hit ** 2)) + rand
        outside = p.z_hit * math.exp(-(self.max_dist ** 2) / (2.0 * p.sigma_hit ** 2)) + rand
        if p.laser_model_type == "likelihood_field_prob":
            self.table.fill(math.log(max(outside, 1e-300)))
            self.table[1:-1, 1:-1] = np.log(np.maximum(pz, 1e-300))
        else:
            self.table.fill(outside ** 3)
            self.table[1:-1, 1:-1] = pz ** 3
        self._range_max = range_max


@dataclass
class Estimate:
    """The filter's pose (x, y, theta) with its 3x3 covariance, the cluster's weight and the particle count."""

    pose: tuple[float, float, float]
    covariance: np.ndarray
    weight: float
    particles: int
    #: sqrt(var x + var y) of the whole weighted particle set (m): small when the filter has one tight hypothesis
    spread_m: float = 0.0


@dataclass(frozen=True)
class RestMove:
    """One Metropolis-Hastings move per particle in place of a sensor update, for scans taken at rest
    (services/localization/settle.py): proposal x' = x + N(0, scale² Σ + diag(min_step_xy_m², min_step_xy_m²,
    min_step_rad²)), Σ the particles' own covariance (the proposal takes the shape of the cloud: a few millimetres
    across a corridor, decimetres along it), accepted with probability min(1, π(x')/π(x)) for π(x) ∝ p₀(x)·L(x),
    L the scan's likelihood and p₀ the Gaussian N(prior_mean, prior_covariance) (flat when None). scale = 2.38/√3
    is the random-walk Metropolis optimum for a 3-D Gaussian target."""

    scale: float = 2.38 / math.sqrt(3.0)
    min_step_xy_m: float = 0.002
    min_step_rad: float = 0.002
    prior_mean: np.ndarray | None = None
    prior_covariance: np.ndarray | None = None
    #: β in π ∝ p₀·Lᵝ
    likelihood_power: float = 1.0


class ParticleFilter:
    """Particles (x [m], y [m], theta [rad]) in the map frame with normalised weights; buffers preallocated."""

    def __init__(self, grid: OccupancyMap, params: AmclParams, rng: np.random.Generator | None = None) -> None:
        params.validate()
        if abs(grid.origin[2]) >= YAW_EPS_RAD:
            # a yawed map is resampled onto the axis-aligned raster that nav's costmaps use (services/common/grid.py),
            # so that localization and planning see the walls in the same cells
            data, x0, y0 = axis_aligned(grid.data, grid.resolution, grid.origin, fill=UNKNOWN)
            grid = OccupancyMap(data, grid.resolution, (x0, y0, 0.0))
        self.grid = grid
        self.params = params
        self.rng = rng or np.random.default_rng(None if params.random_seed < 0 else params.random_seed)
        self._reseedable = rng is None and params.random_seed >= 0
        self.field = LikelihoodField(grid, params)
        free_rows, free_cols = np.nonzero(grid.data == FREE)
        if free_rows.size == 0:
            raise ValueError("the map has no free cell to place particles in")
        self._free_cells = (free_cols.astype(np.float64), free_rows.astype(np.float64))
        m = params.max_particles
        capacity = max(m, params.global_localization_particles)
        self.poses = np.zeros((capacity, 3))
        self._poses_next = np.zeros((capacity, 3))
        self.weights = np.full(capacity, 1.0 / m)
        self.n = m
        #: likelihoods are raised to 1/temperature (annealing after global localization; 1 = plain AMCL)
        self.temperature = 1.0
        self.w_slow = 0.0
        self.w_fast = 0.0
        #: random-particle injection allowed (the driver turns it off while the filter is tracking)
        self.allow_injection = True
        #: no injection at all, whatever the likelihood does (the at-rest settling after an initial pose: the pose
        #: given is the prior, and a particle dropped on a look-alike place elsewhere would outvote it)
        self.suppress_injection = False
        #: particles whose last ``rest_move`` proposal was accepted
        self.rest_moves_accepted = 0
        self._kld_table = np.array([kld_limit(k, params.pf_err, params.pf_z, params.min_particles, m)
                                    for k in range(m + 1)], dtype=np.int64)
        self._counts = np.arange(1, m + 1)
        self._noise = np.empty((capacity, 3))
        self._percol = np.empty((7, capacity))
        self._beam_capacity = 0
        self._last_beams: tuple[np.ndarray, np.ndarray, tuple[float, float, float]] | None = None
        self._ensure_beam_buffers(params.max_beams + 1)
        self._random_poses(self.poses)

    # ------------------------------------------------------------------ buffers and helpers

    def _ensure_beam_buffers(self, beams: int) -> None:
        if beams <= self._beam_capacity:
            return
        size = self.params.max_particles * beams
        # float32 endpoints (grid cells; 1e-4 cell precision) halve the memory traffic of the N x B passes
        self._bx = np.empty(size, dtype=np.float32)
        self._by = np.empty(size, dtype=np.float32)
        self._tmp = np.empty(size, dtype=np.float32)
        self._ix = np.empty(size, dtype=np.intp)
        self._iy = np.empty(size, dtype=np.intp)
        self._vals = np.empty(size, dtype=np.float32)
        self._beam_capacity = beams

    def _random_poses(self, out: np.ndarray) -> None:
        """Fill ``out`` (k x 3) with poses uniform over the map's free cells and headings."""
        k = out.shape[0]
        if k == 0:
            return
        cols, rows = self._free_cells
        pick = self.rng.integers(0, cols.size, size=k)
        jitter = self.rng.random((k, 2))
        x, y = self.grid.cell_to_world(cols[pick] + jitter[:, 0] - 0.5, rows[pick] + jitter[:, 1] - 0.5)
        out[:, 0] = x
        out[:, 1] = y
        out[:, 2] = self.rng.uniform(-math.pi, math.pi, size=k)

    def _random_poses_near(self, out: np.ndarray, center: tuple[float, float, float], radius_m: float) -> None:
        """Fill ``out`` (k x 3) with poses uniform over the free cells within ``radius_m`` of ``center`` (any
        heading); over all free space when none is that close."""
        cols, rows = self._free_cells
        x, y = self.grid.cell_to_world(cols, rows)
        near = np.nonzero((x - center[0]) ** 2 + (y - center[1]) ** 2 <= radius_m * radius_m)[0]
        k = out.shape[0]
        if near.size == 0 or k == 0:
            self._random_poses(out)
            return
        pick = near[self.rng.integers(0, near.size, size=k)]
        jitter = self.rng.random((k, 2)) - 0.5
        out[:, 0], out[:, 1] = self.grid.cell_to_world(cols[pick] + jitter[:, 0], rows[pick] + jitter[:, 1])
        out[:, 2] = self.rng.uniform(-math.pi, math.pi, size=k)

    def _set_uniform_weights(self, n: int) -> None:
        self.n = n
        self.weights[:n] = 1.0 / n

    # ------------------------------------------------------------------ initialisation

    def reseed(self) -> None:
        """With ``random_seed`` >= 0 (and no generator of the caller's), restart the generator from the seed: the
        filter's state after a (re)initialisation then depends only on the inputs since, whatever came before, so a
        replay of a recording that holds the initialisation reproduces the filter exactly."""
        if self._reseedable:
            self.rng = np.random.default_rng(self.params.random_seed)

    def init_gaussian(self, pose: tuple[float, float, float], covariance: np.ndarray) -> None:
        """``max_particles`` particles drawn from N(pose, covariance) (3x3 over x, y, theta)."""
        cov = np.asarray(covariance, dtype=np.float64).reshape(3, 3)
        cov = 0.5 * (cov + cov.T)
        vals, vecs = np.linalg.eigh(cov)
        if not np.all(np.isfinite(vals)) or vals.min() < -1e-12:
            raise ValueError(f"initial covariance is not positive semi-definite: {cov.tolist()}")
        n = self.params.max_particles
        draws = self.rng.standard_normal((n, 3)) * np.sqrt(np.clip(vals, 0.0, None))
        self.poses[:n] = np.asarray(pose, dtype=np.float64) + draws @ vecs.T
        self.poses[:n, 2] = wrap_angle(self.poses[:n, 2])
        self._set_uniform_weights(n)
        self.w_slow = self.w_fast = 0.0
        self.temperature = 1.0  # a pose given by hand ends any annealing of an earlier global localization

    def init_uniform(self) -> None:
        """Global localization: ``global_localization_particles`` (at least ``max_particles``) particles uniform over
        free space; the next resampling brings the population back within [min_particles, max_particles]."""
        n = max(self.params.max_particles, self.params.global_localization_particles)
        self._random_poses(self.poses[:n])
        self._set_uniform_weights(n)
        self.w_slow = self.w_fast = 0.0
        self.temperature = self.params.global_localization_temperature

    def init_around(self, center: tuple[float, float], radius_m: float) -> int:
        """Local relocalization: ``global_localization_particles`` poses uniform over the free cells within
        ``radius_m`` of ``center`` (any heading), annealed like a global localization; returns how many."""
        cols, rows = self._free_cells
        x, y = self.grid.cell_to_world(cols, rows)
        near = np.nonzero((x - center[0]) ** 2 + (y - center[1]) ** 2 <= radius_m * radius_m)[0]
        if near.size == 0:
            self.init_uniform()
            return self.n
        n = max(self.params.max_particles, self.params.global_localization_particles)
        pick = near[self.rng.integers(0, near.size, size=n)]
        jitter = self.rng.random((n, 2)) - 0.5
        px, py = self.grid.cell_to_world(cols[pick] + jitter[:, 0], rows[pick] + jitter[:, 1])
        self.poses[:n, 0] = px
        self.poses[:n, 1] = py
        self.poses[:n, 2] = self.rng.uniform(-math.pi, math.pi, size=n)
        self._set_uniform_weights(n)
        self.w_slow = self.w_fast = 0.0
        self.temperature = self.params.global_localization_temperature
        return n

    def explained_fraction(self, pose: tuple[float, float, float], ranges: np.ndarray, bearings: np.ndarray,
                           mount: tuple[float, float, float]) -> float:
        """Scan match score at ``pose``: hits / (hits + misses) over the beams, where a hit ends within
        ``match_distance_m`` of an obstacle or of free space's edge with unknown space (the field's distances at
        the nearest corner) and a miss ends in known space farther from any (or beyond the map). Beams that end in
        unknown cells are neither: the map cannot say (on a real SLAM map most beams of a campus end there). NaN
        when fewer than ``match_min_beams`` beams are hits or misses."""
        if ranges.size == 0:
            return math.nan
        grid = self.grid
        lx, ly, lth = compose(pose, mount)
        ex = lx + ranges * np.cos(lth + bearings) - grid.origin[0]
        ey = ly + ranges * np.sin(lth + bearings) - grid.origin[1]
        c0, s0 = math.cos(grid.origin[2]), math.sin(grid.origin[2])
        u = (c0 * ex + s0 * ey) / grid.resolution
        v = (-s0 * ex + c0 * ey) / grid.resolution
        dist = self.field.distance_m
        # an endpoint past the map's edge is judged at the edge, plus its distance beyond it (the edge can be a
        # surface, and range noise puts a beam that hit it a centimetre past it)
        uc, vc = np.clip(u, 0.0, dist.shape[1] - 1.0), np.clip(v, 0.0, dist.shape[0] - 1.0)
        beyond_m = np.hypot(u - uc, v - vc) * grid.resolution
        gx = np.floor(uc + 0.5).astype(np.intp)
        gy = np.floor(vc + 0.5).astype(np.intp)
        inside = beyond_m <= self.params.match_distance_m
        hits = np.zeros(ranges.size, dtype=bool)
        unknown = np.zeros(ranges.size, dtype=bool)
        surface_m = np.minimum(self.field.obstacle_distance_m[gy[inside], gx[inside]],
                               self.field.edge_distance_m[gy[inside], gx[inside]]) + beyond_m[inside]
        hits[inside] = surface_m <= self.params.match_distance_m
        unknown[inside] = self.field.near_unknown[gy[inside], gx[inside]] & ~hits[inside]
        judged = int(ranges.size - np.count_nonzero(unknown))
        if judged < self.params.match_min_beams:
            return math.nan
        return float(np.count_nonzero(hits)) / judged

    # ------------------------------------------------------------------ motion

    def motion_update(self, odom_pose: tuple[float, float, float], delta: tuple[float, float, float]) -> None:
        """Omni-corrected model: ``delta`` = (dx, dy, dtheta) of odometry in the odom frame, ending at ``odom_pose``.

        sigma_trans = sqrt(a3 t^2 + a4 r^2), sigma_rot = sqrt(a1 r^2 + a2 t^2), sigma_strafe = sqrt(a4 r^2 +
        a5 t^2); each particle moves by the noisy translation along its bearing plus a noisy strafe across it.
        """
        p = self.params
        dx, dy, dth = delta
        trans2 = dx * dx + dy * dy
        rot2 = dth * dth
        sd = np.array([math.sqrt(p.alpha3 * trans2 + p.alpha4 * rot2),
                       math.sqrt(p.alpha1 * rot2 + p.alpha2 * trans2),
                       math.sqrt(p.alpha4 * rot2 + p.alpha5 * trans2)])
        n = self.n
        noise = self._noise[:n]
        self.rng.standard_normal(out=noise)
        noise *= sd
        trans_hat = noise[:, 0]
        trans_hat += math.sqrt(trans2)
        old_theta = odom_pose[2] - dth
        bearing = self._percol[0, :n]
        np.add(self.poses[:n, 2], wrap_angle(math.atan2(dy, dx) - old_theta), out=bearing)
        cb, sb = self._percol[1, :n], self._percol[2, :n]
        np.cos(bearing, out=cb)
        np.sin(bearing, out=sb)
        strafe = noise[:, 2]
        x, y, th = self.poses[:n, 0], self.poses[:n, 1], self.poses[:n, 2]
        x += trans_hat * cb + strafe * sb
        y += trans_hat * sb - strafe * cb
        th += noise[:, 1]
        th += dth
        self.poses[:n, 2] = wrap_angle(th)

    # ------------------------------------------------------------------ sensor

    def use_scan(self, ranges: np.ndarray, bearings: np.ndarray, mount: tuple[float, float, float],
                 range_max: float) -> None:
        """Make this scan (valid beams: range m, bearing rad in the laser frame) the one ``scan_log_likelihood``,
        ``climb`` and the recovery's sensor resetting score poses on."""
        self._ensure_beam_buffers(int(ranges.size))
        self.field.prepare(range_max)
        res = self.grid.resolution
        rc = (ranges * np.cos(bearings) / res).astype(np.float32)
        rs = (ranges * np.sin(bearings) / res).astype(np.float32)
        self._last_beams = (rc, rs, mount)

    def sensor_update(self, ranges: np.ndarray, bearings: np.ndarray, mount: tuple[float, float, float],
                      range_max: float) -> float:
        """Weight particles by the likelihood field for beams (range m, bearing rad in the laser frame).

        ``ranges``/``bearings`` must already be subsampled and valid (finite, inside the range limits).
        Returns the per-beam mean likelihood that feeds the recovery filters (w_slow, w_fast).
        """
        p = self.params
        n = self.n
        b = int(ranges.size)
        if b == 0:
            return 0.0
        self.use_scan(ranges, bearings, mount, range_max)
        like = self._percol[5, :n]
        self._likelihood_sums(self.poses, n, like)
        if p.laser_model_type == "likelihood_field_prob":
            # product of beam likelihoods, exp(sum log pz), shifted by its maximum to stay in range
            log_max = float(like.max())
            like -= log_max
            if self.temperature > 1.0:
                like /= self.temperature
            np.exp(like, out=like)
        else:
            like += 1.0
            if self.temperature > 1.0:
                np.power(like, 1.0 / self.temperature, out=like)
        tempered = self.temperature > 1.0
        self.temperature = max(1.0, self.temperature * p.global_localization_cooling)
        w = self.weights[:n]
        w *= like
        total = float(w.sum())
        if not math.isfinite(total) or total <= 0.0:
            self._set_uniform_weights(n)
            return 0.0
        w /= total
        # weights of hopeless particles underflow towards subnormal numbers, which make every later operation on
        # them ~100x slower: flush them to zero
        w[w < 1e-200] = 0.0
        # w_avg per beam, so that the recovery filters compare scans with different numbers of valid returns:
        # the weighted mean of pz^3 per beam, or the per-beam geometric mean of pz for the product model
        if p.laser_model_type == "likelihood_field_prob":
            w_avg = math.exp((log_max + math.log(total)) / b)
        else:
            w_avg = (total - 1.0) / b
        self._follow_likelihood_level(w_avg, tempered)
        return w_avg

    def _follow_likelihood_level(self, w_avg: float, tempered: bool) -> None:
        """Move the recovery averages w_slow, w_fast towards this scan's per-beam likelihood ``w_avg``."""
        p = self.params
        if tempered:
            # annealed weights say nothing of how well the map explains the scan: the recovery averages start
            # from the first plain update (else w_slow keeps the level of the uniform start, far below tracking,
            # and a later kidnapping never pulls w_fast under it)
            self.w_slow = self.w_fast = 0.0
        elif self.w_slow == 0.0:
            self.w_slow = self.w_fast = w_avg
        else:
            self.w_slow += p.recovery_alpha_slow * (w_avg - self.w_slow)
            self.w_fast += p.recovery_alpha_fast * (w_avg - self.w_fast)

    def rest_move(self, ranges: np.ndarray, bearings: np.ndarray, mount: tuple[float, float, float],
                  range_max: float, move: RestMove) -> float:
        """A scan taken where the last one was (the robot at rest): one Metropolis-Hastings move per particle
        towards p₀·L (``RestMove``), weights uniform after it. A sensor update would multiply the weights by L
        once more: after k scans at rest the population follows Lᵏ, as if each scan of the same view were new
        evidence, and sharpens onto whatever small bump of the likelihood a map's cells put along a direction the
        scan cannot fix (a corridor: 0.1-0.2 m off, with a spread of millimetres). Here the target stays one scan's
        worth of likelihood times the prior, whatever the number of scans. Returns the per-beam mean likelihood
        (as ``sensor_update``) for the recovery averages."""
        n = self.n
        b = int(ranges.size)
        if b == 0 or n == 0:
            return 0.0
        self.use_scan(ranges, bearings, mount, range_max)
        current = self.poses[:n]
        centred = current - current.mean(axis=0)
        mean_heading = math.atan2(float(np.sin(current[:, 2]).mean()), float(np.cos(current[:, 2]).mean()))
        centred[:, 2] = wrap_angle(current[:, 2] - mean_heading)
        spread = (centred.T @ centred) / n * move.scale**2
        spread += np.diag([move.min_step_xy_m**2, move.min_step_xy_m**2, move.min_step_rad**2])
        try:
            factor = np.linalg.cholesky(spread)
        except np.linalg.LinAlgError:
            factor = np.diag(np.sqrt(np.maximum(np.diag(spread), 0.0)))
        proposed = current + self.rng.standard_normal((n, 3)) @ factor.T
        proposed[:, 2] = wrap_angle(proposed[:, 2])
        ll_current = self.scan_log_likelihood(current)
        ll_proposed = self.scan_log_likelihood(proposed)
        log_ratio = move.likelihood_power * (ll_proposed - ll_current)
        if move.prior_mean is not None and move.prior_covariance is not None:
            before = gaussian_log_density(current, move.prior_mean, move.prior_covariance)
            after = gaussian_log_density(proposed, move.prior_mean, move.prior_covariance)
            if before is not None and after is not None:
                log_ratio += after - before
        with np.errstate(invalid="ignore"):
            accept = np.log(self.rng.random(n)) < log_ratio
        current[accept] = proposed[accept]
        ll = np.where(accept, ll_proposed, ll_current)
        self._set_uniform_weights(n)
        self.rest_moves_accepted = int(np.count_nonzero(accept))
        if self.params.laser_model_type == "likelihood_field_prob":
            top = float(ll.max())
            w_avg = math.exp((top + math.log(float(np.mean(np.exp(ll - top))))) / b)
        else:
            w_avg = (float(np.mean(np.exp(ll))) - 1.0) / b
        self._follow_likelihood_level(w_avg, False)
        return w_avg

    def _likelihood_sums(self, poses: np.ndarray, n: int, out: np.ndarray) -> None:
        """Per-pose sums over the last scan's beams for poses[:n], in chunks of max_particles (buffer size)."""
        assert self._last_beams is not None
        rc, rs, mount = self._last_beams
        chunk = self.params.max_particles
        for start in range(0, n, chunk):
            stop = min(n, start + chunk)
            self._beam_sums(poses, start, stop, rc, rs, mount, out[start:stop])

    def _beam_sums(self, poses: np.ndarray, start: int, stop: int, rc: np.ndarray, rs: np.ndarray,
                   mount: tuple[float, float, float], out: np.ndarray) -> None:
        """Sum of the table values at the beam endpoints of poses start..stop-1 (beams in grid cells)."""
        grid = self.grid
        res = grid.resolution
        ox, oy, oyaw = grid.origin
        c0, s0 = math.cos(oyaw), math.sin(oyaw)
        mx, my, mth = mount
        n = stop - start
        b = rc.size
        # laser pose of each particle, in corner-lattice units
        th = poses[start:stop, 2]
        cth, sth = self._percol[0, :n], self._percol[1, :n]
        np.cos(th, out=cth)
        np.sin(th, out=sth)
        lx = poses[start:stop, 0] + cth * mx - sth * my - ox
        ly = poses[start:stop, 1] + sth * mx + cth * my - oy
        # nearest corner = floor(cell coordinate + 0.5); +1 for the padding border
        gx = (c0 * lx + s0 * ly) / res + 1.5
        gy = (-s0 * lx + c0 * ly) / res + 1.5
        ga = self._percol[2, :n]
        np.add(th, mth - oyaw, out=ga)
        cga, sga = self._percol[3, :n], self._percol[4, :n]
        np.cos(ga, out=cga)
        np.sin(ga, out=sga)
        cga, sga = cga.astype(np.float32), sga.astype(np.float32)
        gx, gy = gx.astype(np.float32), gy.astype(np.float32)
        size = n * b
        bx = self._bx[:size].reshape(n, b)
        by = self._by[:size].reshape(n, b)
        tmp = self._tmp[:size].reshape(n, b)
        ix = self._ix[:size].reshape(n, b)
        iy = self._iy[:size].reshape(n, b)
        vals = self._vals[:size].reshape(n, b)
        # endpoint = laser + R(ga) (rc, rs)
        np.multiply(cga[:, None], rc[None, :], out=bx)
        np.multiply(sga[:, None], rs[None, :], out=tmp)
        bx -= tmp
        bx += gx[:, None]
        np.multiply(sga[:, None], rc[None, :], out=by)
        np.multiply(cga[:, None], rs[None, :], out=tmp)
        by += tmp
        by += gy[:, None]
        width2 = grid.width + 3
        np.clip(bx, 0.0, width2 - 1.0, out=bx)
        np.clip(by, 0.0, grid.height + 2.0, out=by)
        np.copyto(ix, bx, casting="unsafe")
        np.copyto(iy, by, casting="unsafe")
        iy *= width2
        iy += ix
        np.take(self.field.flat, iy, out=vals)
        np.sum(vals, axis=1, out=out)

    # ------------------------------------------------------------------ resampling

    def injection_probability(self) -> float:
        """max(0, 1 - w_fast / w_slow): the share of random particles the next resampling draws."""
        if self.w_slow <= 0.0 or self.params.recovery_alpha_slow <= 0.0 or self.params.recovery_alpha_fast <= 0.0:
            return 0.0
        return max(0.0, 1.0 - self.w_fast / self.w_slow)

    def _recovery_poses(self, k: int) -> np.ndarray:
        """``k`` random poses for recovery: uniform over free space, or (``recovery_sensor_reset``) drawn from
        ``global_localization_particles`` uniform candidates in proportion to their likelihood for the last scan."""
        p = self.params
        candidates = max(k, p.global_localization_particles)
        if not p.recovery_sensor_reset or self._last_beams is None or candidates <= k:
            out = np.empty((k, 3))
            self._random_poses(out)
            return out
        poses = np.empty((candidates, 3))
        self._random_poses(poses)
        sums = np.empty(candidates)
        self._likelihood_sums(poses, candidates, sums)
        if p.laser_model_type == "likelihood_field_prob":
            weights = np.exp(sums - sums.max())
        else:
            weights = sums + 1.0
        cumulative = np.cumsum(weights)
        picks = np.searchsorted(cumulative, self.rng.random(k) * cumulative[-1], side="right")
        picked: np.ndarray = poses[np.minimum(picks, candidates - 1)]
        return picked

    @property
    def last_beam_count(self) -> int:
        """Beams of the last sensor update (0 before the first)."""
        return 0 if self._last_beams is None else int(self._last_beams[0].size)

    def keep_near(self, pose: tuple[float, float, float], radius_m: float) -> int:
        """Replace the particles farther than ``radius_m`` from ``pose`` by copies of random ones within it (weights
        uniform); returns how many were replaced (none when no particle is within the radius)."""
        n = self.n
        d = np.hypot(self.poses[:n, 0] - pose[0], self.poses[:n, 1] - pose[1])
        near, far = np.nonzero(d <= radius_m)[0], np.nonzero(d > radius_m)[0]
        if near.size == 0 or far.size == 0:
            return 0
        self.poses[far] = self.poses[near[self.rng.integers(0, near.size, size=far.size)]]
        self._set_uniform_weights(n)
        return int(far.size)

    def scan_log_likelihood(self, poses: np.ndarray) -> np.ndarray:
        """Log-likelihood of the last scan at each of ``poses`` (k x 3), untempered: sum over beams of log pz
        (``likelihood_field_prob``) or log(1 + sum pz^3) (``likelihood_field``)."""
        k = poses.shape[0]
        sums = np.empty(k)
        if k == 0 or self._last_beams is None:
            return np.full(k, -math.inf)
        self._likelihood_sums(np.ascontiguousarray(poses, dtype=np.float64), k, sums)
        return sums if self.params.laser_model_type == "likelihood_field_prob" else np.log1p(sums)

    def climb(self, poses: np.ndarray, step_m: float = 0.1, step_rad: float = 0.05, steps: int = 8
              ) -> tuple[np.ndarray, np.ndarray]:
        """Hill-climb each pose (k x 3) on the last scan's log-likelihood: each step tries the 27 moves of
        (-s, 0, +s) per axis and keeps the best; a pose whose best move is to stay halves its steps. Returns the
        climbed poses and their log-likelihoods."""
        k = poses.shape[0]
        cur = np.array(poses, dtype=np.float64).reshape(k, 3)
        best = self.scan_log_likelihood(cur)
        if k == 0:
            return cur, best
        unit = np.array([(i, j, a) for i in (-1, 0, 1) for j in (-1, 0, 1) for a in (-1, 0, 1)], dtype=np.float64)
        scale = np.tile([step_m, step_m, step_rad], (k, 1))
        for _ in range(steps):
            trial = (cur[:, None, :] + unit[None, :, :] * scale[:, None, :]).reshape(-1, 3)
            ll = self.scan_log_likelihood(trial).reshape(k, 27)
            pick = np.argmax(ll, axis=1)
            better = ll[np.arange(k), pick] > best
            cur[better] = trial.reshape(k, 27, 3)[better, pick[better]]
            best = np.where(better, ll[np.arange(k), pick], best)
            scale[~better] *= 0.5
        cur[:, 2] = wrap_angle(cur[:, 2])
        return cur, best

    def best_alternative(self, pose: tuple[float, float, float], exclude_m: float, exclude_rad: float,
                         candidates: int, keep: int = 16, seeds: np.ndarray | None = None, near_m: float = 0.0
                         ) -> tuple[np.ndarray, np.ndarray]:
        """Other poses for the last scan, away from ``pose`` (farther than ``exclude_m``, or turned by more than
        ``exclude_rad``): the ``keep`` most likely of ``candidates`` uniform poses over free space (half of them
        within ``near_m`` of ``pose`` when > 0), plus ``seeds``
        (k x 3), all hill-climbed (``climb``). Returns those that stay away, most likely first, with their
        log-likelihoods."""
        if self._last_beams is None:
            return np.zeros((0, 3)), np.zeros(0)
        cand = np.empty((max(candidates, 0), 3))
        self._random_poses(cand)
        if near_m > 0.0:  # half of them near the pose: a repetitive building repeats itself next door first
            self._random_poses_near(cand[: candidates // 2], pose, near_m)
        if candidates > keep:
            ll = self.scan_log_likelihood(cand)
            cand = cand[np.argpartition(-ll, keep - 1)[:keep]]
        if seeds is not None and seeds.size:
            cand = np.vstack([cand, np.asarray(seeds, dtype=np.float64).reshape(-1, 3)])
        climbed, climbed_ll = self.climb(cand)
        far = ((np.hypot(climbed[:, 0] - pose[0], climbed[:, 1] - pose[1]) > exclude_m)
               | (np.abs(wrap_angle(climbed[:, 2] - pose[2])) > exclude_rad))
        order = np.argsort(-climbed_ll[far])
        return climbed[far][order], climbed_ll[far][order]

    def resample(self) -> int:
        """Low-variance resampling with KLD-sampled population size and random injection; returns the new size."""
        p = self.params
        m = p.max_particles
        n = self.n
        cumulative = np.cumsum(self.weights[:n])
        cumulative[-1] = 1.0
        positions = (self.rng.random() + np.arange(m)) / m
        picks = np.searchsorted(cumulative, positions, side="right")
        np.minimum(picks, n - 1, out=picks)
        self.rng.shuffle(picks)  # KLD takes a prefix: it must be a random subset, not the lowest indices
        new = self._poses_next[:m]
        np.take(self.poses, picks, axis=0, out=new)
        w_diff = 0.0 if self.suppress_injection else self.injection_probability()
        if not self.allow_injection and w_diff < self.params.tracking_injection_min:
            w_diff = 0.0
        if w_diff > 0.0:
            inject = np.nonzero(self.rng.random(m) < w_diff)[0]
            if inject.size:
                new[inject] = self._recovery_poses(inject.size)
            # amcl zeroes both averages here, and the next scan restarts them at the level of the (possibly wrong)
            # population: a filter that converged on a wrong pose after a kidnapping then never injects again.
            # Restarting only w_fast from w_slow keeps the level that tracking reached: while the scans still fit
            # worse than that, every update injects a few sensor-reset particles until one lands on the true pose.
            self.w_fast = self.w_slow
        keys = self._bin_keys(new)
        _, first = np.unique(keys, return_index=True)
        is_first = np.zeros(m, dtype=np.int64)
        is_first[first] = 1
        occupied_bins = np.cumsum(is_first)
        done = np.nonzero(self._counts > self._kld_table[occupied_bins])[0]
        count = int(done[0]) + 1 if done.size else m
        count = min(max(count, p.min_particles), m)
        if self.temperature > 1.0:
            self._roughen(new[:count])
        self.poses, self._poses_next = self._poses_next, self.poses
        self._set_uniform_weights(count)
        return count

    def _roughen(self, poses: np.ndarray) -> None:
        """Annealing jitter: poses += N(0, diag(sxy, sxy, sth)) with s = sqrt(temperature) * jitter."""
        p = self.params
        scale = math.sqrt(self.temperature)
        k = poses.shape[0]
        poses[:, :2] += self.rng.standard_normal((k, 2)) * (scale * p.global_localization_jitter_xy_m)
        turn = self.rng.standard_normal(k) * (scale * p.global_localization_jitter_theta_rad)
        poses[:, 2] = wrap_angle(poses[:, 2] + turn)

    @staticmethod
    def _bin_keys(poses: np.ndarray) -> np.ndarray:
        bx = np.floor(poses[:, 0] / BIN_XY_M).astype(np.int64)
        by = np.floor(poses[:, 1] / BIN_XY_M).astype(np.int64)
        bt = np.floor((np.asarray(poses[:, 2]) + math.pi) / BIN_THETA_RAD).astype(np.int64)
        return (bx * 1_000_003 + by) * 64 + bt

    # ------------------------------------------------------------------ estimate

    def estimate(self) -> Estimate:
        """Weighted mean and covariance of the heaviest cluster of adjacent bins (pf_cluster_stats)."""
        n = self.n
        poses, w = self.poses[:n], self.weights[:n]
        labels = cluster_labels(poses)
        count = int(labels.max()) + 1
        weight = np.bincount(labels, weights=w, minlength=count)
        best = int(np.argmax(weight))
        sel = labels == best
        ws = w[sel]
        total = float(ws.sum())
        if total <= 0.0:
            ws = np.full(int(sel.sum()), 1.0)
            total = float(ws.size)
        x, y, th = poses[sel, 0], poses[sel, 1], poses[sel, 2]
        mx, my = float(ws @ x) / total, float(ws @ y) / total
        mc, ms = float(ws @ np.cos(th)) / total, float(ws @ np.sin(th)) / total
        cov = np.zeros((3, 3))
        cov[0, 0] = float(ws @ (x * x)) / total - mx * mx
        cov[1, 1] = float(ws @ (y * y)) / total - my * my
        cov[0, 1] = cov[1, 0] = float(ws @ (x * y)) / total - mx * my
        cov[2, 2] = -2.0 * math.log(max(math.hypot(mc, ms), 1e-12))
        cov[0, 0], cov[1, 1] = max(cov[0, 0], 0.0), max(cov[1, 1], 0.0)
        wall = w if float(w.sum()) > 0.0 else np.full(n, 1.0 / n)
        wsum = float(wall.sum())
        ax, ay = float(wall @ poses[:, 0]) / wsum, float(wall @ poses[:, 1]) / wsum
        var = float(wall @ ((poses[:, 0] - ax) ** 2 + (poses[:, 1] - ay) ** 2)) / wsum
        return Estimate((mx, my, math.atan2(ms, mc)), cov, total, n, math.sqrt(max(var, 0.0)))


def cluster_labels(poses: np.ndarray) -> np.ndarray:
    """Cluster label (0..k-1) of each pose: connected components of occupied KLD bins, 26-neighbourhood, with the
    heading bins wrapping around."""
    nt = int(math.ceil(2.0 * math.pi / BIN_THETA_RAD))
    bx = np.floor(poses[:, 0] / BIN_XY_M).astype(np.int64)
    by = np.floor(poses[:, 1] / BIN_XY_M).astype(np.int64)
    bt = np.clip(np.floor((wrap_angle(poses[:, 2]) + math.pi) / BIN_THETA_RAD).astype(np.int64), 0, nt - 1)
    bx -= bx.min()
    by -= by.min()
    dense = np.zeros((int(bx.max()) + 1, int(by.max()) + 1, nt + 1), dtype=bool)
    dense[bx, by, bt] = True
    dense[:, :, nt] = dense[:, :, 0]
    labels, count = gridops.label(dense)
    parent = np.arange(count + 1)

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = int(parent[i])
        return i

    first, last = labels[:, :, 0], labels[:, :, nt]
    for a, b in set(zip(first[first > 0].tolist(), last[first > 0].tolist(), strict=True)):
        ra, rb = root(a), root(b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    roots = np.array([root(i) for i in range(count + 1)])
    _, compact = np.unique(roots, return_inverse=True)
    cluster_of: np.ndarray = compact[labels[bx, by, bt]] - (1 if count > 0 else 0)
    return cluster_of


@dataclass
class LowScoreEvidence:
    """Scans in a row whose match score is low and on which the held pose no longer fits (``Amcl``'s verdict): when
    the stretch began (s) and how far the robot has travelled (m, path) and turned (rad) since, by odometry."""

    started_s: float
    odom_pose: tuple[float, float, float]
    travelled_m: float = 0.0
    turned_rad: float = 0.0

    def advance(self, odom_pose: tuple[float, float, float]) -> None:
        """Add the odometry motion from the last scan of the stretch to this one."""
        last = self.odom_pose
        self.travelled_m += math.hypot(odom_pose[0] - last[0], odom_pose[1] - last[1])
        self.turned_rad += abs(float(wrap_angle(odom_pose[2] - last[2])))
        self.odom_pose = odom_pose


@dataclass
class ScanBeams:
    """A scan reduced to the beams AMCL uses: ranges (m) and bearings (rad) in the laser frame, and range_max."""

    ranges: np.ndarray
    bearings: np.ndarray
    range_max: float


def gaussian_log_density(poses: np.ndarray, mean: np.ndarray, covariance: np.ndarray) -> np.ndarray | None:
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


def select_beams(ranges: np.ndarray, angle_min: float, angle_increment: float, range_min: float,
                 range_max: float, params: AmclParams, max_beams: int | None = None) -> ScanBeams:
    """Subsample a scan (Nav2's step, for ``max_beams``: default the params') and keep finite returns inside
    (range_min, range_max).

    ``laser_min_range``/``laser_max_range`` > 0 override the scan's limits (as in Nav2).
    """
    ranges = np.asarray(ranges, dtype=np.float64)
    lo = params.laser_min_range if params.laser_min_range > 0 else range_min
    hi = params.laser_max_range if params.laser_max_range > 0 else range_max
    idx = beam_indices(ranges.size, params.max_beams if max_beams is None else max_beams)
    r = ranges[idx]
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r > lo) & (r < hi)
    idx = idx[ok]
    return ScanBeams(ranges[idx], angle_min + idx * angle_increment, float(hi))


class Amcl:
    """The filter's driver: update gates, resample interval, initial pose, global localization, no-motion update,
    and the verdict with its recovery.

    ``process(odom_pose, beams, mount, stamp)`` takes the odometry pose (odom frame) at the scan's time. After a
    filter update, ``estimate`` is the map pose and ``map_odom`` the correction with map pose = map_odom ∘ odom pose.

    Verdict (``state``, every scan, see ``AmclParams``): ``localizing`` → ``tracking`` when the scans fit and the
    particles agree; ``tracking`` → ``lost`` when they stop fitting. Lost starts the recovery: sensor resets around
    ``last_good`` (the last pose judged tracking, or the initial pose), then global localization; ``reason`` says
    where it stands. A filter that is localizing for longer than ``recovery_attempt_s`` without converging (e.g. an
    initial pose 2 m off) is declared lost the same way. A requested global localization is the global stage itself:
    it forgets ``last_good`` and has ``global_recovery_s`` to converge before it starts again.
    """

    #: scan period assumed when ``process`` gets no stamp (s)
    DEFAULT_SCAN_PERIOD_S = 0.04

    def __init__(self, grid: OccupancyMap, params: AmclParams, rng: np.random.Generator | None = None,
                 uncertainty_params: UncertaintyParams | None = None) -> None:
        self.params = params
        self.pf = ParticleFilter(grid, params, rng)
        self.pf_odom_pose: tuple[float, float, float] | None = None
        self.force_update = False
        self.resample_count = 0
        self.updates = 0
        self.estimate: Estimate | None = None
        self.map_odom: tuple[float, float, float] | None = None
        self.state: str = "localizing"
        self.reason = "no pose yet"
        self.match_score = 0.0
        self.spread_m = math.inf
        #: distance (m) between the last update's estimate and the one before carried by odometry: a tracking
        #: filter's estimate moves continuously, and one that jumps farther than ``lost_spread_m`` is lost
        self.jump_m = 0.0
        self.last_good: tuple[float, float, float] | None = None
        #: the initial pose's Gaussian (mean (3,), covariance (3, 3)) the particles were drawn from; None after a
        #: global localization. What the scans cannot fix (along a featureless corridor) only this prior fixes
        self.initial_prior: tuple[np.ndarray, np.ndarray] | None = None
        self.lost_at: float | None = None
        self.lost_reason = ""
        self._scores: list[float] = []
        self._now = 0.0
        self._last_update_at = -math.inf
        self._stage = -1  # -1: none; 0..local_recovery_attempts-1: local resets; local_recovery_attempts: global
        self._stage_started_at = 0.0
        self._updates_since_reset = 0
        #: a converged filter must still be confirmed before it tracks (after a loss or a global localization)
        self.unconfirmed = False
        self._confirmations = 0
        self._confirm_checked_update = -1
        #: map->odom while the verdict last said tracking on a fitting scan (the track held before a loss)
        self._good_map_odom: tuple[float, float, float] | None = None
        self._track_map_odom: tuple[float, float, float] | None = None
        #: log-likelihood per beam of the (hill-climbed) estimate over the last tracking updates; its median at the
        #: loss is the fit a re-localised pose must nearly reach
        self._fits: collections.deque[float] = collections.deque(maxlen=params.fit_window)
        self._track_fit: float | None = None
        #: the best other poses of the last confirmation check (map frame) and the odometry pose they were at
        self._rivals = np.zeros((0, 3))
        self._rivals_odom: tuple[float, float, float] | None = None
        #: the current stretch of low-scoring scans the track no longer fits (None: the last scan fitted)
        self._evidence: LowScoreEvidence | None = None
        self._evidence_text = ""
        #: scans whose score was below lost_score while tracking but on which the track still fitted
        self.low_scores_discounted = 0
        #: (stamp s, odometry pose) of the scans over the last lost_refit_history_s, oldest first
        self._odom_recent: collections.deque[tuple[float, float, float]] = collections.deque()
        self._odom_recent_s: collections.deque[float] = collections.deque()
        self.stale_scans_ignored = 0
        #: scans stamped before this (s) predate the last initial pose or global request: ignored
        self._scans_from_s = -math.inf
        #: a refinement waits for the next update (request_nomotion_update(refine=True))
        self.refine_pending = False
        self.last_refinement: Refinement | None = None
        #: how well the pose is known per direction (drift while driving, shrunk by what the scans pin)
        self.uncertainty = PoseUncertainty(uncertainty_params)

    def set_initial_pose(self, pose: tuple[float, float, float], covariance: np.ndarray | None = None, *,
                         stamp_s: float | None = None) -> None:
        """Particles around ``pose`` (default covariance: 0.5 m, 0.5 m, pi/12 rad std-devs, as Nav2). ``stamp_s``:
        when the pose was given; scans taken before it show the robot before it was placed there and are ignored
        (as ROS's initialpose carries a header stamp)."""
        if covariance is None:
            covariance = np.diag([0.25, 0.25, (math.pi / 12.0) ** 2])
        if not all(math.isfinite(v) for v in pose):
            raise ValueError(f"initial pose {pose} is not finite")
        self.pf.reseed()
        self.pf.init_gaussian(pose, covariance)
        self.initial_prior = (np.array(pose, dtype=float), np.array(covariance, dtype=float).reshape(3, 3))
        self._reinitialised(stamp_s)
        self.uncertainty.reset(covariance)
        self.last_good = (float(pose[0]), float(pose[1]), float(pose[2]))
        # the pose given is the prior that tells self-similar places apart: no confirmation against the whole map
        self.unconfirmed = False
        self._track_map_odom = None
        self._track_fit = None
        self._fits.clear()
        self._set_state("localizing", f"initial pose ({pose[0]:.2f}, {pose[1]:.2f}, {pose[2]:.2f})")

    def global_localization(self, *, stamp_s: float | None = None) -> None:
        """Particles over all free space; ``stamp_s`` as in ``set_initial_pose``."""
        self.pf.reseed()
        self.pf.init_uniform()
        self.initial_prior = None
        self._reinitialised(stamp_s)
        # the request says the pose is unknown: this is the global stage of a recovery, given global_recovery_s, and
        # no pose from before it is trusted (a local search around the old pose, where the robot no longer is,
        # would settle on whatever there looks like the scan)
        self._stage = self.params.local_recovery_attempts
        self.last_good = None
        self._good_map_odom = None
        self.unconfirmed = True
        self._track_map_odom = None
        self._track_fit = None
        self._fits.clear()
        self._set_state("localizing", "global localization")

    def request_nomotion_update(self, refine: bool = False) -> None:
        """Update on the next scan without motion; with ``refine`` (the robot stands still and a precise pose is
        wanted) that update is followed by the dense scan-to-map refinement (services/localization/refine.py)
        when ``process`` gets the scan's dense beams."""
        self.force_update = True
        self.refine_pending = self.refine_pending or refine

    def withdraw_nomotion_request(self) -> None:
        """Nobody waits for the requested update any more (its answer's deadline passed without a scan): a late scan
        must not move the estimate under a client that has judged without it."""
        self.force_update = False
        self.refine_pending = False

    def reanchor_odometry(self) -> None:
        """Odometry restarted: the next scan updates the filter without motion and re-derives map_odom."""
        self.pf_odom_pose = None
        self._forget_odometry()

    def _forget_odometry(self) -> None:
        self._odom_recent.clear()
        self._odom_recent_s.clear()

    def _reinitialised(self, stamp_s: float | None = None) -> None:
        self._forget_odometry()
        self._scans_from_s = -math.inf if stamp_s is None else float(stamp_s)
        self.pf_odom_pose = None
        self.resample_count = 0
        self.estimate = None
        self.map_odom = None
        self._scores.clear()
        self._stage = -1
        self._stage_started_at = self._now
        self._updates_since_reset = 0
        self._confirmations = 0
        self._rivals = np.zeros((0, 3))
        self._evidence = None

    def _set_state(self, state: str, reason: str) -> None:
        self.state, self.reason = state, reason
        self.pf.allow_injection = state != "tracking" or self.params.inject_while_tracking

    def process(self, odom_pose: tuple[float, float, float], beams: ScanBeams,
                mount: tuple[float, float, float], stamp: float | None = None, dense: ScanBeams | None = None,
                rest_move: RestMove | None = None) -> bool:
        """One scan at ``stamp`` (s; None: DEFAULT_SCAN_PERIOD_S after the last): motion + sensor update
        (+ resampling) when the gates open, then the verdict; returns whether the filter updated. ``dense``: every
        valid beam of the scan, for a pending refinement. ``rest_move``: the robot has not moved since the last
        update; that update is a Metropolis-Hastings move (``ParticleFilter.rest_move``) instead of a sensor update
        and resampling (not while annealing). A scan stamped before the last initial pose or global request is
        ignored (returns False)."""
        if stamp is not None and stamp < self._scans_from_s:
            self.stale_scans_ignored += 1
            return False
        self._now = self._now + self.DEFAULT_SCAN_PERIOD_S if stamp is None else float(stamp)
        p = self.params
        if self.state != "tracking" and self._now - self._last_update_at >= p.recovery_update_period_s:
            self.force_update = True  # converge (or recover) at rest too
        if self.pf_odom_pose is None:
            self.pf_odom_pose = odom_pose
            update = True
        else:
            px, py, pth = self.pf_odom_pose
            delta = (odom_pose[0] - px, odom_pose[1] - py, float(wrap_angle(odom_pose[2] - pth)))
            update = (abs(delta[0]) > p.update_min_d or abs(delta[1]) > p.update_min_d
                      or abs(delta[2]) > p.update_min_a or self.force_update)
            if update:
                self.pf.motion_update(odom_pose, delta)
                self._predict_uncertainty(pth, delta)
                self.pf_odom_pose = odom_pose
        if update:
            self.force_update = False
            self._last_update_at = self._now
            moved_at_rest = rest_move is not None and self.pf.temperature <= 1.0 and self.estimate is not None
            if moved_at_rest:
                assert rest_move is not None
                self.pf.rest_move(beams.ranges, beams.bearings, mount, beams.range_max, rest_move)
            else:
                self.pf.sensor_update(beams.ranges, beams.bearings, mount, beams.range_max)
                self.resample_count += 1
            # the weighted set carries this scan's evidence; resampling only adds noise to its mean
            self.estimate = self.pf.estimate()
            self.spread_m = self.estimate.spread_m
            self.jump_m = 0.0
            if self.map_odom is not None:  # how far the estimate moved from where odometry carried the last one
                carried = compose(self.map_odom, odom_pose)
                self.jump_m = math.hypot(self.estimate.pose[0] - carried[0], self.estimate.pose[1] - carried[1])
            if not moved_at_rest and self.resample_count % self.params.resample_interval == 0:
                self.pf.resample()
            if self.refine_pending and dense is not None:
                self.refine_pending = False
                self._refine(dense, mount)
            self._update_uncertainty(beams, mount)
            self.map_odom = compose(self.estimate.pose, inverse(odom_pose))
            self.updates += 1
            self._updates_since_reset += 1
            if self.state == "tracking":
                self._fits.append(self._fit(self.estimate.pose)[1])
        self._remember_odometry(odom_pose)
        if self.map_odom is not None:
            self._judge(compose(self.map_odom, odom_pose), odom_pose, beams, mount)
        return update

    def _remember_odometry(self, odom_pose: tuple[float, float, float]) -> None:
        """Keep the odometry poses of the scans over the last ``lost_refit_history_s`` (the re-fit's seeds)."""
        if self._odom_recent_s and self._now < self._odom_recent_s[-1]:  # the clock went back: another run
            self._forget_odometry()
        self._odom_recent.append(odom_pose)
        self._odom_recent_s.append(self._now)
        while self._odom_recent_s and self._odom_recent_s[0] < self._now - self.params.lost_refit_history_s:
            self._odom_recent.popleft()
            self._odom_recent_s.popleft()

    def _predict_uncertainty(self, odom_theta: float, delta: tuple[float, float, float]) -> None:
        """Grow the tracked covariance by the odometry step ``delta`` (odom frame, from heading ``odom_theta``)."""
        c, s = math.cos(odom_theta), math.sin(odom_theta)
        body = (c * delta[0] + s * delta[1], -s * delta[0] + c * delta[1], delta[2])
        heading = self.estimate.pose[2] if self.estimate is not None else odom_theta
        self.uncertainty.predict(heading, body)

    def _update_uncertainty(self, beams: ScanBeams, mount: tuple[float, float, float]) -> None:
        """Shrink the tracked covariance by what this scan pins at the estimate; a filter that is not tracking
        has only its particle cloud to say how well it knows the pose."""
        est = self.estimate
        if est is None:
            return
        if self.state != "tracking":
            self.uncertainty.reset(est.covariance)
            return
        grid = self.pf.grid
        info = scan_information(self.pf.field.exact_distance_m(), grid.origin, grid.resolution,
                                self.params.sigma_hit, est.pose, beams.ranges, beams.bearings, mount,
                                self.uncertainty.params)
        self.uncertainty.update(info)

    def _refine(self, dense: ScanBeams, mount: tuple[float, float, float]) -> None:
        """Move the estimate (and every particle with it) to the dense scan's maximum-likelihood pose nearby, when
        the filter is tracking (a lost or localizing filter has no estimate worth polishing)."""
        est = self.estimate
        if est is None or self.state != "tracking":
            return
        grid = self.pf.grid
        p = self.params
        model = BeamModel(p.z_hit, p.z_rand / dense.range_max if dense.range_max > 0 else 0.0, p.sigma_hit,
                          self.pf.field.max_dist)
        distance, walls = self.pf.field.refinement_fields(p.map_surface)
        r = refine_pose(distance, grid.origin, grid.resolution, model, est.pose, est.covariance, dense.ranges,
                        dense.bearings, mount, occupied=walls)
        self.last_refinement = r
        if not r.used:
            return
        dx, dy = r.pose[0] - est.pose[0], r.pose[1] - est.pose[1]
        dth = float(wrap_angle(r.pose[2] - est.pose[2]))
        n = self.pf.n
        self.pf.poses[:n, 0] += dx
        self.pf.poses[:n, 1] += dy
        self.pf.poses[:n, 2] = wrap_angle(self.pf.poses[:n, 2] + dth)
        self.estimate = Estimate(r.pose, est.covariance, est.weight, est.particles, est.spread_m)

    def _judge(self, pose: tuple[float, float, float], odom_pose: tuple[float, float, float], beams: ScanBeams,
               mount: tuple[float, float, float]) -> None:
        """Score the scan at the map pose (the held one: map_odom ∘ ``odom_pose``), then move the verdict and the
        recovery on."""
        p = self.params
        score = self.pf.explained_fraction(pose, beams.ranges, beams.bearings, mount)
        if math.isfinite(score):  # else the scan saw too little the map knows: the verdict waits
            self._scores.append(score)
            del self._scores[:-p.match_window]
        if self._scores:
            self.match_score = float(np.median(self._scores))
        if len(self._scores) < p.match_window and self.state != "tracking":
            return
        now = self._now
        if self.state == "tracking":
            spread = self.spread_m > p.lost_spread_m
            if spread and self._track_fits() and self.jump_m <= p.lost_spread_m and self.estimate is not None:
                # the pose still explains the scans as well as the track did: the particles that spread out found
                # other poses fitting the scan (a self-similar building), which is no evidence against the track
                self.pf.keep_near(self.estimate.pose, p.lost_spread_m)
                spread = False
            low = self._low_score_sustained(pose, odom_pose, beams, mount)
            if low or spread or self.jump_m > p.lost_spread_m:
                self.lost_at = now
                self.lost_reason = (f"scan match {self.match_score:.2f}, spread {self.spread_m:.2f} m"
                                    + (f", estimate jumped {self.jump_m:.2f} m" if self.jump_m > p.lost_spread_m
                                       else "") + (f", {self._evidence_text}" if low else ""))
                self._evidence = None
                # first the Augmented-MCL injection (allowed now, with w_slow still at the tracking level) for
                # recovery_attempt_s: it finds a nearby kidnap within centimetres of travel; the sensor resets
                # around last_good, then global, follow only when it has not converged by then
                self._stage, self._stage_started_at = -1, now
                self.unconfirmed, self._confirmations = True, 0
                self._track_map_odom = self._good_map_odom
                self._track_fit = float(np.median(self._fits)) if self._fits else None
                self._fits.clear()
                self._set_state("lost", f"recovering by random-particle injection (lost: {self.lost_reason})")
            else:
                self.last_good = pose
                self._good_map_odom = self.map_odom
            return
        converged = (len(self._scores) >= p.match_window and self.match_score >= p.track_score
                     and self.spread_m <= p.track_spread_m and self.pf.temperature <= 1.0
                     and self._updates_since_reset >= 2)
        if not converged:
            self._confirmations = 0
        elif self.unconfirmed:
            converged = self._confirm()
        if converged:
            self._stage = -1
            self.unconfirmed = False
            self._set_state("tracking", f"scan match {self.match_score:.2f}, spread {self.spread_m:.2f} m")
            self.last_good = pose
            return
        limit = p.global_recovery_s if self._stage >= p.local_recovery_attempts else p.recovery_attempt_s
        if now - self._stage_started_at < limit:
            return
        if (self._stage < 0 and self.state == "localizing" and self.initial_prior is not None
                and len(self._scores) >= p.match_window and self.match_score >= p.track_score):
            # the scans fit the pose given; they only do not narrow it down (a corridor whose ends the lidar does
            # not see): that is no evidence of a wrong pose, and a search of the whole map would find look-alikes
            self.reason = (f"the scans fit the pose given but do not fix it (spread {self.spread_m:.2f} m): "
                           "move the robot, or give the pose more precisely")
            return
        if self.state != "lost":  # an initial pose (or a global localization) that never converged: it was wrong
            self.lost_at = now
            self.lost_reason = f"not converged {limit:.0f} s after the {self.reason}"
        self._start_stage(0 if self._stage < 0 else min(self._stage + 1, p.local_recovery_attempts))

    def _low_score_sustained(self, pose: tuple[float, float, float], odom_pose: tuple[float, float, float],
                             beams: ScanBeams, mount: tuple[float, float, float]) -> bool:
        """Whether a low scan match has become evidence against the track (``AmclParams.lost_evidence_*``): the
        median score below ``lost_score`` and the held ``pose``, hill-climbed on this scan, at least ``fit_drop`` nats
        per beam below the track's median fit, on every scan over ``lost_evidence_m`` travelled, ``lost_evidence_rad``
        turned or ``lost_evidence_s``. Without a track fit to compare with (fewer than 2 tracking updates) the fit
        test counts as failed."""
        p = self.params
        if self.match_score >= p.lost_score or beams.ranges.size == 0:
            self._evidence = None
            return False
        reference = float(np.median(self._fits)) if len(self._fits) >= 2 else None
        self.pf.use_scan(beams.ranges, beams.bearings, mount, beams.range_max)
        fit = self._refit(pose)
        if reference is not None and fit >= reference - p.fit_drop:
            # the scan fits the track a few centimetres away: a late scan (or odometry ahead of it), not a loss
            self._evidence = None
            self.low_scores_discounted += 1
            return False
        ev = self._evidence
        if ev is None:
            ev = self._evidence = LowScoreEvidence(self._now, odom_pose)
        ev.advance(odom_pose)
        ref = "none yet" if reference is None else f"{reference:.2f}"
        self._evidence_text = (f"fit {fit:.2f} vs track {ref} nats per beam over {ev.travelled_m:.2f} m, "
                               f"{ev.turned_rad:.2f} rad, {self._now - ev.started_s:.2f} s")
        return (ev.travelled_m >= p.lost_evidence_m or ev.turned_rad >= p.lost_evidence_rad
                or self._now - ev.started_s >= p.lost_evidence_s)

    def _refit(self, pose: tuple[float, float, float]) -> float:
        """Log-likelihood per beam (nats) of the best local re-fit of the current scan: ``pose`` and the poses
        odometry held over the last ``lost_refit_history_s`` (map_odom ∘ each, one per 0.05 m or 0.05 rad of
        motion), all hill-climbed."""
        seeds = [pose]
        if self.map_odom is not None:
            last = pose
            for odom_pose in reversed(self._odom_recent):
                held = compose(self.map_odom, odom_pose)
                if (math.hypot(held[0] - last[0], held[1] - last[1]) >= 0.05
                        or abs(float(wrap_angle(held[2] - last[2]))) >= 0.05):
                    seeds.append(held)
                    last = held
        _, ll = self.pf.climb(np.array(seeds))
        return float(ll.max()) / max(self.pf.last_beam_count, 1)

    def _track_fits(self) -> bool:
        """Whether the latest update's pose explains its scan about as well as the track has lately (per-beam
        log-likelihood at most ``fit_drop`` below the median of the last ``fit_window`` tracking updates)."""
        if len(self._fits) < 2:
            return False
        return self._fits[-1] >= float(np.median(self._fits)) - self.params.fit_drop

    def _fit(self, pose: tuple[float, float, float]) -> tuple[tuple[float, float, float], float]:
        """``pose`` hill-climbed on the last scan, with its log-likelihood per beam (nats)."""
        climbed, ll = self.pf.climb(np.array([pose]))
        beams = self.pf.last_beam_count
        return (float(climbed[0, 0]), float(climbed[0, 1]), float(climbed[0, 2])), float(ll[0]) / max(beams, 1)

    def _carried_rivals(self) -> np.ndarray:
        """The rivals of the last confirmation check, moved by the odometry since (map pose ∘ odom motion)."""
        if self._rivals.size == 0 or self._rivals_odom is None or self.pf_odom_pose is None:
            return np.zeros((0, 3))
        step = compose(inverse(self._rivals_odom), self.pf_odom_pose)
        return np.array([compose((float(r[0]), float(r[1]), float(r[2])), step) for r in self._rivals])

    def _confirm(self) -> bool:
        """One more check of a converged, unconfirmed filter on its latest update (see ``AmclParams.confirm_*``):
        True once ``confirm_updates`` updates in a row found no other pose within ``confirm_margin`` of it."""
        p = self.params
        if p.confirm_updates == 0:
            return True
        est = self.estimate
        if est is None or self.pf_odom_pose is None:
            return False
        if self.updates == self._confirm_checked_update:
            return False  # no new scan in the filter since the last check
        self._confirm_checked_update = self.updates
        pf = self.pf
        hypothesis, fit = self._fit(est.pose)
        at = f"({hypothesis[0]:.2f}, {hypothesis[1]:.2f})"
        if self._track_fit is not None and fit < self._track_fit - p.fit_drop:
            self._confirmations = 0
            self.reason = (f"{at} not confirmed: it explains the scan worse than the track did ({fit:.2f} vs "
                           f"{self._track_fit:.2f} nats per beam)")
            return False
        hypothesis_ll = fit * max(pf.last_beam_count, 1)
        seeds = [self._carried_rivals()]
        if self._track_map_odom is not None:  # the track held before the loss, where odometry carried it
            seeds.append(np.array([compose(self._track_map_odom, self.pf_odom_pose)]))
        rivals, rivals_ll = pf.best_alternative(hypothesis, p.confirm_exclude_m, p.confirm_exclude_rad,
                                                p.global_localization_particles, seeds=np.vstack(seeds),
                                                near_m=p.confirm_near_m)
        # the best rivals ride along with odometry: a pose found once keeps competing on the next scans
        self._rivals, self._rivals_odom = rivals[:p.confirm_rivals], self.pf_odom_pose
        if rivals_ll.size == 0:
            other, other_ll = hypothesis, -math.inf
        else:
            other, other_ll = (float(rivals[0, 0]), float(rivals[0, 1]), float(rivals[0, 2])), float(rivals_ll[0])
        margin = hypothesis_ll - other_ll
        rival = f"({other[0]:.2f}, {other[1]:.2f}, {other[2]:.2f})"
        if margin >= p.confirm_margin:
            self._confirmations += 1
            self.reason = (f"confirming {at}: {self._confirmations}/{p.confirm_updates} scans, best other pose "
                           f"{rival} {min(margin, 999.0):.1f} nats less likely")
            return self._confirmations >= p.confirm_updates
        self._confirmations = 0
        if margin <= -p.confirm_margin:
            # the filter settled on a pose that another one clearly beats: search around that one instead
            pf.init_gaussian(other, np.diag([0.1 ** 2, 0.1 ** 2, 0.05 ** 2]))
            self._scores.clear()
            self._updates_since_reset = 0
            self.reason = f"{at} rejected: {rival} explains the scan {-margin:.1f} nats better; relocalizing there"
        else:
            self.reason = f"ambiguous: {at} and {rival} explain the scan about as well ({margin:+.1f} nats)"
        return False

    def _start_stage(self, stage: int) -> None:
        p = self.params
        if stage < p.local_recovery_attempts and self.last_good is not None:
            radius = p.local_recovery_radius_m * (2.0 ** stage)
            self.pf.init_around(self.last_good[:2], radius)
            what = f"relocalizing within {radius:.1f} m of ({self.last_good[0]:.2f}, {self.last_good[1]:.2f})"
        else:
            stage = p.local_recovery_attempts
            self.pf.init_uniform()
            what = "global relocalization" if self._stage < stage else "cannot relocalize: global localization again"
        self.pf_odom_pose = None
        self.resample_count = 0
        self._scores.clear()
        self._updates_since_reset = 0
        self._stage, self._stage_started_at = stage, self._now
        self._set_state("lost", f"{what} (lost: {self.lost_reason})")
