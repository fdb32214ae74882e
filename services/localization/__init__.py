"""Localization service: the map server (ROS map_server YAML + PGM/PNG) and AMCL.

- ``map_io``: load/save maps in the map_server format (``OccupancyMap``), used by ``zagv map``.
- ``amcl``: the particle filter core (numpy, no I/O) and ``AmclParams`` (Nav2 parameter names).
- ``config``: the ``[localization]`` table (``LocalizationConfig``).
- ``node``: the service shell on Zenoh; ``python -m services.localization`` runs it.
- ``synthetic``: rectangle worlds, an exact laser and noisy odometry for tests and benchmarks.
- ``bench``: ``zagv bench --only amcl``.
"""
