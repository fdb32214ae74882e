"""The filter's verdict on real SLAM maps: a kidnapping is noticed within a second, and after it the filter either
tracks the right pose again or keeps saying it is lost (never tracking a wrong pose at the end)."""

from __future__ import annotations

import numpy as np
import pytest

from services.common.map_io import load_map
from services.localization.amcl import Amcl, AmclParams
from services.localization.realmap import (
    SCAN_PERIOD_S,
    SCAN_STEP_M,
    GridLaser,
    axis_aligned,
    dense,
    initial_pose_trial,
    kidnap_trial,
    random_route,
    run,
)


@pytest.fixture
def levine(shared_dir):
    return load_map(shared_dir / "data" / "maps" / "upenn_levine" / "levine.yaml")


def test_tracking_on_a_real_map_says_tracking_and_stays_close(levine):
    grid = axis_aligned(levine)
    laser = GridLaser(grid, rng=np.random.default_rng(3))
    truth = dense(random_route(laser, np.random.default_rng(3), length_m=15.0))
    amcl = Amcl(grid, AmclParams(random_seed=3))
    amcl.set_initial_pose(truth[0], np.diag([0.05 ** 2, 0.05 ** 2, 0.03 ** 2]))
    trace = run(amcl, laser, truth, seed=3)
    states = np.array(trace.states)
    assert max(trace.errors_xy_m) < 0.3
    assert np.mean(states[10:] == "tracking") > 0.95, "a correct filter must not be called lost"
    assert "lost" not in states


def test_scans_half_a_second_late_on_a_real_map_keep_the_track(levine):
    """Scans stamped 0.48 s late (12 periods at 25 Hz), driving at 0.2 m/s and turning at 0.5 rad/s: the score dips
    below lost_score where turns start, the track is right all along, and the verdict stays tracking (before the
    low-score hysteresis this route went lost and re-localised 62 m off; seeds 2 and 3 went lost too)."""
    seed = 1
    grid = axis_aligned(levine)
    laser = GridLaser(grid, rng=np.random.default_rng(seed))
    truth = dense(random_route(laser, np.random.default_rng(seed), length_m=12.0), SCAN_STEP_M, 0.02)
    amcl = Amcl(grid, AmclParams(random_seed=seed))
    amcl.set_initial_pose(truth[0], np.diag([0.05 ** 2, 0.05 ** 2, 0.03 ** 2]))
    trace = run(amcl, laser, truth, seed=seed, scan_period_s=SCAN_PERIOD_S, scan_lag=12)
    assert amcl.low_scores_discounted > 0
    assert "lost" not in trace.states
    assert max(trace.errors_xy_m) < 0.3


@pytest.mark.slow
def test_kidnapping_on_a_real_map_is_detected_within_a_second(levine):
    trial = kidnap_trial(levine, 1, AmclParams(random_seed=1))
    print(f"\nkidnapping on upenn_levine: {trial}")
    assert trial.detect_s is not None and trial.detect_s <= 1.0
    assert trial.outcome in ("recovered", "reports_lost")


@pytest.mark.slow
def test_a_corrupted_initial_pose_recovers_or_is_reported(levine):
    trial = initial_pose_trial(levine, 2, AmclParams(random_seed=2))
    print(f"\ninitial pose 2 m off on upenn_levine: {trial}")
    assert trial.outcome in ("recovered", "reports_lost")
