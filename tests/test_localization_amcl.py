"""AMCL core pieces: beam step, KLD limit, motion model, sensor model, resampling, clusters, gates, odom history."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common.map_io import OccupancyMap
from services.common.se2 import compose, inverse
from services.common.world import World
from services.localization.amcl import (
    Amcl,
    AmclParams,
    ParticleFilter,
    ScanBeams,
    beam_indices,
    cluster_labels,
    kld_limit,
    select_beams,
)
from services.localization.odom_history import OdomHistory
from services.localization.synthetic import Laser


def room() -> tuple[World, OccupancyMap]:
    world = World.from_rectangles("room", 0.05, [-0.5, -0.5, 8.5, 4.5], [[0.0, 0.0, 8.0, 4.0]], [[5.0, 1.0, 5.5, 2.0]])
    return world, world.occupancy_map()


def test_beam_step_matches_nav2():
    assert beam_indices(541, 60).size == 61  # step (541 - 1) // 59 = 9
    assert beam_indices(10, 60).tolist() == list(range(10))


def test_select_beams_drops_invalid_returns():
    ranges = np.array([1.0, np.inf, np.nan, 0.01, 20.0, 5.0], dtype=np.float32)
    beams = select_beams(ranges, -1.0, 0.5, 0.05, 20.0, AmclParams(max_beams=60))
    assert beams.ranges.tolist() == [1.0, 5.0]
    assert beams.bearings.tolist() == pytest.approx([-1.0, 1.5])
    beams = select_beams(ranges, -1.0, 0.5, 0.05, 20.0, AmclParams(laser_max_range=3.0))
    assert beams.ranges.tolist() == [1.0] and beams.range_max == 3.0


def test_kld_limit():
    assert kld_limit(1, 0.05, 0.99, 500, 2000) == 500  # one bin: the minimum (pf.c asks for the maximum)
    assert kld_limit(2, 0.05, 0.99, 500, 2000) == 500
    limits = [kld_limit(k, 0.01, 3.0, 1, 10**6) for k in range(2, 200)]
    assert limits == sorted(limits) and limits[-1] > 10 * limits[0]


def test_se2_helpers():
    a = (1.0, 2.0, 0.7)
    b = (-0.3, 0.5, -2.0)
    assert compose(compose(a, b), inverse(b)) == pytest.approx(a)
    assert compose(a, inverse(a)) == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)


def test_motion_model_without_noise_moves_each_particle_in_its_own_frame():
    _, grid = room()
    params = AmclParams(min_particles=2, max_particles=2, alpha1=0, alpha2=0, alpha3=0, alpha4=0, alpha5=0)
    pf = ParticleFilter(grid, params, np.random.default_rng(0))
    pf.poses[:2] = [(1.0, 1.0, 0.0), (2.0, 2.0, math.pi / 2)]
    # odometry: from (0, 0, 0.2) forward 1 m and left 0.5 m in the body frame, turning 0.3 rad
    old = (0.0, 0.0, 0.2)
    new = compose(old, (1.0, 0.5, 0.3))
    pf.motion_update(new, (new[0] - old[0], new[1] - old[1], new[2] - old[2]))
    assert tuple(pf.poses[0]) == pytest.approx(compose((1.0, 1.0, 0.0), (1.0, 0.5, 0.3)))
    assert tuple(pf.poses[1]) == pytest.approx(compose((2.0, 2.0, math.pi / 2), (1.0, 0.5, 0.3)))


def test_motion_model_noise_follows_the_alphas():
    _, grid = room()
    params = AmclParams(min_particles=1, max_particles=20000, global_localization_particles=0,
                        alpha1=0.0, alpha2=0.0, alpha3=0.04, alpha4=0.0, alpha5=0.01)
    pf = ParticleFilter(grid, params, np.random.default_rng(1))
    pf.poses[:] = (2.0, 2.0, 0.0)
    pf.motion_update((1.0, 0.0, 0.0), (1.0, 0.0, 0.0))
    # sigma_trans = sqrt(a3) * 1 m = 0.2 along x; sigma_strafe = sqrt(a5) * 1 m = 0.1 across
    assert np.mean(pf.poses[:, 0]) == pytest.approx(3.0, abs=0.01)
    assert np.std(pf.poses[:, 0]) == pytest.approx(0.2, rel=0.05)
    assert np.std(pf.poses[:, 1]) == pytest.approx(0.1, rel=0.05)
    assert np.std(pf.poses[:, 2]) == 0.0


@pytest.mark.parametrize("model", ["likelihood_field", "likelihood_field_prob"])
def test_sensor_model_prefers_the_true_pose(model):
    world, grid = room()
    true = (3.0, 2.5, 0.4)
    laser = Laser(world, noise_m=0.0)
    params = AmclParams(min_particles=5, max_particles=5, laser_model_type=model)
    beams = select_beams(laser.scan(true, (0.45, 0.0, 0.0)), laser.angle_min, laser.angle_increment, 0.05, 20.0,
                         params)
    pf = ParticleFilter(grid, params, np.random.default_rng(0))
    pf.poses[:5] = [true, (3.2, 2.5, 0.4), (3.0, 2.3, 0.4), (3.0, 2.5, 0.5), (6.5, 3.0, 2.0)]
    pf.weights[:5] = 0.2
    pf.sensor_update(beams.ranges, beams.bearings, (0.45, 0.0, 0.0), beams.range_max)
    assert int(np.argmax(pf.weights[:5])) == 0
    assert pf.weights[:5].sum() == pytest.approx(1.0)


def test_resampling_kld_and_low_variance():
    _, grid = room()
    params = AmclParams(min_particles=100, max_particles=3000, recovery_alpha_slow=0.0, global_localization_particles=0)
    pf = ParticleFilter(grid, params, np.random.default_rng(2))
    pf.init_uniform()
    assert pf.n == 3000
    pf.resample()
    assert pf.n > 1000  # spread over the whole room: many bins, many particles
    pf.init_gaussian((2.0, 2.0, 0.0), np.diag([0.01, 0.01, 0.001]))
    assert pf.temperature == 1.0  # a pose given by hand ends the annealing of the global start
    pf.weights[: pf.n] = 0.0
    pf.weights[7] = 1.0  # all the weight on one particle: every copy is that particle
    kept = tuple(pf.poses[7])
    pf.resample()
    assert 100 <= pf.n < 3000
    assert np.all(pf.poses[: pf.n] == kept)


def test_random_injection_when_the_fast_average_drops():
    _, grid = room()
    params = AmclParams(min_particles=500, max_particles=500, recovery_sensor_reset=False)
    pf = ParticleFilter(grid, params, np.random.default_rng(3))
    pf.init_gaussian((2.0, 2.0, 0.0), np.diag([1e-4, 1e-4, 1e-4]))
    pf.w_slow, pf.w_fast = 0.5, 0.25
    assert pf.injection_probability() == pytest.approx(0.5)
    pf.resample()
    far = np.hypot(pf.poses[: pf.n, 0] - 2.0, pf.poses[: pf.n, 1] - 2.0) > 0.5
    assert 0.3 < far.mean() < 0.7
    assert pf.w_slow == pf.w_fast == 0.5  # w_fast restarts from w_slow, which keeps the tracking level


def test_estimate_takes_the_heaviest_cluster_and_wraps_heading():
    _, grid = room()
    params = AmclParams(min_particles=1, max_particles=400)
    pf = ParticleFilter(grid, params, np.random.default_rng(4))
    rng = np.random.default_rng(5)
    pf.poses[:200] = np.column_stack([rng.normal(1.0, 0.05, 200), rng.normal(1.0, 0.05, 200),
                                      rng.choice([math.pi - 0.02, -math.pi + 0.02], 200)])
    pf.poses[200:400] = np.column_stack([rng.normal(6.0, 0.05, 200), rng.normal(3.0, 0.05, 200), np.zeros(200)])
    pf.weights[:200] = 0.6 / 200
    pf.weights[200:400] = 0.4 / 200
    labels = cluster_labels(pf.poses[:400])
    assert len(set(labels[:200].tolist())) == 1 and labels[0] != labels[300]
    est = pf.estimate()
    assert est.pose[:2] == pytest.approx((1.0, 1.0), abs=0.02)
    assert abs(abs(est.pose[2]) - math.pi) < 0.01
    assert est.weight == pytest.approx(0.6)
    assert 0 < est.covariance[0, 0] < 0.01 and est.covariance[2, 2] < 0.01


def test_update_gates_and_nomotion():
    world, grid = room()
    params = AmclParams(update_min_d=0.2, update_min_a=0.2, random_seed=1)
    amcl = Amcl(grid, params)
    laser = Laser(world)
    beams = lambda pose: select_beams(laser.scan(pose, (0.45, 0, 0)), laser.angle_min,  # noqa: E731
                                      laser.angle_increment, 0.05, 20.0, params)
    amcl.set_initial_pose((2.0, 2.0, 0.0), np.diag([0.01, 0.01, 0.01]))
    assert amcl.process((0.0, 0.0, 0.0), beams((2.0, 2.0, 0.0)), (0.45, 0, 0))  # first scan always updates
    assert not amcl.process((0.1, 0.0, 0.0), beams((2.1, 2.0, 0.0)), (0.45, 0, 0))
    assert amcl.process((0.25, 0.0, 0.0), beams((2.25, 2.0, 0.0)), (0.45, 0, 0))
    assert not amcl.process((0.25, 0.0, 0.1), beams((2.25, 2.0, 0.1)), (0.45, 0, 0))
    amcl.request_nomotion_update()
    assert amcl.process((0.25, 0.0, 0.1), beams((2.25, 2.0, 0.1)), (0.45, 0, 0))
    assert amcl.updates == 3
    est = compose(amcl.map_odom, (0.25, 0.0, 0.1))
    assert math.hypot(est[0] - 2.25, est[1] - 2.0) < 0.05
    empty = ScanBeams(np.empty(0), np.empty(0), 20.0)
    amcl.request_nomotion_update()
    assert amcl.process((0.25, 0.0, 0.1), empty, (0.45, 0, 0))  # no beams: motion only, no crash


def test_bad_parameters_are_named():
    _, grid = room()
    with pytest.raises(ValueError, match="min_particles"):
        ParticleFilter(grid, AmclParams(min_particles=10, max_particles=5))
    with pytest.raises(ValueError, match="alpha3"):
        ParticleFilter(grid, AmclParams(alpha3=-1.0))
    with pytest.raises(ValueError, match="no free cell"):
        ParticleFilter(OccupancyMap(np.full((5, 5), 100, dtype=np.int8), 0.1), AmclParams())


def test_odom_history_interpolates_and_bounds():
    h = OdomHistory(keep_s=1.0)
    h.add(10.0, (0.0, 0.0, 3.0))
    h.add(10.2, (1.0, 2.0, -3.0))  # heading crosses +-pi: interpolate along the short arc
    x, y, th = h.at(10.1, 0.05)
    assert (x, y) == pytest.approx((0.5, 1.0))
    assert abs(abs(th) - math.pi) < 1e-9
    assert h.at(10.23, 0.05) == (1.0, 2.0, -3.0)
    assert h.at(10.5, 0.05) is None and h.at(9.0, 0.05) is None
    h.add(10.1, (5.0, 5.0, 0.0))  # out of order: ignored
    assert h.latest_stamp == 10.2
    h.add(12.0, (2.0, 2.0, 0.0))
    assert list(h.stamps) == [12.0]


MOUNT = (0.45, 0.0, 0.0)


def room_filter(seed: int):
    """AMCL on the room's map and the beams a laser at MOUNT sees from a pose of the room."""
    world, grid = room()
    params = AmclParams(random_seed=seed)
    laser = Laser(world)

    def beams(pose):
        return select_beams(laser.scan(pose, MOUNT), laser.angle_min, laser.angle_increment, 0.05, 20.0, params)

    return Amcl(grid, params), beams


