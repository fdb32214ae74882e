"""A re-localisation is trusted only once confirmed, and a good track is not declared lost by particles that found
other poses fitting the scan (services/localization/amcl.py, ``AmclParams.confirm_*`` and ``fit_drop``).

The rooms are small rasters, so that a global search covers them densely: one whose walls and furniture are
symmetric under a half turn about its centre (every scan fits two poses equally), and the same room without the twins
(one pose fits)."""

from __future__ import annotations

import math

import numpy as np

from services.common.map_io import FREE, OCCUPIED, OccupancyMap
from services.localization.amcl import Amcl, AmclParams, select_beams
from services.localization.realmap import GridLaser, RunTrace, dense, run
from services.localization.synthetic import MOUNT

RES_M = 0.05
#: the scans are 0.2 s apart: while not tracking the filter updates on every one (recovery_update_period_s)
PERIOD_S = 0.2


def room(symmetric: bool) -> OccupancyMap:
    """A 9 m x 5 m room with three boxes; ``symmetric``: each has a twin turned by a half turn about the centre."""
    h, w = 100, 180
    data = np.full((h, w), FREE, dtype=np.int8)
    data[:2, :] = data[-2:, :] = data[:, :2] = data[:, -2:] = OCCUPIED
    boxes = [(20, 36, 30, 50), (60, 64, 40, 80), (30, 70, 120, 124)]
    for r0, r1, c0, c1 in boxes:
        data[r0:r1, c0:c1] = OCCUPIED
    for r0, r1, c0, c1 in boxes if symmetric else []:
        data[h - r1:h - r0, w - c1:w - c0] = OCCUPIED
    return OccupancyMap(data, RES_M, (0.0, 0.0, 0.0))


def half_turn(pose: tuple[float, float, float]) -> tuple[float, float, float]:
    """The pose a half turn about the room's centre (4.5 m, 2.5 m) maps ``pose`` to."""
    return (9.0 - pose[0], 5.0 - pose[1], float(math.atan2(-math.sin(pose[2]), -math.cos(pose[2]))))


def at_rest(amcl: Amcl, laser: GridLaser, truth: tuple[float, float, float], scans: int, t0_s: float = 0.0
            ) -> list[tuple[str, str, float]]:
    """Scans from ``truth`` with the odometry standing still; per scan the verdict, its reason and the error (m)."""
    out = []
    for i in range(scans):
        beams = select_beams(laser.scan(truth), laser.angle_min, laser.angle_increment, laser.range_min,
                             laser.range_max, amcl.params)
        amcl.process((0.0, 0.0, 0.0), beams, MOUNT, t0_s + i * PERIOD_S)
        err = math.inf if amcl.estimate is None else math.hypot(amcl.estimate.pose[0] - truth[0],
                                                                amcl.estimate.pose[1] - truth[1])
        out.append((amcl.state, amcl.reason, err))
    return out


TRUTH = (4.0, 1.0, 0.4)


def global_params(**kw: float) -> AmclParams:
    """A small room needs fewer global particles; the first stage is long enough for the annealing (20 updates)
    plus the confirmation."""
    return AmclParams(random_seed=4, global_localization_particles=5000, recovery_attempt_s=10.0, **kw)


def test_the_test_room_is_symmetric_only_when_asked():
    sym, asym = room(True), room(False)
    assert np.array_equal(sym.data, sym.data[::-1, ::-1])
    assert not np.array_equal(asym.data, asym.data[::-1, ::-1])
    laser = GridLaser(sym, noise_m=0.0)
    assert np.allclose(laser.scan(TRUTH), laser.scan(half_turn(TRUTH)), atol=2 * RES_M)


def global_in_the_symmetric_room(confirm_updates: int) -> list[tuple[str, str, float]]:
    """Global localization in the symmetric room at rest: the particles end on one of the two poses (resampling
    the same view over and over depletes the other). The verdict of every scan."""
    grid = room(True)
    amcl = Amcl(grid, global_params(confirm_updates=confirm_updates))
    amcl.global_localization()
    return at_rest(amcl, GridLaser(grid, rng=np.random.default_rng(4)), TRUTH, 70)


def test_a_pose_with_an_equally_likely_twin_is_never_trusted():
    trace = global_in_the_symmetric_room(AmclParams().confirm_updates)
    assert "tracking" not in [s for s, _, _ in trace], "two poses fit every scan equally: neither may be trusted"
    assert any(r.startswith("ambiguous") for _, r, _ in trace), [r for _, r, _ in trace][-5:]


def test_without_confirmation_one_of_the_twins_is_tracked():
    """The case the confirmation exists for: unconfirmed, the filter claims one of two equally likely poses."""
    trace = global_in_the_symmetric_room(0)
    assert "tracking" in [s for s, _, _ in trace]


def test_global_localization_in_an_asymmetric_room_is_confirmed_on_the_true_pose():
    grid = room(False)
    amcl = Amcl(grid, global_params())
    amcl.global_localization()
    trace = at_rest(amcl, GridLaser(grid, rng=np.random.default_rng(4)), TRUTH, 80)
    states = [s for s, _, _ in trace]
    assert "tracking" in states
    first = states.index("tracking")
    assert any(r.startswith("confirming") for _, r, _ in trace[:first])
    assert all(e < 0.1 for s, _, e in trace if s == "tracking")


