"""The ``[safety]`` table: the collision monitor's zones and limits (``SafetyParams``) and the watch period."""

from __future__ import annotations

import math

from services.safety.monitor import SafetyParams


class SafetyConfig(SafetyParams, kw_only=True, forbid_unknown_fields=True):
    """Collision monitor settings (``SafetyParams``) plus the node's timing.

    - ``robot_radius_m`` < 0 takes ``[robot] chassis_radius_m``.
    - ``watch_period_s``: how often (clock s) the node re-checks the last command against the newest scan and the
      scan's age, so that an obstacle or a lost scan stops the robot between two commands.
    - ``cmd_timeout_s``: a command older than this is no longer re-issued by the watch (the drive stops on a silent
      command stream by itself).
    - ``state_publish_hz``: ``safety/state`` rate while nothing changes (a change is published at once).
    """

    robot_radius_m: float = -1.0
    watch_period_s: float = 0.05
    cmd_timeout_s: float = 0.2
    state_publish_hz: float = 2.0

    def __post_init__(self) -> None:
        for name in ("watch_period_s", "cmd_timeout_s", "state_publish_hz"):
            value = getattr(self, name)
            if not (value > 0 and math.isfinite(value)):
                raise ValueError(f"safety.{name} must be > 0, got {value!r}")

    def params(self, chassis_radius_m: float) -> SafetyParams:
        fields = {f: getattr(self, f) for f in SafetyParams.__struct_fields__}
        if fields["robot_radius_m"] < 0:
            fields["robot_radius_m"] = chassis_radius_m
        out = SafetyParams(**fields)
        out.validate()
        return out
