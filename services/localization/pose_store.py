"""The last good pose across restarts: ``<state_dir>/localization_pose.json``, one JSON object.

Fields: ``map_yaml`` (the resolved path of the map the pose is in), ``x``, ``y`` (m), ``theta`` (rad),
``covariance`` (3x3, row-major), ``stamp`` (s). It is written atomically (a temporary file, then ``os.replace``)
and only while the filter is ``tracking``: a lost pose must not become the next start's initial pose. A saved pose
is used only on the same map, and its spread is never trusted below ``SAVED_SPREAD_FLOOR_M`` (a restart may follow
a move by hand).
"""

from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path

import numpy as np

POSE_FILE = "localization_pose.json"
SAVED_SPREAD_FLOOR_M = 0.05
Pose = tuple[float, float, float]


class SavedPoseIgnored(Exception):
    """A saved pose that is not used, with the log level its reason deserves."""

    def __init__(self, message: str, level: int = logging.WARNING) -> None:
        super().__init__(message)
        self.level = level


def should_save(state: str, has_estimate: bool) -> bool:
    """Only a tracking estimate is saved."""
    return has_estimate and state == "tracking"


def read_saved_pose(path: Path, map_yaml: str) -> tuple[Pose, np.ndarray] | None:
    """The pose and covariance saved in ``path`` for ``map_yaml`` (None: no file); raises SavedPoseIgnored."""
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
        if data.get("map_yaml") != str(Path(map_yaml).resolve()):
            raise SavedPoseIgnored(f"saved pose in {path} belongs to another map; not used", logging.INFO)
        pose = (float(data["x"]), float(data["y"]), float(data["theta"]))
        cov = np.asarray(data["covariance"], dtype=float).reshape(3, 3)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SavedPoseIgnored(f"ignoring unreadable saved pose {path}: {exc}") from None
    if not all(math.isfinite(v) for v in pose) or not np.all(np.isfinite(cov)):
        raise SavedPoseIgnored(f"ignoring non-finite saved pose in {path}")
    return pose, cov + np.diag([SAVED_SPREAD_FLOOR_M ** 2] * 3)


def write_pose(path: Path, map_yaml: str, pose: Pose, covariance: np.ndarray, stamp: float) -> None:
    """Write the record atomically; raises OSError."""
    data = {"map_yaml": str(Path(map_yaml).resolve()), "x": pose[0], "y": pose[1], "theta": pose[2],
            "covariance": covariance.reshape(-1).tolist(), "stamp": stamp}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data))
    os.replace(tmp, path)
