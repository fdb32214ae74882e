"""Settings every service shares: the Zenoh connection, the clock source and the liveness watchdog."""

from __future__ import annotations

from typing import Any, Literal

import msgspec


class ZenohSettings(msgspec.Struct, forbid_unknown_fields=True):
    """How a process joins the robot's Zenoh network ([zenoh] table).

    Multicast scouting is always off: sessions connect to the explicit ``connect`` endpoints only.
    ``config_file`` (json5) is applied first, then these keys. ``peer`` (the default, rmw_zenoh's data path): the
    router serves discovery and remote clients, data goes directly between the processes of one host; ``client``
    (the way back, ``mode = "client"`` or ``--set zenoh.mode="client"``): everything through the router.
    Command-line tools are clients whatever this says (``services.client.connect``).
    """

    mode: Literal["client", "peer", "router"] = "peer"
    connect: list[str] = msgspec.field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    listen: list[str] = msgspec.field(default_factory=list)
    config_file: str = ""
    #: opt-in: a peer with no ``listen`` endpoint listens on a unix socket of its own in this folder instead of an
    #: ephemeral loopback TCP port (the data path then takes no TCP port; a unix socket buffers less, so a slow
    #: subscriber of a DROP topic loses samples sooner: services/common/session.py)
    peer_socket_dir: str = ""
    #: extra zenoh config keys, e.g. {"transport/unicast/lowlatency": true}
    options: dict[str, Any] = msgspec.field(default_factory=dict)


class ClockSettings(msgspec.Struct, forbid_unknown_fields=True):
    """Clock source ([clock] table): wall time, or the simulator's ``clock`` topic when ``use_sim_time``."""

    use_sim_time: bool = False


class LivenessSettings(msgspec.Struct, forbid_unknown_fields=True):
    """The event-loop watchdog ([liveness] table, ``services.common.liveness``): after ``stall_s`` without a turn
    of the loop the health token is withdrawn, after ``kill_s`` the process kills itself to be restarted.
    0 takes the service's default."""

    stall_s: float = 0.0
    kill_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("stall_s", "kill_s"):
            value = getattr(self, name)
            if not (value >= 0 and value < float("inf")):
                raise ValueError(f"liveness.{name} must be a finite number >= 0, got {value}")
