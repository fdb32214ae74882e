"""The one ROS map writer (services/common/ros_map.py): what it writes loads back through localization's reader
with the same classes, size and origin, and no other module writes map_server files by hand."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import yaml

from services.common.map_io import FREE, OCCUPIED, UNKNOWN, load_map
from services.common.ros_map import trinary_pixels, write_ros_map

REPO_ROOT = Path(__file__).resolve().parents[1]


def test_written_map_loads_back_with_its_classes_and_origin(tmp_path: Path) -> None:
    occupancy = np.array([[0, 19, 20, 64, 65, 100], [-1, -1, 0, 0, 100, 100]], dtype=np.int8)  # row 0 at origin y
    pixels = trinary_pixels(occupancy)
    assert pixels.tolist() == [[254, 254, 205, 205, 0, 0], [205, 205, 254, 254, 0, 0]]
    yaml_path, image_path = write_ros_map(tmp_path / "sub" / "room.yaml", pixels[::-1], 0.05, (-1.5, 2.0, 0.0))
    assert (yaml_path.name, image_path.name) == ("room.yaml", "room.pgm")
    meta = yaml.safe_load(yaml_path.read_text())
    assert meta == {"image": "room.pgm", "mode": "trinary", "resolution": 0.05, "origin": [-1.5, 2.0, 0.0],
                    "negate": 0, "occupied_thresh": 0.65, "free_thresh": 0.196}
    back = load_map(yaml_path)
    expected = np.where(pixels == 254, FREE, np.where(pixels == 0, OCCUPIED, UNKNOWN))
    assert np.array_equal(back.data, expected)
    assert back.resolution == 0.05 and tuple(back.origin) == (-1.5, 2.0, 0.0)


def test_no_other_module_writes_pgm_headers() -> None:
    header = re.compile(r"""["']P5\\n""")
    writers = [str(p.relative_to(REPO_ROOT)) for p in (REPO_ROOT / "services").rglob("*.py")
               if header.search(p.read_text()) and p.name != "ros_map.py"]
    assert writers == [], f"map_server files are written by services/common/ros_map.py only: {writers}"
