"""Front end against bad odometry, on a synthetic room ray-cast exactly: an odometry jump that a good match is held
back from by the odometry prior is recognised as an outlier, and a weak match far from the odometry (more likely a
similar-looking place than a slip) falls back to the odometry instead of being kept."""

from __future__ import annotations

import numpy as np

from services.common.se2 import between, compose
from services.localization.slam.mapper import GraphSlam, SlamConfig
from tests.test_slam_constraint import ROOM, _scanner

#: the odometry jumps by 0.25 m, 0.1 m and -0.041 rad between scans 5 and 6 (a wheel slip of the degraded setting)
JUMP = np.array([0.25, 0.1, -0.041])


def _drive_through_a_jump(config: SlamConfig) -> tuple[GraphSlam, np.ndarray]:
    """Twelve scans 0.1 m apart across the room, odometry jumping after the sixth; the pose errors (12, 3)."""
    scan = _scanner(ROOM)
    truth = [np.array([-2.0 + 0.1 * k, 0.0, 0.0]) for k in range(12)]
    odom = truth[:6] + [compose(compose(truth[5], JUMP), between(truth[5], t)) for t in truth[6:]]
    slam = GraphSlam(config)
    poses = [slam.add_scan(float(k), odom[k], scan(truth[k])) for k in range(12)]
    return slam, np.abs(between(np.array(truth), np.array(poses)))


def test_an_odometry_jump_is_an_outlier_not_a_prior():
    slam, error = _drive_through_a_jump(SlamConfig())
    assert slam.odometry_outliers >= 1
    assert error[:, :2].max() < 0.01 and error[:, 2].max() < 0.005, error.max(axis=0)
    # with the check off, the prior keeps part of the jump in the pose
    held, held_error = _drive_through_a_jump(SlamConfig(odometry_outlier_sigma=1e9))
    assert held.odometry_outliers == 0 and held_error[:, :2].max() > 0.015, held_error.max(axis=0)


def test_clean_odometry_is_no_outlier():
    scan = _scanner(ROOM)
    slam = GraphSlam()
    for k in range(12):
        pose = np.array([-2.0 + 0.1 * k, 0.05 * k, 0.01 * k])
        assert np.abs(between(pose, slam.add_scan(float(k), pose, scan(pose)))).max() < 0.01
    assert slam.odometry_outliers == 0


def test_a_weak_match_far_from_the_odometry_falls_back_to_it():
    """Every match is made weak (min_match_score above any score): the one after the jump lands 0.27 m from the
    prediction, beyond ``weak_match_max_sigma`` of the motion prior, so the odometry prediction is kept."""
    weak = dict(min_match_score=1.01, rescue_below_score=1.01, weak_match_score=0.0)
    gated, error = _drive_through_a_jump(SlamConfig(**weak))
    assert gated.fallback_matches >= 1
    assert error[6, :2].max() > 0.2  # the prediction: the whole jump
    kept, kept_error = _drive_through_a_jump(SlamConfig(**weak, weak_match_max_sigma=1e9))
    assert kept.fallback_matches == 0 and kept_error[6, :2].max() < 0.05
