"""Relative-pose error of Kümmerle et al. 2009, "On measuring the accuracy of SLAM algorithms".

For each ground-truth relation δ*_ij (the pose of scan j seen from scan i) and the estimate
δ_ij = x_i⁻¹ ⊕ x_j, the error is ε = δ*_ij⁻¹ ⊕ δ_ij; the translational error is ‖ε_xy‖ (m) and the rotational
error |ε_θ| (rad). Reported: mean and standard deviation of both over all relations. The relations relate
*scans*, i.e. poses of the laser: a robot trajectory is first moved to the laser frame (``scan_poses``).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass

import numpy as np

from .se2 import between, compose, wrap_angle


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

    def as_dict(self) -> dict:
        return asdict(self)


def scan_poses(robot_poses: np.ndarray, sensor_pose: np.ndarray) -> np.ndarray:
    """Laser poses x ⊕ s of robot poses x (N, 3) for a laser mounted at s = (x, y, theta) on the robot."""
    robot_poses = np.asarray(robot_poses, float)
    return compose(robot_poses, np.broadcast_to(np.asarray(sensor_pose, float), robot_poses.shape))


def _lookup(stamps_s: np.ndarray, at_s: np.ndarray, tolerance_s: float) -> tuple[np.ndarray, np.ndarray]:
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
    i, ok_i = _lookup(stamps_s, relations.stamp_from_s, tolerance_s)
    j, ok_j = _lookup(stamps_s, relations.stamp_to_s, tolerance_s)
    ok = ok_i & ok_j
    if not ok.any():
        raise ValueError("no relation stamp matches the trajectory's stamps")
    estimated = between(poses[i[ok]], poses[j[ok]])
    error = between(relations.relative_pose[ok], estimated)
    trans = np.hypot(error[:, 0], error[:, 1])
    rot = np.abs(wrap_angle(error[:, 2]))
    return RelativePoseError(float(trans.mean()), float(trans.std()), float(rot.mean()), float(rot.std()),
                             float(trans.max()), int(ok.sum()), int((~ok).sum()))