def test_particles_on_a_twin_pose_do_not_make_a_fitting_track_lost():
    """Particles that found the symmetric pose (as injected ones do in a self-similar building) spread the cloud
    far beyond lost_spread_m, but the track still explains the scans as well as before: it stays tracking on its own
    pose and the far particles are dropped."""
    grid = room(True)
    laser = GridLaser(grid, rng=np.random.default_rng(5))
    amcl = Amcl(grid, AmclParams(random_seed=5))
    amcl.set_initial_pose(TRUTH, np.diag([0.03 ** 2, 0.03 ** 2, 0.02 ** 2]))
    for k in range(12):
        amcl.request_nomotion_update()
        at_rest(amcl, laser, TRUTH, 1, k * PERIOD_S)
    assert amcl.state == "tracking"
    pf = amcl.pf
    twin = np.asarray(half_turn(TRUTH))
    moved = np.arange(0, pf.n, 3)  # a third of the particles onto the twin
    pf.poses[moved] = pf.poses[moved] - np.asarray(TRUTH) + twin
    amcl.request_nomotion_update()
    state, reason, err = at_rest(amcl, laser, TRUTH, 1, 12 * PERIOD_S)[0]
    assert amcl.spread_m > AmclParams().lost_spread_m
    assert state == "tracking", reason
    assert err < 0.1
    assert np.all(np.hypot(pf.poses[:pf.n, 0] - TRUTH[0], pf.poses[:pf.n, 1] - TRUTH[1]) < 1.0)


def test_a_kidnapped_robot_is_lost_at_once_and_never_tracks_a_wrong_pose():
    grid = room(False)
    laser = GridLaser(grid, rng=np.random.default_rng(6))
    amcl = Amcl(grid, AmclParams(random_seed=6))
    amcl.set_initial_pose(TRUTH, np.diag([0.03 ** 2, 0.03 ** 2, 0.02 ** 2]))
    for k in range(12):
        amcl.request_nomotion_update()
        at_rest(amcl, laser, TRUTH, 1, k * PERIOD_S)
    assert amcl.state == "tracking"
    carried_to = (6.8, 1.2, 2.5)
    trace = at_rest(amcl, laser, carried_to, 100, 12 * PERIOD_S)
    states = [s for s, _, _ in trace]
    assert "lost" in states[:5], "the kidnapping is noticed within a second"
    noticed = states.index("lost")
    wrong = [(i, r, e) for i, (s, r, e) in enumerate(trace) if i > noticed and s == "tracking" and e > 0.2]
    assert not wrong, wrong[:3]


#: along the asymmetric room, a turn in place and across it, driving at 0.2 m/s and turning at 0.5 rad/s with scans
#: at 25 Hz (8 mm, 0.02 rad apart)
LAP = [(0.8, 0.6, 0.0), (5.5, 0.6, 0.0), (5.5, 0.6, 1.57), (5.5, 3.0, 1.57)]
SCAN_PERIOD_S = 0.04


def lap(scan_lag: int, kidnap_to: tuple[float, float, float] | None = None, seed: int = 8) -> tuple[Amcl, RunTrace]:
    """The lap with every scan stamped ``scan_lag`` periods late (the odometry it is placed with is that of a pose
    the robot reached later); ``kidnap_to``: halfway along the first leg the robot is carried there and drives on
    from it."""
    grid = room(False)
    laser = GridLaser(grid, beams=181, rng=np.random.default_rng(seed))
    truth = dense(LAP, 0.2 * SCAN_PERIOD_S, 0.5 * SCAN_PERIOD_S)
    kidnap_at = None
    if kidnap_to is not None:
        kidnap_at = 290
        dx, dy = kidnap_to[0] - truth[kidnap_at][0], kidnap_to[1] - truth[kidnap_at][1]
        truth = truth[:kidnap_at] + [(x + dx, y + dy, th) for x, y, th in truth[kidnap_at:kidnap_at + 150]]
    amcl = Amcl(grid, AmclParams(random_seed=seed))
    amcl.set_initial_pose(truth[0], np.diag([0.03 ** 2, 0.03 ** 2, 0.02 ** 2]))
    return amcl, run(amcl, laser, truth, seed=seed, scan_period_s=SCAN_PERIOD_S, kidnap_at=kidnap_at,
                     scan_lag=scan_lag)


def test_scans_half_a_second_late_do_not_make_a_good_track_lost():
    """Placed at a pose odometry has already moved past (0.1 m on the legs, 0.24 rad where a turn starts), the scans
    match the map poorly (score below lost_score) while the track is right: hill-climbed from the poses odometry
    held over the last moments, the scan fits as well as the track did, so the verdict stays tracking."""
    amcl, trace = lap(scan_lag=12)
    assert amcl.low_scores_discounted > 0, "the lag must bring the score below lost_score for the test to mean much"
    assert "lost" not in trace.states, [i for i, s in enumerate(trace.states) if s == "lost"][:5]
    assert max(trace.errors_xy_m) < 0.3


def test_a_kidnapping_with_scans_half_a_second_late_is_still_noticed_within_half_a_second():
    amcl, trace = lap(scan_lag=12, kidnap_to=(3.0, 4.2, 0.0))
    t = np.array(trace.times_s)
    fault_s = 290 * SCAN_PERIOD_S
    lost = [ti for ti, s in zip(t, trace.states, strict=True) if ti >= fault_s and s == "lost"]
    assert lost and lost[0] - fault_s <= 0.5, lost[:1]
    assert "scan match" in amcl.lost_reason and "fit" in amcl.lost_reason, amcl.lost_reason
