"""Real-map sensor-model pieces: free space's edge with unknown space as a surface, the dense refinement at rest
(its prior along directions the scan does not pin, its pass-through check on thick walls), yawed maps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common.map_io import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from services.localization.amcl import Amcl, AmclParams, ParticleFilter, ScanBeams, select_beams
from services.localization.realmap import MOUNT, GridLaser
from services.localization.refine import BeamModel, interpolated_distance, refine_pose

RES = 0.05


def hall(edge_unknown: bool, wall_cells: int = 1) -> OccupancyMap:
    """A 10 m x 4 m hall: occupied side walls ``wall_cells`` thick; its west end is occupied, or (``edge_unknown``)
    free space simply ends there against unknown space, as on a SLAM map; an occupied pillar in it."""
    data = np.full((120, 300), UNKNOWN, dtype=np.int8)
    data[20:100, 50:250] = FREE
    data[20 - wall_cells:20, 50 - wall_cells:250 + wall_cells] = OCCUPIED
    data[100:100 + wall_cells, 50 - wall_cells:250 + wall_cells] = OCCUPIED
    data[20:100, 250:250 + wall_cells] = OCCUPIED
    if not edge_unknown:
        data[20:100, 50 - wall_cells:50] = OCCUPIED
    data[70:76, 180:186] = OCCUPIED
    return OccupancyMap(data, RES, (0.0, 0.0, 0.0))


def dense_beams(laser: GridLaser, pose: tuple[float, float, float], params: AmclParams, max_beams: int
                ) -> ScanBeams:
    return select_beams(laser.scan(pose), laser.angle_min, laser.angle_increment, laser.range_min, laser.range_max,
                        params, max_beams=max_beams)


def test_free_space_edge_against_unknown_is_a_surface():
    grid = hall(edge_unknown=True)
    pf = ParticleFilter(grid, AmclParams(random_seed=1))
    field = pf.field
    # corner (row 60, column 50): the west edge of free space, no occupied cell near it
    assert field.obstacle_distance_m[60, 50] > 1.0
    assert field.edge_distance_m[60, 50] == 0.0 and field.distance_m[60, 50] == 0.0
    # a scan of the west end explains its beams there (hits, not "unknown")
    pose = (4.0, 3.0, math.pi)
    laser = GridLaser(grid, rng=np.random.default_rng(2))
    beams = dense_beams(laser, pose, pf.params, 60)
    assert pf.explained_fraction(pose, beams.ranges, beams.bearings, MOUNT) > 0.95


def test_filter_at_rest_settles_on_the_truth_along_a_hall_ending_in_unknown():
    grid = hall(edge_unknown=True)
    params = AmclParams(random_seed=3)
    truth = (5.0, 2.0, math.pi)  # facing the west end, which alone pins x
    laser = GridLaser(grid, rng=np.random.default_rng(4))
    amcl = Amcl(grid, params)
    amcl.set_initial_pose((truth[0] + 0.1, truth[1], truth[2]), np.diag([0.1 ** 2, 0.05 ** 2, 0.02 ** 2]))
    for k in range(40):
        amcl.request_nomotion_update()
        amcl.process((0.0, 0.0, 0.0), dense_beams(laser, truth, params, params.max_beams), MOUNT, 0.1 * k)
    assert abs(amcl.estimate.pose[0] - truth[0]) < 0.03


def _refine(grid: OccupancyMap, truth, start, cov_diag, seed: int):
    params = AmclParams()
    pf = ParticleFilter(grid, params)
    laser = GridLaser(grid, rng=np.random.default_rng(seed))
    beams = dense_beams(laser, truth, params, 541)
    model = BeamModel(params.z_hit, params.z_rand / beams.range_max, params.sigma_hit, params.laser_likelihood_max_dist)
    return refine_pose(pf.field.exact_distance_m(), grid.origin, grid.resolution, model, start,
                       np.diag(cov_diag), beams.ranges, beams.bearings, MOUNT, occupied=pf.field.occupied)


def test_refinement_finds_the_pose_a_wall_thickness_away():
    """Thick walls: a pose shifted by their thickness puts the endpoints on the far faces, which the distance field
    alone scores as hits; the pass-through check does not."""
    grid = hall(edge_unknown=False, wall_cells=2)
    truth = (3.0, 2.0, 0.3)
    for seed, start in enumerate([(3.0, 2.1, 0.3), (2.93, 1.92, 0.31), (3.04, 2.05, 0.29)]):
        r = _refine(grid, truth, start, [0.03 ** 2, 0.03 ** 2, 0.01 ** 2], seed)
        assert r.used
        assert math.hypot(r.pose[0] - truth[0], r.pose[1] - truth[1]) < 0.01, (start, r)
        assert abs(r.pose[2] - truth[2]) < 0.005


def test_refinement_keeps_the_filter_where_the_scan_does_not_pin_the_pose():
    """In the middle of a long featureless corridor seen without its ends, x is unobserved: the prior (the filter's
    belief) keeps it, while y and theta, which the walls pin, are corrected."""
    data = np.full((60, 1200), UNKNOWN, dtype=np.int8)
    data[20:40, :] = FREE
    data[19, :] = OCCUPIED
    data[40, :] = OCCUPIED
    grid = OccupancyMap(data, RES, (0.0, 0.0, 0.0))
    truth = (30.0, 1.5, 0.0)
    start = (30.04, 1.53, 0.01)
    r = _refine(grid, truth, start, [0.02 ** 2, 0.02 ** 2, 0.01 ** 2], 5)
    assert abs(r.pose[0] - start[0]) < 0.01  # stays: nothing to say
    assert abs(r.pose[1] - truth[1]) < 0.01 and abs(r.pose[2] - truth[2]) < 0.004


def test_amcl_refines_on_request_only_when_tracking_and_moves_its_particles():
    grid = hall(edge_unknown=True)
    params = AmclParams(random_seed=7)
    amcl = Amcl(grid, params)
    truth = (6.0, 2.5, 2.5)
    laser = GridLaser(grid, rng=np.random.default_rng(7))
    amcl.set_initial_pose(truth, np.diag([0.02 ** 2, 0.02 ** 2, 0.01 ** 2]))
    t = 0.0
    for _ in range(30):
        t += 0.1
        amcl.request_nomotion_update()
        amcl.process((0.0, 0.0, 0.0), dense_beams(laser, truth, params, params.max_beams), MOUNT, t)
    assert amcl.state == "tracking"
    # shift the whole filter 6 cm off, as a filter that drifted while driving
    amcl.pf.poses[:amcl.pf.n, 0] += 0.06
    amcl.request_nomotion_update(refine=True)
    t += 0.1
    scan = laser.scan(truth)
    dense = select_beams(scan, laser.angle_min, laser.angle_increment, laser.range_min, laser.range_max, params,
                         max_beams=scan.size)
    amcl.process((0.0, 0.0, 0.0), dense_beams(laser, truth, params, params.max_beams), MOUNT, t, dense)
    assert amcl.last_refinement is not None and amcl.last_refinement.used
    # a 6 cm shift comes back to 0.0135-0.016 m over particle draws (seeds 1..20): judged at 0.02 m, whatever the seed
    assert math.hypot(amcl.estimate.pose[0] - truth[0], amcl.estimate.pose[1] - truth[1]) < 0.02
    mean_x = float(np.average(amcl.pf.poses[:amcl.pf.n, 0], weights=amcl.pf.weights[:amcl.pf.n]))
    assert abs(mean_x - truth[0]) < 0.03  # the particles moved with it
    assert not amcl.refine_pending


def test_yawed_map_is_resampled_onto_the_axis_aligned_raster():
    grid = hall(edge_unknown=False)
    yawed = OccupancyMap(grid.data, RES, (15.0, 6.0, math.pi))  # the same hall turned half a turn about (15, 6)
    pf = ParticleFilter(yawed, AmclParams(random_seed=1))
    assert pf.grid.origin[2] == 0.0
    assert np.array_equal(pf.grid.data, grid.data[::-1, ::-1])
    assert math.isclose(pf.grid.origin[0], 0.0, abs_tol=1e-6) and math.isclose(pf.grid.origin[1], 0.0, abs_tol=1e-6)


@pytest.mark.parametrize(("map_surface", "wall_cells"), [("face", 2), ("cell", 3)])
def test_beams_that_reach_their_end_through_a_wall_score_as_misses(map_surface: str, wall_cells: int):
    """Facing a thick wall head-on: a pose one wall thickness closer puts every endpoint on the wall's far face,
    a hit for the distance field alone; the pass-through check scores it far below the truth. With ``cell`` the
    check counts the cells behind a wall's first layer only: on a map built from scans a wall two cells thick is
    the band its surface's hits spread over."""
    from services.localization.refine import log_likelihood

    grid = hall(edge_unknown=False, wall_cells=wall_cells)
    params = AmclParams()
    pf = ParticleFilter(grid, params)
    truth = (11.0, 3.0, 0.0)  # 0.5 m from the inner face of the east wall (x = 12.5 ..)
    laser = GridLaser(grid, beams=541, fov_rad=math.radians(30.0), rng=np.random.default_rng(8))
    beams = dense_beams(laser, truth, params, 541)
    model = BeamModel(params.z_hit, params.z_rand / 20.0, params.sigma_hit, params.laser_likelihood_max_dist)
    poses = np.array([truth, (truth[0] + wall_cells * RES, truth[1], truth[2])])
    distance, walls = pf.field.refinement_fields(map_surface)
    args = (distance, grid.origin, grid.resolution, model, poses, beams.ranges, beams.bearings, MOUNT)
    plain = log_likelihood(*args)
    checked = log_likelihood(*args, occupied=walls)
    assert plain[1] > plain[0] - 0.3 * abs(plain[0])  # the field alone tells them apart poorly
    assert checked[1] < checked[0] - 100.0


