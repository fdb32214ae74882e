"""Relative-pose error of Kümmerle et al. 2009, "On measuring the accuracy of SLAM algorithms".

For each ground-truth relation δ*_ij (the pose of scan j seen from scan i) and the estimate
δ_ij = x_i⁻¹ ⊕ x_j, the error is ε = δ*_ij⁻¹ ⊕ δ_ij; the translational error is ‖ε_xy‖ (m) and the rotational
error |ε_θ| (rad). Reported: mean and standard deviation of both over all relations. The relations relate
*scans*, i.e. poses of the laser: a robot trajectory is first moved to the laser frame (``scan_poses``).

Against a reference trajectory (a SLAM-corrected log): ``aligned_trajectory_error`` is the RMS position error
after the rigid SE(2) alignment minimising it (Umeyama 1991 without scale), and ``false_closures`` lists the loop
closures whose measured relative pose disagrees with the reference's relative pose of the same two scans.

A reference made by another SLAM run need not share the laser's metric: if its poses are consistent with ranges a
fraction of a percent longer or shorter than the log's, a map built from the scans is uniformly smaller or larger
than the reference, and the rigid error grows with the building's size although no part of the map is bent.
``aligned_trajectory_error`` therefore also reports the Sim(2) fit (Umeyama with scale): ``scale``, the factor that
takes the estimate onto the reference (1.003: the reference is 0.3 % larger), and ``scaled_rms_m``, the RMS position
error after that fit. The rigid figure stays the headline. The fit takes whatever a uniform scale explains: a metric
mismatch, but also a bend that happens to shrink or stretch the trajectory; it is a metric mismatch when the map's
edges show the same bias one by one (their along-track length against the reference's): ``edge_bias`` measures that
on the front end's keyframe edges, whose measurements loop closures do not touch.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from services.common.se2 import between, compose, wrap_angle


@dataclass
class Relations:
    """Ground-truth relations: stamps (N,) of both scans and relative poses (N, 3) = (dx, dy, dyaw)."""

    stamp_from_s: np.ndarray
    stamp_to_s: np.ndarray
    relative_pose: np.ndarray


def parse_relations(lines: Iterable[str]) -> Relations:
    """Lines ``t1 t2 dx dy dz roll pitch yaw`` (blank lines and ``#`` comments skipped)."""
    rows = []
    for number, line in enumerate(lines, start=1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        fields = text.split()
        if len(fields) < 8:
            raise ValueError(f"relations line {number}: expected 8 fields 't1 t2 dx dy dz roll pitch yaw'")
        t1, t2, dx, dy, _, _, _, yaw = (float(v) for v in fields[:8])
        rows.append((t1, t2, dx, dy, yaw))
    table = np.array(rows, float).reshape(-1, 5)
    return Relations(table[:, 0], table[:, 1], table[:, 2:5])


@dataclass
class RelativePoseError:
    translation_mean_m: float
    translation_std_m: float
    rotation_mean_rad: float
    rotation_std_rad: float
    translation_max_m: float
    n_relations: int
    n_missing: int

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def scan_poses(robot_poses: np.ndarray, sensor_pose: np.ndarray) -> np.ndarray:
    """Laser poses x ⊕ s of robot poses x (N, 3) for a laser mounted at s = (x, y, theta) on the robot."""
    robot_poses = np.asarray(robot_poses, float)
    return compose(robot_poses, np.broadcast_to(np.asarray(sensor_pose, float), robot_poses.shape))


def match_stamps(stamps_s: np.ndarray, at_s: np.ndarray, tolerance_s: float) -> tuple[np.ndarray, np.ndarray]:
    """For each of ``at_s``: the index of the nearest of ``stamps_s`` (any order), and whether it lies within
    ``tolerance_s``."""
    order = np.argsort(stamps_s)
    sorted_stamps = stamps_s[order]
    pos = np.clip(np.searchsorted(sorted_stamps, at_s), 1, len(sorted_stamps) - 1)
    left = sorted_stamps[pos - 1]
    right = sorted_stamps[pos]
    nearer = np.where(np.abs(at_s - left) <= np.abs(at_s - right), pos - 1, pos)
    found = np.abs(sorted_stamps[nearer] - at_s) <= tolerance_s
    return order[nearer], found


def relative_pose_error(stamps_s: np.ndarray, poses: np.ndarray, relations: Relations, *,
                        tolerance_s: float = 1e-3) -> RelativePoseError:
    """Error of the trajectory (stamps (N,), poses (N, 3)) on the relations whose stamps both match a
    trajectory stamp within ``tolerance_s``; the others are counted in ``n_missing``."""
    stamps_s = np.asarray(stamps_s, float)
    if len(stamps_s) < 2:
        raise ValueError("the trajectory needs at least two poses")
    i, ok_i = match_stamps(stamps_s, relations.stamp_from_s, tolerance_s)
    j, ok_j = match_stamps(stamps_s, relations.stamp_to_s, tolerance_s)
    ok = ok_i & ok_j
    if not ok.any():
        raise ValueError("no relation stamp matches the trajectory's stamps")
    estimated = between(poses[i[ok]], poses[j[ok]])
    error = between(relations.relative_pose[ok], estimated)
    trans = np.hypot(error[:, 0], error[:, 1])
    rot = np.abs(wrap_angle(error[:, 2]))
    return RelativePoseError(float(trans.mean()), float(trans.std()), float(rot.mean()), float(rot.std()),
                             float(trans.max()), int(ok.sum()), int((~ok).sum()))


@dataclass
class TrajectoryError:
    rms_m: float
    max_m: float
    rotation_rms_rad: float
    n_poses: int
    scale: float = 1.0  #: Sim(2) fit: reference ≈ scale · R · estimate + t
    scaled_rms_m: float = 0.0  #: RMS position error after the Sim(2) fit

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _rotation(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def _umeyama(poses: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Umeyama 1991 on positions: (p̄, r̄, θ, s) with θ the rotation minimising Σ‖R(θ)(p_i − p̄) − (r_i − r̄)‖² and
    s = Σ (r_i − r̄)·R(θ)(p_i − p̄) / Σ ‖p_i − p̄‖² the scale of the similarity fit (θ is the same with or without)."""
    p = np.asarray(poses, float)[:, :2]
    r = np.asarray(reference, float)[:, :2]
    mp, mr = p.mean(axis=0), r.mean(axis=0)
    pc, rc = p - mp, r - mr
    cov = rc.T @ pc
    theta = float(np.arctan2(cov[1, 0] - cov[0, 1], cov[0, 0] + cov[1, 1]))
    spread = float(np.sum(pc * pc))
    scale = float(np.sum(rc * (pc @ _rotation(theta).T)) / spread) if spread > 0.0 else 1.0
    return mp, mr, theta, scale


def align_se2(poses: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """The transform T (x, y, theta) minimising Σ‖T ⊕ p_i − r_i‖² over positions (Umeyama, no scale)."""
    mp, mr, theta, _ = _umeyama(poses, reference)
    t = mr - _rotation(theta) @ mp
    return np.array([t[0], t[1], theta])


def aligned_trajectory_error(poses: np.ndarray, reference: np.ndarray) -> TrajectoryError:
    """RMS / max position error and RMS heading error of ``poses`` (N, 3) against ``reference`` (N, 3) after the
    rigid fit ``align_se2``; with the similarity fit's scale s and RMS (positions s·R(θ)(p_i − p̄) + r̄)."""
    poses = np.asarray(poses, float)
    reference = np.asarray(reference, float)
    if poses.shape != reference.shape or len(poses) < 2:
        raise ValueError(f"trajectories must have the same length >= 2 (got {poses.shape} and {reference.shape})")
    mp, mr, theta, scale = _umeyama(poses, reference)
    rotation = _rotation(theta)
    rigid = np.array([*(mr - rotation @ mp), theta])
    aligned = compose(np.broadcast_to(rigid, poses.shape), poses)
    d = np.hypot(*(aligned[:, :2] - reference[:, :2]).T)
    rot = wrap_angle(aligned[:, 2] - reference[:, 2])
    fitted = scale * (poses[:, :2] - mp) @ rotation.T + mr
    scaled = np.hypot(*(fitted - reference[:, :2]).T)
    return TrajectoryError(float(np.sqrt(np.mean(d**2))), float(d.max()), float(np.sqrt(np.mean(rot**2))),
                           len(poses), scale, float(np.sqrt(np.mean(scaled**2))))


@dataclass
class EdgeBias:
    """Systematic error of a chain of relative poses (keyframe edges) against the reference's, per metre driven."""

    #: Σ (edge length along the reference's direction − reference length) / Σ reference length, in %
    along_pct: float
    #: Σ heading error / Σ reference length, in degrees per 100 m (a steady turn of the map against the reference)
    heading_deg_per_100m: float
    #: Σ heading error · sign(reference turn) / Σ |reference turn| over the edges turning more than ``min_turn_rad``,
    #: in %: turns measured too small (−) or too large (+), which cancel in the sum above when left and right turns
    #: alternate (NaN without such an edge)
    turn_pct: float
    n_edges: int
    path_m: float


def edge_bias(reference_from: np.ndarray, reference_to: np.ndarray, measured: np.ndarray, *,
              min_length_m: float = 0.2, min_turn_rad: float = 0.05) -> EdgeBias:
    """Bias of ``measured`` relative poses (M, 3) against the reference's relative poses between ``reference_from``
    and ``reference_to`` (M, 3 each): with δ* = from⁻¹ ⊕ to of length ℓ and unit direction u, the along-track error
    is δ_xy·u − ℓ and the heading error wrap(δ_θ − δ*_θ); both are summed and divided by Σℓ. Edges shorter than
    ``min_length_m`` (turns on the spot) have no direction to measure along and are left out. ``turn_pct`` relates
    the heading error of every edge turning more than ``min_turn_rad`` to its turn, spot turns included.

    A scan matcher whose every edge comes out 0.3 % short gives ``along_pct`` −0.3 whatever the loops, where a
    bent map with unbiased edges gives about 0; summed heading errors show a steady turn the same way."""
    truth = between(np.asarray(reference_from, float).reshape(-1, 3), np.asarray(reference_to, float).reshape(-1, 3))
    measured = np.asarray(measured, float).reshape(-1, 3)
    if len(truth) != len(measured):
        raise ValueError(f"{len(measured)} measured edges for {len(truth)} reference edges")
    length = np.hypot(truth[:, 0], truth[:, 1])
    keep = length >= min_length_m
    path_m = float(length[keep].sum())
    if not keep.any():
        raise ValueError(f"no edge of at least {min_length_m} m to measure along")
    direction = truth[keep, :2] / length[keep, None]
    along = np.sum(measured[keep, :2] * direction, axis=1) - length[keep]
    heading = wrap_angle(measured[keep, 2] - truth[keep, 2])
    turning = np.abs(truth[:, 2]) > min_turn_rad
    turn_error = wrap_angle(measured[turning, 2] - truth[turning, 2]) * np.sign(truth[turning, 2])
    turn_pct = 100.0 * float(turn_error.sum()) / float(np.abs(truth[turning, 2]).sum()) if turning.any() else math.nan
    return EdgeBias(100.0 * float(along.sum()) / path_m, 100.0 * math.degrees(float(heading.sum())) / path_m,
                    turn_pct, int(keep.sum()), path_m)


def false_closures(from_scans: np.ndarray, to_scans: np.ndarray, measurements: np.ndarray, reference: np.ndarray, *,
                   max_xy_m: float = 0.3, max_theta_rad: float = 0.05) -> np.ndarray:
    """Mask of closures (scan ``to`` seen from scan ``from`` = ``measurements`` (M, 3)) that differ from the
    reference trajectory's ``between(reference[from], reference[to])`` by more than ``max_xy_m`` or
    ``max_theta_rad``."""
    if len(from_scans) == 0:
        return np.zeros(0, bool)
    truth = between(reference[np.asarray(from_scans)], reference[np.asarray(to_scans)])
    error = between(truth, np.asarray(measurements, float).reshape(-1, 3))
    outliers: np.ndarray = ((np.hypot(error[:, 0], error[:, 1]) > max_xy_m)
                            | (np.abs(wrap_angle(error[:, 2])) > max_theta_rad))
    return outliers
