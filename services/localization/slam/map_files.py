"""Writing an ``OccupancyGrid`` in the ROS map_server format: a YAML description plus a binary PGM (P5) image."""

from __future__ import annotations

from pathlib import Path

from .occupancy import OccupancyGrid

OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196


def write_ros_map(grid: OccupancyGrid, directory: str | Path, name: str = "map") -> Path:
    """Write ``name.pgm`` (trinary: 0 occupied, 254 free, 205 unknown) and ``name.yaml``; returns the YAML path."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    image = grid.trinary_image(OCCUPIED_THRESH, FREE_THRESH)
    height, width = image.shape
    pgm = directory / f"{name}.pgm"
    with pgm.open("wb") as f:
        f.write(f"P5\n# zagv map build\n{width} {height}\n255\n".encode())
        f.write(image.tobytes())
    yaml_path = directory / f"{name}.yaml"
    ox, oy = (float(v) for v in grid.origin_xy_m)
    yaml_path.write_text(
        f"image: {pgm.name}\n"
        f"mode: trinary\n"
        f"resolution: {grid.resolution_m:.6g}\n"
        f"origin: [{ox:.6f}, {oy:.6f}, 0.0]\n"
        f"negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\n"
        f"free_thresh: {FREE_THRESH}\n")
    return yaml_path


def write_trajectory(path: str | Path, stamps_s, poses) -> None:
    """Text file, one line per scan: ``stamp_s x_m y_m theta_rad``."""
    lines = ["# stamp_s x_m y_m theta_rad"]
    lines += [f"{t:.6f} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f}" for t, p in zip(stamps_s, poses)]
    Path(path).write_text("\n".join(lines) + "\n")


def read_trajectory(path: str | Path):
    """(stamps_s (N,), poses (N, 3)) from a file written by ``write_trajectory``."""
    import numpy as np

    table = np.loadtxt(path, comments="#", ndmin=2)
    if table.shape[1] < 4:
        raise ValueError(f"{path}: expected lines 'stamp x y theta'")
    return table[:, 0], table[:, 1:4]