def test_the_refinement_is_unbiased_on_a_map_built_from_scans():
    """A map built like SLAM builds one (``OccupancyGrid``: each hit marks the cell it fell in) from scans of the
    rendered hall at the true poses: the surface lies inside the first layer of wall cells, not on its free face.
    Refined from the truth with ``map_surface = "cell"``, the pose stays within 1 cm (``face`` is printed for
    comparison)."""
    from services.common.se2 import transform_points
    from services.localization.slam.occupancy import OccupancyGrid

    world = hall(edge_unknown=False, wall_cells=3)
    laser = GridLaser(world, rng=np.random.default_rng(3))
    route = [(3.0 + 0.25 * k, 2.0 + 1.5 * (k % 2), 0.4 * k) for k in range(30)]
    clouds = []
    for pose in route:
        r = laser.scan(pose)
        ok = np.isfinite(r)
        hits = np.column_stack([r[ok] * np.cos(laser.angles[ok]), r[ok] * np.sin(laser.angles[ok])])
        clouds.append(transform_points(np.asarray(MOUNT), hits))
    everything = np.concatenate([transform_points(np.asarray(p), c) for p, c in zip(route, clouds)])
    built = OccupancyGrid.covering(everything.min(axis=0), everything.max(axis=0), RES)
    built.origin_xy_m = built.origin_xy_m + 0.013  # a lattice that does not line up with the world's
    for pose, cloud in zip(route, clouds):
        built.insert_scan(np.asarray(pose), np.asarray(MOUNT[:2]), cloud)
    image = built.trinary_image()[::-1]
    data = np.where(image == 0, OCCUPIED, np.where(image == 254, FREE, UNKNOWN)).astype(np.int8)
    grid = OccupancyMap(data, RES, (float(built.origin_xy_m[0]), float(built.origin_xy_m[1]), 0.0))
    params = AmclParams()
    pf = ParticleFilter(grid, params)
    model = BeamModel(params.z_hit, params.z_rand / 20.0, params.sigma_hit, params.laser_likelihood_max_dist)
    check = GridLaser(world, rng=np.random.default_rng(4))
    errors: dict[str, list[float]] = {"face": [], "cell": []}
    for truth in [(3.5, 2.0, 0.0), (8.0, 3.2, 2.0), (11.5, 2.0, -0.7), (5.5, 4.3, 1.2)]:
        beams = dense_beams(check, truth, params, 541)
        for surface, found in errors.items():
            distance, walls = pf.field.refinement_fields(surface)
            r = refine_pose(distance, grid.origin, grid.resolution, model, truth,
                            np.diag([0.03 ** 2, 0.03 ** 2, 0.01 ** 2]), beams.ranges, beams.bearings, MOUNT,
                            occupied=walls)
            found.append(math.hypot(r.pose[0] - truth[0], r.pose[1] - truth[1]) if r.used else math.inf)
    print(f"refined from the truth on a map built from scans: face {errors['face']}, cell {errors['cell']}")
    assert max(errors["cell"]) < 0.01, errors


