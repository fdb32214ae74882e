"""Writing an ``OccupancyGrid`` in the ROS map_server format: a YAML description plus a binary PGM (P5) image."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from services.common.ros_map import FREE_THRESH as FREE_THRESH
from services.common.ros_map import OCCUPIED_THRESH as OCCUPIED_THRESH
from services.common.ros_map import write_ros_map as write_map_files

from .occupancy import OccupancyGrid


def write_ros_map(grid: OccupancyGrid, directory: str | Path, name: str = "map") -> Path:
    """Write ``name.pgm`` (trinary: 0 occupied, 254 free, 205 unknown) and ``name.yaml``; returns the YAML path."""
    image = grid.trinary_image(OCCUPIED_THRESH, FREE_THRESH)
    ox, oy = (float(v) for v in grid.origin_xy_m)
    yaml_path, _ = write_map_files(Path(directory) / name, image, grid.resolution_m, (ox, oy, 0.0),
                                   comment="zagv map build")
    return yaml_path


def write_trajectory(path: str | Path, stamps_s: Iterable[float], poses: Iterable[Sequence[float]]) -> None:
    """Text file, one line per scan: ``stamp_s x_m y_m theta_rad``."""
    lines = ["# stamp_s x_m y_m theta_rad"]
    lines += [f"{t:.6f} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f}" for t, p in zip(stamps_s, poses)]
    Path(path).write_text("\n".join(lines) + "\n")


def read_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_s (N,), poses (N, 3)) from a file written by ``write_trajectory``."""
    table = np.loadtxt(path, comments="#", ndmin=2)
    if table.shape[1] < 4:
        raise ValueError(f"{path}: expected lines 'stamp x y theta'")
    return table[:, 0], table[:, 1:4]
