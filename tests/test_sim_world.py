"""The simulator's world: loading, ray casting against a brute-force march, obstacles, map rendering."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import yaml

from services.common.world import World, WorldError, builtin_worlds, load_world


@pytest.fixture(scope="module")
def corridor() -> World:
    return World.load_builtin("corridor")


def brute_range(world: World, x: float, y: float, angle: float, max_range: float, step: float = 0.0005) -> float:
    """Sample the beam every 0.5 mm and return the first sample in a solid cell (the reference to match)."""
    t = np.arange(0.0, max_range, step)
    rows = np.floor((y + t * math.sin(angle) - world.origin_xy[1]) / world.resolution_m).astype(int)
    cols = np.floor((x + t * math.cos(angle) - world.origin_xy[0]) / world.resolution_m).astype(int)
    inside = (rows >= 0) & (rows < world.shape[0]) & (cols >= 0) & (cols < world.shape[1])
    solid = ~inside
    solid[inside] = world.solid[rows[inside], cols[inside]]
    hits = np.flatnonzero(solid)
    return float(t[hits[0]]) if hits.size else max_range


def test_builtin_worlds_load_with_goals_and_free_start() -> None:
    assert {"corridor", "empty_room", "loop"} <= set(builtin_worlds())
    for name in builtin_worlds():
        w = World.load_builtin(name)
        x, y, _ = w.start_pose
        assert not w.circle_collides(x, y, 0.63), f"{name}: start pose collides"
        for g in w.goals:
            assert not w.circle_collides(g.pose[0], g.pose[1], 0.63), f"{name}: goal {g.id} collides"
    with pytest.raises(WorldError, match="no built-in world 'nope'"):
        World.load_builtin("nope")


def test_corridor_geometry(corridor: World) -> None:
    assert corridor.extent == pytest.approx((-2.5, -2.0, 29.5, 15.5))
    assert corridor.shape == (350, 640)
    assert not corridor.is_solid(0.0, 0.0)
    assert corridor.is_solid(-1.5, -0.9)  # the cabinet
    assert corridor.is_solid(10.0, 6.0)  # wall north of the corridor
    assert not corridor.is_solid(7.5, 5.1)  # a door recess
    assert corridor.is_solid(40.0, 0.0)  # outside the extent
    assert [g.id for g in corridor.goals] == ["1", "2", "3", "4", "5", "6", "7"]
    assert corridor.goals[5].pose == pytest.approx((23.1, 13.4, -1.57))
    assert "box" in corridor.dynamic and not corridor.dynamic["box"].active


def test_axis_aligned_ranges_are_exact(corridor: World) -> None:
    r = corridor.raycast(3.0, 3.5, np.array([math.pi / 2, -math.pi / 2, math.pi, 0.0]), 20.0)
    assert r[0] == pytest.approx(1.4, abs=1e-5)  # north wall at y = 4.9
    assert r[1] == pytest.approx(4.9, abs=1e-5)  # south: across the lobby to its wall at y = -1.4
    assert r[2] == pytest.approx(5.0, abs=1e-5)  # west wall at x = -2
    assert r[3] == 20.0  # down the corridor: nothing within 20 m
    # from exactly on a cell face, straight down (cos(3 pi/2) is -1.8e-16, not 0): must not stall on the face
    r = corridor.raycast(15.0, 3.0, np.array([1.5 * math.pi, math.pi]), 20.0, max_iterations=200)
    assert r == pytest.approx([1.4, 17.0], abs=1e-5)


def test_raycast_matches_brute_force(corridor: World) -> None:
    rng = np.random.default_rng(7)
    poses = [(0.0, 0.0), (3.0, 3.5), (10.0, 3.2), (24.0, 10.0), (26.0, 6.0), (23.3, 13.9), (-1.0, 0.9)]
    for x, y in poses:
        angles = rng.uniform(-math.pi, math.pi, 40)
        fast = corridor.raycast(x, y, angles, 12.0)
        for a, r in zip(angles, fast):
            assert r == pytest.approx(brute_range(corridor, x, y, a, 12.0), abs=0.0015), (x, y, a)


def test_raycast_from_inside_a_wall_or_outside_is_zero(corridor: World) -> None:
    assert corridor.raycast(10.0, 6.0, np.array([0.0, 1.0]), 20.0).tolist() == [0.0, 0.0]
    assert corridor.raycast(100.0, 0.0, np.array([0.0]), 20.0).tolist() == [0.0]


def test_raycast_refuses_a_non_finite_pose_by_name(corridor: World) -> None:
    with pytest.raises(ValueError, match="non-finite pose or angle: x=nan"):
        corridor.raycast(math.nan, 0.0, np.array([0.0]), 20.0)
    with pytest.raises(ValueError, match="1 non-finite of 2 angles"):
        corridor.raycast(3.0, 3.5, np.array([0.0, math.inf]), 20.0)


def test_a_runaway_step_cannot_throw_a_beam_off_the_grid() -> None:
    """However a step is computed (here the free-run table is poisoned with inf and NaN, the way a beam exactly
    along a grid axis multiplies a run by 1/cos ~ 1e16), a beam ends within the range asked for instead of at a
    float index outside the grid (seen once as ``index -9223372036854775808 is out of bounds``)."""
    w = World.load_builtin("corridor")
    clean = w.raycast(3.0, 3.5, np.linspace(-math.pi, math.pi, 73), 20.0)
    w._runs_flat = w._runs_flat.copy()
    w._runs_flat[::7] = np.inf
    w._runs_flat[3::7] = np.nan
    poisoned = w.raycast(3.0, 3.5, np.linspace(-math.pi, math.pi, 73), 20.0)
    assert np.isfinite(poisoned).all() and (poisoned >= 0.0).all() and (poisoned <= 20.0).all()
    assert np.count_nonzero(np.abs(poisoned - clean) < 1e-6) > 0


def test_dynamic_obstacles_by_request_and_schedule() -> None:
    w = World.load_builtin("corridor")
    beam = np.array([0.0])
    assert w.raycast(5.0, 2.3, beam, 20.0)[0] == 20.0
    assert not w.circle_collides(8.5, 2.8, 0.63)
    w.set_obstacle("box", None)
    assert w.raycast(5.0, 2.3, beam, 20.0)[0] == pytest.approx(4.0)
    assert w.clearance_m(8.5, 2.8) == pytest.approx(0.5)
    assert w.circle_collides(8.5, 2.8, 0.63)
    w.set_obstacle("extra", [6.0, 2.0, 6.5, 2.6])
    assert w.raycast(5.0, 2.3, beam, 20.0)[0] == pytest.approx(1.0)
    assert w.active_obstacle_ids() == ["box", "extra"]
    w.remove_obstacle("extra")
    w.clear_obstacles()
    assert w.raycast(5.0, 2.3, beam, 20.0)[0] == 20.0
    with pytest.raises(WorldError):
        w.remove_obstacle("box")
    with pytest.raises(WorldError, match="min < max"):
        w.set_obstacle("bad", [1.0, 1.0, 0.0, 2.0])
    w.dynamic["box"].appear_at_s = 5.0
    w.dynamic["box"].vanish_at_s = 8.0
    assert not w.apply_schedule(4.9)
    assert w.apply_schedule(5.0) and w.active_obstacle_ids() == ["box"]
    assert w.apply_schedule(8.0) and w.active_obstacle_ids() == []


def test_map_roundtrip_and_unknown_cells_are_solid(tmp_path, corridor: World) -> None:
    yml, pgm = corridor.write_map(tmp_path / "world")
    text = yml.read_text()
    meta = yaml.safe_load(text)
    assert meta["mode"] == "trinary" and meta["origin"] == [-2.5, -2.0, 0.0] and meta["resolution"] == 0.05
    raw = pgm.read_bytes()
    assert raw.startswith(b"P5\n")
    assert set(np.unique(np.frombuffer(raw[-640 * 350:], dtype=np.uint8)).tolist()) == {0, 254}
    again = World.load_map_yaml(yml)
    assert np.array_equal(again.solid, corridor.solid)
    assert again.origin_xy == pytest.approx(corridor.origin_xy)
    # a map with an unknown (205) patch: that patch is solid for the simulator
    from PIL import Image

    img = np.full((40, 60), 254, dtype=np.uint8)
    img[10:20, 30:40] = 205
    img[0, :] = 0
    Image.fromarray(img).save(tmp_path / "m.png")
    (tmp_path / "m.yaml").write_text("image: m.png\nresolution: 0.1\norigin: [1.0, 2.0, 0.0]\nnegate: 0\n"
                                     "occupied_thresh: 0.65\nfree_thresh: 0.196\n")
    m = load_world(map_yaml=str(tmp_path / "m.yaml"))
    assert m.shape == (40, 60)
    assert m.is_solid(1.0 + 3.5, 2.0 + (40 - 15) * 0.1)  # the unknown patch (image rows 10..19 from the top)
    assert not m.is_solid(1.0 + 1.0, 2.0 + 1.0)
    assert m.is_solid(1.0 + 1.0, 2.0 + 3.95)  # image row 0 = top = max y
    # a yawed origin is resampled onto the axis-aligned raster covering the turned map (outside it: solid)
    (tmp_path / "turned.yaml").write_text("image: m.png\nresolution: 0.1\norigin: [0, 0, 0.5]\n")
    turned = World.load_map_yaml(tmp_path / "turned.yaml")
    c, s = math.cos(0.5), math.sin(0.5)
    assert not turned.is_solid(c * 1.0 - s * 1.0, s * 1.0 + c * 1.0)  # map (1, 1) is free, as above
    assert turned.is_solid(c * 3.5 - s * 2.5, s * 3.5 + c * 2.5)  # the unknown patch
    assert turned.is_solid(turned.origin_xy[0] + 0.05, turned.origin_xy[1] + 0.05)  # a corner off the map
    with pytest.raises(WorldError, match="missing.yaml"):
        World.load_map_yaml(tmp_path / "missing.yaml")


def test_render_map_cli(tmp_path) -> None:
    out = tmp_path / "run" / "world"
    subprocess.run([sys.executable, "-m", "services.sim.render_map", "--world", "loop", "--out", str(out)],
                   check=True, capture_output=True)
    w = World.load_map_yaml(out.with_suffix(".yaml"))
    assert np.array_equal(w.solid, World.load_builtin("loop").solid)



def test_render_map_names_a_bad_world(tmp_path, capsys) -> None:
    from services.sim.render_map import main

    assert main(["--world", "nope", "--out", str(tmp_path / "w")]) == 2
    assert "no built-in world 'nope'" in capsys.readouterr().err


def brute_clearance(world: World, x: float, y: float) -> float:
    """Distance from (x, y) to every solid cell square (and the solid outside of the extent), by brute force."""
    res = world.resolution_m
    rows, cols = np.nonzero(np.pad(world.solid, 1, constant_values=True))
    x0 = world.origin_xy[0] + (cols - 1) * res
    y0 = world.origin_xy[1] + (rows - 1) * res
    dx = np.maximum.reduce([x0 - x, np.zeros_like(x0), x - (x0 + res)])
    dy = np.maximum.reduce([y0 - y, np.zeros_like(y0), y - (y0 + res)])
    return float(np.hypot(dx, dy).min())


def block_world() -> World:
    """8 m x 8 m of free 0.25 m cells with one solid cell covering [2.5, 2.75) x [2.5, 2.75)."""
    solid = np.zeros((32, 32), dtype=bool)
    solid[10, 10] = True
    return World(name="block", resolution_m=0.25, origin_xy=(0.0, 0.0), solid=solid)


def test_contact_is_judged_at_the_point_not_at_its_cell_centre() -> None:
    w = block_world()
    # 0.74 m left of the block's face, but in a cell whose centre is 0.615 m from it: no contact for a 0.63 m disc
    assert w.clearance_m(1.76, 2.625) == pytest.approx(0.74)
    assert not w.circle_collides(1.76, 2.625, 0.63)
    # diagonally 0.368 m from the block's corner, in a cell whose centre is farther: a 0.5 m disc touches it
    assert w.clearance_m(2.24, 2.24) == pytest.approx(math.hypot(0.26, 0.26))
    assert w.circle_collides(2.24, 2.24, 0.5)
    assert w.clearance_m(2.6, 2.6) == 0.0


def test_clearance_matches_brute_force_on_a_cluttered_raster() -> None:
    rng = np.random.default_rng(4)
    solid = rng.random((40, 60)) < 0.08
    glass = solid & (rng.random((40, 60)) < 0.5)
    w = World(name="clutter", resolution_m=0.1, origin_xy=(-1.0, 2.0), solid=solid, glass=glass)
    for x, y in zip(rng.uniform(-1.0, 5.0, 300), rng.uniform(2.0, 6.0, 300), strict=True):
        expected = 0.0 if w.is_solid(x, y) else brute_clearance(w, x, y)
        assert w.clearance_m(x, y) == pytest.approx(expected, abs=1e-9), (x, y)
        # a contact test against 0.3 m: exact up to 0.3 m, a lower bound above it
        quick = w.clearance_m(x, y, exact_within_m=0.3)
        assert quick == pytest.approx(expected, abs=1e-9) if expected <= 0.3 else 0.3 < quick <= expected + 1e-9