def test_a_requested_update_is_consumed_whatever_the_verdict_and_can_be_withdrawn():
    """localization/nomotion answers once its update ran: the request must be consumed by the settler's paths while
    localizing too (no refinement then), and a withdrawn request must not update on a later scan."""
    from services.localization.settle import AtRestSettler

    grid = hall(edge_unknown=True)
    params = AmclParams(random_seed=9)
    amcl, settler = Amcl(grid, params), AtRestSettler()
    truth = (6.0, 2.5, 2.5)
    laser = GridLaser(grid, rng=np.random.default_rng(10))
    amcl.set_initial_pose(truth, np.diag([0.02 ** 2, 0.02 ** 2, 0.01 ** 2]))
    assert amcl.state == "localizing"
    amcl.request_nomotion_update(refine=True)
    settler.process(amcl, (0.0, 0.0, 0.0), dense_beams(laser, truth, params, params.max_beams), MOUNT, 0.1,
                    dense_beams(laser, truth, params, 541))
    assert not amcl.refine_pending and amcl.last_refinement is None  # updated, not refined while localizing
    for k in range(30):  # converge at rest
        amcl.request_nomotion_update()
        amcl.process((0.0, 0.0, 0.0), dense_beams(laser, truth, params, params.max_beams), MOUNT, 0.2 + 0.1 * k)
    assert amcl.state == "tracking"
    updates = amcl.updates
    amcl.request_nomotion_update(refine=True)
    amcl.withdraw_nomotion_request()
    amcl.process((0.0, 0.0, 0.0), dense_beams(laser, truth, params, params.max_beams), MOUNT, 5.0,
                 dense_beams(laser, truth, params, 541))
    assert amcl.updates == updates and amcl.last_refinement is None
    amcl.request_nomotion_update(refine=True)
    amcl.process((0.0, 0.0, 0.0), dense_beams(laser, truth, params, params.max_beams), MOUNT, 5.1,
                 dense_beams(laser, truth, params, 541))
    assert amcl.updates == updates + 1 and amcl.last_refinement is not None and not amcl.refine_pending


