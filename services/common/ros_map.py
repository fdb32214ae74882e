"""Writing a map in the ROS map_server format: ``<base>.yaml`` plus a binary PGM (P5) image, trinary mode.

Pixels are map_server's trinary values: 0 occupied, 254 free, 205 unknown. The YAML carries ``occupied_thresh``
0.65 and ``free_thresh`` 0.196 (map_saver's), so map_server and every reader of the format load the image back to
the same three classes. The image is given with its rows in file order (top row = largest y), as a PGM stores it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

PGM_OCCUPIED, PGM_FREE, PGM_UNKNOWN = 0, 254, 205
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196


def trinary_pixels(occupancy: np.ndarray, *, free_thresh: float = FREE_THRESH,
                   occupied_thresh: float = OCCUPIED_THRESH) -> np.ndarray:
    """map_saver's rule on an OccupancyGrid-style array (-1 unknown, 0..100 %): free (254) when 0 <= value <= 100 *
    free_thresh, occupied (0) when value >= 100 * occupied_thresh, unknown (205) otherwise. Rows stay in order."""
    pixels = np.full(occupancy.shape, PGM_UNKNOWN, dtype=np.uint8)
    pixels[(occupancy >= 0) & (occupancy <= free_thresh * 100.0)] = PGM_FREE
    pixels[occupancy >= occupied_thresh * 100.0] = PGM_OCCUPIED
    return pixels


def write_ros_map(base: str | Path, image_top_row_first: np.ndarray, resolution_m: float,
                  origin: tuple[float, float, float], *, comment: str = "zagv") -> tuple[Path, Path]:
    """Write ``<base>.yaml`` and ``<base>.pgm`` (a ``.yaml``/``.yml``/``.pgm`` suffix on ``base`` is dropped);
    returns (yaml path, image path). Raises OSError when the folder cannot be written."""
    base = Path(base)
    if base.suffix in (".yaml", ".yml", ".pgm"):
        base = base.with_suffix("")
    yaml_path, image_path = base.with_name(base.name + ".yaml"), base.with_name(base.name + ".pgm")
    image = np.ascontiguousarray(image_top_row_first, dtype=np.uint8)
    if image.ndim != 2:
        raise ValueError(f"a map image is 2-D, got shape {image.shape}")
    rows, cols = image.shape
    base.parent.mkdir(parents=True, exist_ok=True)
    with image_path.open("wb") as f:
        f.write(f"P5\n# {comment}\n{cols} {rows}\n255\n".encode())
        f.write(image.tobytes())
    ox, oy, oyaw = (float(v) for v in origin)
    yaml_path.write_text(f"image: {image_path.name}\nmode: trinary\nresolution: {float(resolution_m)!r}\n"
                         f"origin: [{ox!r}, {oy!r}, {oyaw!r}]\nnegate: 0\n"
                         f"occupied_thresh: {OCCUPIED_THRESH}\nfree_thresh: {FREE_THRESH}\n")
    return yaml_path, image_path
