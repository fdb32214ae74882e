"""Open-loop drift between loop closures: the odometry's systematic error is calibrated out of the prediction, and
the loop-closure search widens with the pose uncertainty accumulated since the last accepted closure."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common.se2 import between, compose
from services.localization.slam.mapper import GraphSlam, LoopClosure, SlamConfig
from services.localization.slam.odometry_calibration import OdometryCalibration
from services.localization.slam.search_gate import position_sigma_m, propagate, relative_sigmas, scaled
from tests.test_slam_constraint import ROOM, _scanner


def test_calibration_recovers_scale_rotation_scale_and_drift():
    scale, rotation_scale, drift = 0.96, 1.03, math.radians(-1.5)  # truth = model(odometry)
    rng = np.random.default_rng(2)
    calibration = OdometryCalibration()
    for _ in range(400):
        path_m = rng.uniform(0.0, 0.6)
        heading = rng.uniform(-np.pi, np.pi)
        odom_t = path_m * np.array([math.cos(heading), math.sin(heading)])
        odom_turn = rng.uniform(-0.25, 0.25)
        calibration.observe(odom_t, odom_turn, path_m, scale * odom_t + rng.normal(0, 0.003, 2),
                            rotation_scale * odom_turn + drift * path_m + rng.normal(0, 0.002))
    assert calibration.scale == pytest.approx(scale, abs=0.005)
    assert calibration.rotation_scale == pytest.approx(rotation_scale, abs=0.01)
    assert math.degrees(calibration.drift_rad_per_m) == pytest.approx(math.degrees(drift), abs=0.1)
    np.testing.assert_allclose(calibration.correct(np.array([0.3, -0.4, 0.1])),
                               [0.3 * scale, -0.4 * scale, 0.1 * rotation_scale + 0.5 * drift], atol=0.005)


def test_calibration_starts_at_identity_stays_bounded_and_rejects_bad_input():
    calibration = OdometryCalibration(max_scale_error=0.2)
    np.testing.assert_array_equal(calibration.correct(np.array([0.1, 0.2, 0.3])), [0.1, 0.2, 0.3])
    for _ in range(100):  # a wheel reading three times the truth: clamped, not believed
        calibration.observe(np.array([0.5, 0.0]), 0.0, 0.5, np.array([1.5, 0.0]), 0.0)
    assert calibration.scale == pytest.approx(1.2)
    with pytest.raises(ValueError, match="finite"):
        calibration.observe(np.array([np.nan, 0.0]), 0.0, 0.5, np.array([0.5, 0.0]), 0.0)
    with pytest.raises(ValueError, match="horizon"):
        OdometryCalibration(horizon_m=0.0)


def _drive_on_biased_odometry(config: SlamConfig) -> GraphSlam:
    """A lap of the room (3 m sides, 0.1 m apart, quarter turns in 8 steps) on odometry that reads 5 % long and
    turns 2°/m to the left."""
    scan = _scanner(ROOM)
    truth, pose = [], np.array([-2.0, -1.5, 0.0])
    for _ in range(3):
        for _ in range(25):
            truth.append(pose.copy())
            pose = compose(pose, np.array([0.1, 0.0, 0.0]))
        for _ in range(8):
            truth.append(pose.copy())
            pose = compose(pose, np.array([0.0, 0.0, math.pi / 16]))
    odom = [truth[0]]
    for a, b in zip(truth[:-1], truth[1:], strict=True):
        step = between(a, b)
        dist = float(np.hypot(step[0], step[1]))
        odom.append(compose(odom[-1], np.array([1.05 * step[0], 1.05 * step[1], step[2] + math.radians(2.0) * dist])))
    slam = GraphSlam(config)
    for k, (t, o) in enumerate(zip(truth, odom, strict=True)):
        slam.add_scan(float(k), o, scan(t))
    return slam


def test_the_mapper_learns_the_odometry_error_from_its_matches():
    """The calibration the mapper keeps moves from identity towards the inverse of the odometry's error (scale
    1/1.05 = 0.952, drift −2°/m), from matched keyframes only; with calibration off the prediction stays raw."""
    slam = _drive_on_biased_odometry(SlamConfig())
    calibration = slam.odometry_calibration
    assert calibration.observations >= 10
    assert 0.94 < calibration.scale < 0.985, calibration.scale
    assert -2.5 < math.degrees(calibration.drift_rad_per_m) < -0.5, math.degrees(calibration.drift_rad_per_m)
    raw = _drive_on_biased_odometry(SlamConfig(calibrate_odometry=False))
    step = np.array([0.1, 0.0, 0.0])
    assert raw.config.calibrate_odometry is False
    assert np.abs(calibration.correct(step) - step).max() > 0.002


def test_uncertainty_grows_along_a_path_and_widens_the_search_gate():
    """A heading spread per step swings the later positions sideways: 10 steps of 1 m with σ_θ² = q per step give a
    lateral variance Σ_k q·(10 − k)² (k = 1..10, heading error of step k acting over the 10 − k metres after it)."""
    q = 1e-4
    step_covariance = np.diag([0.0, 0.0, q])
    covariance, pose = np.zeros((3, 3)), np.zeros(3)
    for _ in range(10):
        covariance = propagate(covariance, pose, np.array([1.0, 0.0, 0.0]), step_covariance)
        pose = compose(pose, np.array([1.0, 0.0, 0.0]))
    assert covariance[1, 1] == pytest.approx(q * sum((10 - k) ** 2 for k in range(1, 11)))
    assert covariance[0, 0] == pytest.approx(0.0, abs=1e-12) and covariance[2, 2] == pytest.approx(10 * q)
    sigma = position_sigma_m(covariance)
    assert sigma == pytest.approx(math.sqrt(covariance[1, 1]))
    assert scaled(4.0, 3.0, sigma, 12.0) == pytest.approx(4.0 + 3.0 * sigma)
    assert scaled(4.0, 3.0, 100.0, 12.0) == 12.0 and scaled(4.0, 3.0, 0.0, 12.0) == 4.0


def test_the_gate_uses_the_uncertainty_relative_to_the_candidate():
    """Σ_jk = Σ_k − A_jk Σ_j A_jkᵀ on one chain: a keyframe j driven just before k is only as uncertain relative to
    k as the edges between them, while the 20 m chain from the anchor is the full Σ_k; a keyframe propagated from an
    older anchor (seen before the last closure) gets Σ_k whole."""
    step_covariance = np.diag([1e-4, 1e-4, 1e-4])
    covariance, pose = np.zeros((3, 3)), np.zeros(3)
    covariances, positions = [covariance], [pose[:2].copy()]
    for _ in range(20):
        covariance = propagate(covariance, pose, np.array([1.0, 0.0, 0.0]), step_covariance)
        pose = compose(pose, np.array([1.0, 0.0, 0.0]))
        covariances.append(covariance)
        positions.append(pose[:2].copy())
    anchors = np.zeros(21, int)
    anchors[:3] = -1  # propagated before the anchor moved
    sigma_xy, sigma_theta = relative_sigmas(covariance, pose[:2], 0, np.array(covariances), np.array(positions),
                                            anchors)
    assert sigma_xy[3] == pytest.approx(position_sigma_m(covariance - _carried(covariances[3], positions[3], pose)))
    assert sigma_xy[0] == pytest.approx(position_sigma_m(covariance))
    assert sigma_theta[0] == pytest.approx(math.sqrt(covariance[2, 2]))
    assert sigma_xy[20] == pytest.approx(0.0, abs=1e-9) and sigma_theta[20] == pytest.approx(0.0, abs=1e-9)
    # two steps back: what two edges add, seen from 2 m (heading errors swing 1 and 0 m): 1e-4·(2 + 1²) laterally
    assert sigma_xy[18] == pytest.approx(math.sqrt(1e-4 * 3), rel=1e-6)
    assert sigma_xy[18] < 0.1 * sigma_xy[3]


def _carried(covariance: np.ndarray, position: np.ndarray, pose: np.ndarray) -> np.ndarray:
    lever = np.eye(3)
    lever[0, 2], lever[1, 2] = -(pose[1] - position[1]), pose[0] - position[0]
    out: np.ndarray = lever @ covariance @ lever.T
    return out


def test_an_accepted_closure_anchors_the_uncertainty():
    """The newest keyframe's uncertainty grows with every keyframe edge; a closure accepted at an earlier keyframe
    restarts it from the closure's covariance, propagated over the edges since."""
    scan = _scanner(ROOM)
    slam = GraphSlam(SlamConfig(loop_search_sigmas=3.0))
    traces = []
    for k in range(30):
        pose = np.array([-2.5 + 0.15 * k, -0.5, 0.0])
        slam.add_scan(float(k), pose, scan(pose))
        traces.append(float(np.trace(slam.drift_covariance)))
    assert slam.n_keyframes >= 6 and traces[-1] > traces[0]
    assert all(b >= a for a, b in zip(traces, traces[1:], strict=False))
    grown = slam.drift_covariance.copy()
    to = slam.n_keyframes - 3
    poses = slam.graph.poses()
    closure = LoopClosure(0, to, between(poses[0], poses[to]), 0.0)
    slam._accept(closure)
    loop_covariance = np.linalg.inv(slam._loop_info)
    assert np.trace(slam.drift_covariance) < np.trace(grown)
    assert np.trace(slam.drift_covariance) > np.trace(loop_covariance)  # two edges propagated on top


def test_a_loop_grid_built_before_the_path_passed_its_centre_is_rebuilt():
    """The loop grid of a keyframe first searched while the path had not gone past it lacks its later neighbours;
    reusing it for a revisit would match against half the place (edmonton: a widened search's early look-ups
    cost a closure pair of the real revisit and 8 of 26 closures)."""
    scan = _scanner(ROOM)
    slam = GraphSlam()
    for k in range(40):
        pose = np.array([-2.5 + 0.13 * k, -0.5 + 0.02 * k, 0.0])
        slam.add_scan(float(k), pose, scan(pose))
    n = slam.n_keyframes
    assert n >= 8
    half = slam._loop_grid(2, 2)
    assert slam._loop_grid(2, 2) is half  # same keyframes: cached
    full = slam._loop_grid(2, n - 1)
    assert full is not half
    assert slam._loop_grid(2, n - 1) is full
