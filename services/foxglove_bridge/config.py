"""The ``[foxglove]`` table: where the Foxglove WebSocket server listens and whether clients may send goals."""

from __future__ import annotations

import msgspec


class FoxgloveConfig(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Foxglove bridge settings.

    - ``host``/``port``: the WebSocket server (loopback by default; 0 picks a free port).
    - ``allow_goals``: accept poses published by a Foxglove client on ``goal_topic`` as navigation goals.
    - ``robot_hz``: rate of the footprint/modules scene (Hz of clock time).
    """

    host: str = "127.0.0.1"
    port: int = 8765
    allow_goals: bool = False
    goal_topic: str = "/goal_pose"
    robot_hz: float = 5.0

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port {self.port} is not a TCP port")
        if not self.robot_hz >= 0:
            raise ValueError("robot_hz must be >= 0")