def test_an_endpoint_just_past_the_map_edge_scores_at_the_edge() -> None:
    """A map whose free space reaches its edge (a cropped SLAM map): the edge is a surface, and a beam that range
    noise puts a centimetre past it is a hit a centimetre off, not a beam ending nowhere (that pulled poses 3 cm
    inwards on a real campus map)."""
    field = np.full((5, 5), 0.1)
    field[:, 4] = 0.0  # the last column of corners: the map's edge, a surface
    x = np.array([0.2, 0.21, 0.25, 1.0])
    d = interpolated_distance(field, (0.0, 0.0, 0.0), 0.05, x, np.full(4, 0.1), outside_m=2.0)
    assert d[0] == pytest.approx(0.0, abs=1e-6)
    assert d[1] == pytest.approx(0.01, abs=1e-6)
    assert d[2] == pytest.approx(0.05, abs=1e-6)
    assert d[3] == pytest.approx(0.8, abs=1e-6)  # far beyond: the distance to the edge, capped at outside_m


@pytest.mark.parametrize("map_surface", ["face", "cell"])
def test_the_compiled_scan_likelihood_matches_numpy(map_surface: str):
    """The C kernel (``_refine.c``) against the NumPy reference: poses all over the hall and beyond its edge (beams
    ending off the map), a rotated map origin, a mounted laser, with and without the pass-through check."""
    from services.localization import refine

    if refine._refine is None:
        pytest.skip("the _refine C extension was not built (no C compiler at install)")
    grid = hall(edge_unknown=False, wall_cells=2)
    params = AmclParams()
    pf = ParticleFilter(grid, params)
    laser = GridLaser(grid, beams=541, rng=np.random.default_rng(5))
    beams = dense_beams(laser, (6.0, 3.0, 0.3), params, 541)
    model = BeamModel(params.z_hit, params.z_rand / 20.0, params.sigma_hit, params.laser_likelihood_max_dist)
    distance, walls = pf.field.refinement_fields(map_surface)
    rng = np.random.default_rng(11)
    poses = np.column_stack([rng.uniform(-2.0, 16.0, 300), rng.uniform(-2.0, 8.0, 300), rng.uniform(-4.0, 4.0, 300)])
    origin = (grid.origin[0] - 0.3, grid.origin[1] + 0.2, 0.07)
    for occupied in (None, walls):
        args = (distance, origin, grid.resolution, model, poses, beams.ranges, beams.bearings, (0.25, 0.02, 0.01))
        compiled = refine.log_likelihood(*args, occupied=occupied)
        reference = refine.log_likelihood_numpy(*args, occupied=occupied)
        np.testing.assert_allclose(compiled, reference, rtol=1e-11, atol=1e-9)