def test_reanchor_after_an_odometry_restart_keeps_the_map_pose():
    amcl, beams = room_filter(2)
    mount = MOUNT
    amcl.set_initial_pose((2.0, 2.0, 0.0), np.diag([0.01, 0.01, 0.01]))
    amcl.process((10.0, -3.0, 1.0), beams((2.0, 2.0, 0.0)), mount)
    amcl.reanchor_odometry()  # drive restarted: odometry starts again at zero, the robot has not moved
    assert amcl.process((0.0, 0.0, 0.0), beams((2.0, 2.0, 0.0)), mount)
    est = compose(amcl.map_odom, (0.0, 0.0, 0.0))
    assert math.hypot(est[0] - 2.0, est[1] - 2.0) < 0.05 and abs(est[2]) < 0.03


def test_scans_taken_before_the_initial_pose_are_ignored():
    amcl, beams = room_filter(3)
    mount = MOUNT
    amcl.set_initial_pose((2.0, 2.0, 0.0), np.diag([0.01, 0.01, 0.01]), stamp_s=10.0)
    # a scan still in flight from where the robot stood before it was placed (6.5, 3, pi) must not move the filter
    assert not amcl.process((0.0, 0.0, 0.0), beams((6.5, 3.0, math.pi)), mount, stamp=9.9)
    assert amcl.stale_scans_ignored == 1 and amcl.updates == 0
    assert amcl.process((0.0, 0.0, 0.0), beams((2.0, 2.0, 0.0)), mount, stamp=10.05)
    est = compose(amcl.map_odom, (0.0, 0.0, 0.0))
    assert math.hypot(est[0] - 2.0, est[1] - 2.0) < 0.05

