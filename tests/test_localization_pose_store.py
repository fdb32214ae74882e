"""Pose persistence across restarts (services/localization/pose_store.py)."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest

from services.localization.pose_store import (
    POSE_FILE,
    SAVED_SPREAD_FLOOR_M,
    SavedPoseIgnored,
    read_saved_pose,
    should_save,
    write_pose,
)


def test_a_tracking_pose_round_trips_on_its_own_map_with_a_spread_floor(tmp_path: Path) -> None:
    path, map_yaml = tmp_path / "state" / POSE_FILE, str(tmp_path / "corridor.yaml")
    assert read_saved_pose(path, map_yaml) is None
    write_pose(path, map_yaml, (9.5, 3.25, -1.0), np.zeros((3, 3)), 12.0)
    assert not path.with_suffix(".tmp").exists()  # written atomically
    pose, cov = read_saved_pose(path, map_yaml)
    assert pose == (9.5, 3.25, -1.0)
    np.testing.assert_allclose(np.diag(cov), [SAVED_SPREAD_FLOOR_M ** 2] * 3)
    assert should_save("tracking", True) and not should_save("lost", True) and not should_save("tracking", False)


def test_a_pose_from_another_map_or_a_broken_file_is_ignored_with_the_reason(tmp_path: Path) -> None:
    path = tmp_path / POSE_FILE
    write_pose(path, str(tmp_path / "a.yaml"), (1.0, 2.0, 0.0), np.eye(3), 0.0)
    with pytest.raises(SavedPoseIgnored, match="another map") as other:
        read_saved_pose(path, str(tmp_path / "b.yaml"))
    assert other.value.level == logging.INFO
    path.write_text("{not json")
    with pytest.raises(SavedPoseIgnored, match="unreadable"):
        read_saved_pose(path, str(tmp_path / "a.yaml"))
    data = {"map_yaml": str((tmp_path / "a.yaml").resolve()), "x": math.nan, "y": 0.0, "theta": 0.0,
            "covariance": [0.0] * 9}
    path.write_text(json.dumps(data))
    with pytest.raises(SavedPoseIgnored, match="non-finite"):
        read_saved_pose(path, str(tmp_path / "a.yaml"))
