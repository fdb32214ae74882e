"""Write a simulator world's map in the ROS map_server format: ``PREFIX.yaml`` + ``PREFIX.pgm``.

``python -m services.sim.render_map --world corridor --out run/world`` (or ``--map some.yaml`` to re-render a map
as the simulator sees it). Trinary PGM: 254 free, 0 occupied; origin = the world's min corner, yaw 0.
"""

from __future__ import annotations

import argparse
import sys

from services.common.world import WorldError, builtin_worlds, load_world


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m services.sim.render_map", description=__doc__.splitlines()[0])
    g = p.add_mutually_exclusive_group()
    g.add_argument("--world", default="corridor", help=f"built-in world ({', '.join(builtin_worlds())})")
    g.add_argument("--map", dest="map_yaml", default="", help="a ROS map YAML to re-render")
    p.add_argument("--out", required=True, help="output prefix: writes PREFIX.yaml and PREFIX.pgm")
    args = p.parse_args(argv)
    try:
        world = load_world(args.world, args.map_yaml)
    except WorldError as exc:
        print(f"render_map: {exc}", file=sys.stderr)
        return 2
    yml, pgm = world.write_map(args.out)
    rows, cols = world.shape
    print(f"render_map: {world.name}: {cols}x{rows} cells at {world.resolution_m} m -> {yml}, {pgm}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
