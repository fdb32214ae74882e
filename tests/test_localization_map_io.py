"""Map I/O in the ROS map_server format: modes, negate, thresholds, row order, origin, round trips, bad input."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from proto import decode_as, encode
from proto.messages import OccupancyGrid
from services.cli.main import main as zagv_main
from services.common.map_io import MapError, OccupancyMap, load_map, save_map


def write_map(tmp: Path, pixels: np.ndarray, *, name: str = "m", ext: str = "pgm", mode_line: str = "",
              extra: str = "", origin: str = "[1.0, -2.0, 0.5]") -> Path:
    image = tmp / f"{name}.{ext}"
    Image.fromarray(pixels).save(image)
    yaml_path = tmp / f"{name}.yaml"
    yaml_path.write_text(f"image: {image.name}\nresolution: 0.1\norigin: {origin}\n{mode_line}{extra}"
                         "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n")
    return yaml_path


def test_trinary_thresholds_and_row_order(tmp_path):
    # image row 0 is the top of the map: after loading it becomes the last grid row
    pixels = np.array([[0, 254, 205], [255, 90, 200]], dtype=np.uint8)
    grid = load_map(write_map(tmp_path, pixels))
    # p = (255 - g)/255: 0 -> 1.0 occ; 254 -> free; 205 -> 0.196.. unknown; 90 -> 0.647 unknown; 200 -> 0.216 unknown
    assert grid.data.tolist() == [[0, -1, -1], [100, 0, -1]]
    assert grid.resolution == 0.1
    assert grid.origin == (1.0, -2.0, 0.5)
    assert grid.counts() == {"free": 2, "occupied": 1, "unknown": 3, "other": 0}


def test_negate_scale_and_raw_modes(tmp_path):
    pixels = np.array([[0, 255, 128, 40]], dtype=np.uint8)
    plain = load_map(write_map(tmp_path, pixels, name="n", mode_line="mode: trinary\n"))
    assert plain.data.tolist() == [[100, 0, -1, 100]]
    (tmp_path / "n.yaml").write_text((tmp_path / "n.yaml").read_text().replace("negate: 0", "negate: 1"))
    assert load_map(tmp_path / "n.yaml").data.tolist() == [[0, 100, -1, 0]]
    # scale: in-between p becomes round(100 (p - free) / (occ - free)); 128 -> p = 0.498 -> 66
    scaled = load_map(write_map(tmp_path, pixels, name="s", mode_line="mode: scale\n"))
    p = (255 - 128) / 255
    assert scaled.data.tolist() == [[100, 0, round(100 * (p - 0.196) / (0.65 - 0.196)), 100]]
    raw = load_map(write_map(tmp_path, np.array([[0, 100, 101, 37]], dtype=np.uint8), name="r",
                             mode_line="mode: raw\n"))
    assert raw.data.tolist() == [[0, 100, -1, 37]]


def test_png_rgb_and_alpha(tmp_path):
    rgb = np.zeros((1, 3, 3), dtype=np.uint8)
    rgb[0, 0] = (255, 255, 252)  # mean 254 -> free
    rgb[0, 1] = (0, 0, 30)       # mean 10 -> occupied
    rgb[0, 2] = (205, 205, 205)
    assert load_map(write_map(tmp_path, rgb, name="c", ext="png")).data.tolist() == [[0, 100, -1]]
    rgba = np.zeros((1, 2, 4), dtype=np.uint8)
    rgba[0, 0] = (128, 128, 128, 255)
    rgba[0, 1] = (128, 128, 128, 100)  # not opaque: unknown in scale mode
    scaled = load_map(write_map(tmp_path, rgba, name="a", ext="png", mode_line="mode: scale\n"))
    assert scaled.data[0, 0] > 0 and scaled.data[0, 1] == -1


def test_save_load_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    data = rng.choice(np.array([-1, 0, 100], dtype=np.int8), size=(37, 53))
    grid = OccupancyMap(data, 0.05, (-3.25, 7.5, 0.3))
    yaml_path, image_path = save_map(grid, tmp_path / "sub" / "saved")
    assert image_path.read_bytes().startswith(b"P5")
    assert set(np.unique(np.asarray(Image.open(image_path)))) <= {0, 205, 254}
    text = yaml_path.read_text()
    assert "occupied_thresh: 0.65" in text and "free_thresh: 0.196" in text and "negate: 0" in text
    back = load_map(yaml_path)
    assert np.array_equal(back.data, data)
    assert back.resolution == 0.05 and back.origin == (-3.25, 7.5, 0.3)
    # the saved image's first row is the map's top
    assert np.array_equal(np.asarray(Image.open(image_path))[0] == 0, data[-1] == 100)


def test_message_round_trip_and_cell_geometry():
    data = np.zeros((4, 6), dtype=np.int8)
    data[1, 2] = 100
    grid = OccupancyMap(data, 0.5, (10.0, 20.0, math.pi / 2))
    msg = decode_as(OccupancyGrid, encode(grid.to_msg(stamp=3.0)))
    back = OccupancyMap.from_msg(msg)
    assert np.array_equal(back.data, data) and back.origin == grid.origin and msg.width == 6
    x, y = grid.cell_to_world(np.array([2]), np.array([1]))
    # yaw 90 deg: grid +x points along map +y
    assert (float(x[0]), float(y[0])) == pytest.approx((10.0 - 0.75, 20.0 + 1.25))
    col, row = grid.world_to_cell(x, y)
    assert (int(col[0]), int(row[0])) == (2, 1)


@pytest.mark.parametrize(("yaml_text", "needle"), [
    ("resolution: 0.05\norigin: [0, 0, 0]\n", "missing key(s) image"),
    ("image: nowhere.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n", "does not exist"),
    ("image: m.pgm\nresolution: 0.05\norigin: [0, 0]\n", "`origin` must be [x, y, yaw]"),
    ("image: m.pgm\nresolution: -1\norigin: [0, 0, 0]\n", "`resolution` must be > 0"),
    ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nmode: fancy\n", "`mode` must be one of"),
    ("image: bad.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n", "cannot read image"),
    ("image: [unclosed\n", "syntax error at line"),
])
def test_bad_yaml_names_the_problem(tmp_path, yaml_text, needle):
    Image.fromarray(np.zeros((2, 2), dtype=np.uint8)).save(tmp_path / "m.pgm")
    (tmp_path / "bad.pgm").write_bytes(b"P5 not really an image")
    path = tmp_path / "x.yaml"
    path.write_text(yaml_text)
    with pytest.raises(MapError) as err:
        load_map(path)
    assert needle in str(err.value) and str(path) in str(err.value)


def test_every_shared_map_loads_and_round_trips(shared_dir, tmp_path):
    yamls = sorted((shared_dir / "data" / "maps").glob("*/*.yaml"))
    assert len(yamls) >= 3
    for path in yamls:
        grid = load_map(path)
        counts = grid.counts()
        assert counts["free"] > 0 and counts["occupied"] > 0, path
        assert counts["free"] + counts["occupied"] + counts["unknown"] + counts["other"] == grid.data.size
        back = load_map(save_map(grid, tmp_path / path.stem)[0])
        assert np.array_equal(back.data, grid.data), path
    depot = load_map(shared_dir / "data" / "maps" / "nav2_depot" / "depot.yaml")
    assert (depot.width, depot.height, depot.resolution) == (604, 307, 0.05)


def test_cli_map_info(shared_dir, capsys):
    path = str(shared_dir / "data" / "maps" / "turtlebot3_house" / "turtlebot3_house.yaml")
    assert zagv_main(["map", "info", path, "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["width"], info["height"]) == (384, 384)
    assert info["origin"] == [-10.0, -10.0, 0.0]
    assert sum(info["cells"].values()) == 384 * 384
    assert zagv_main(["map", "info", path]) == 0
    out = capsys.readouterr().out
    assert "384 x 384 cells" in out and f"free {info['cells']['free']}" in out


def test_cli_map_info_bad_file(tmp_path, capsys):
    assert zagv_main(["map", "info", str(tmp_path / "none.yaml")]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_coarsen_keeps_thin_walls_and_needs_most_of_a_block_free() -> None:
    from services.common.map_io import coarsen

    data = np.zeros((4, 6), dtype=np.int8)
    data[:, 1] = 100          # a wall one fine cell thick
    data[0:2, 4:6] = -1       # a block with nothing known
    data[2, 4] = -1           # 3 of 4 known, all free
    data[2:4, 2] = -1         # half known: 2 free of 2 known
    grid = OccupancyMap(data, 0.05, (1.0, 2.0, 0.5))
    coarse = coarsen(grid, 2)
    assert coarse.resolution == pytest.approx(0.10) and coarse.origin == (1.0, 2.0, 0.5)
    assert coarse.data.tolist() == [[100, 0, -1], [100, 0, 0]]
    with pytest.raises(MapError, match="whole number"):
        coarsen(grid, 0)
    assert np.array_equal(coarsen(grid, 1).data, data)


def test_coarsen_pads_a_partial_block_with_unknown_and_round_trips(tmp_path) -> None:
    from services.common.map_io import coarsen

    grid = OccupancyMap(np.zeros((5, 5), dtype=np.int8), 0.05)
    coarse = coarsen(grid, 2)
    assert coarse.data.shape == (3, 3)
    assert coarse.data[2, 2] == -1 and coarse.data[0, 2] == 0  # a quarter known / half known
    yaml_path, _ = save_map(coarse, tmp_path / "coarse")
    back = load_map(yaml_path)
    assert np.array_equal(back.data, coarse.data) and back.resolution == pytest.approx(0.10)


def test_every_shared_map_coarsens_to_a_tenth_of_a_metre(shared_dir) -> None:
    """A real map re-rastered onto about 0.10 m keeps every occupied cell's place covered and most free space."""
    from services.common.map_io import coarsen

    for yaml_path in sorted((shared_dir / "data" / "maps").glob("*/*.yaml")):
        grid = load_map(yaml_path)
        k = round(0.10 / grid.resolution)
        if k < 2:
            continue
        coarse = coarsen(grid, k)
        rows, cols = np.nonzero(grid.data == 100)
        assert (coarse.data[rows // k, cols // k] == 100).all(), yaml_path.name
        free_fine = (grid.data == 0).sum() * grid.resolution ** 2
        free_coarse = (coarse.data == 0).sum() * coarse.resolution ** 2
        assert 0.5 * free_fine < free_coarse <= free_fine * 1.5, (yaml_path.name, free_fine, free_coarse)
