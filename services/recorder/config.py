"""The ``[recorder]`` table: the black box (a rolling recording saved on faults and on demand)."""

from __future__ import annotations

import msgspec


class RecorderConfig(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Black box settings.

    - ``blackbox``: keep the rolling recording (on by default).
    - ``window_s``: how much of the past (s of clock time) a saved bag covers.
    - ``post_trigger_s``: clock time recorded after a trigger before the bag is written.
    - ``cooldown_s``: triggers within this long after a save are merged into it (on-demand saves always run).
    - ``blackbox_dir``: where bags go (empty: ``<state_dir>/blackbox``, or ``./blackbox`` without a state dir).
    - ``max_saved``: oldest saved bags beyond this many are deleted.
    - ``exclude``: topic names not kept (e.g. ``["nav/costmap"]`` to save memory).
    - ``save_on_crash``: save when a service's health token disappears.
    """

    blackbox: bool = True
    window_s: float = 120.0
    post_trigger_s: float = 2.0
    cooldown_s: float = 10.0
    state_dir: str = ""
    blackbox_dir: str = ""
    max_saved: int = 20
    exclude: list[str] = msgspec.field(default_factory=list)
    save_on_crash: bool = True

    def __post_init__(self) -> None:
        if not self.window_s > 0:
            raise ValueError("window_s must be > 0")
        for name in ("post_trigger_s", "cooldown_s"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0")
        if self.max_saved < 1:
            raise ValueError("max_saved must be >= 1")

    def directory(self) -> str:
        if self.blackbox_dir:
            return self.blackbox_dir
        return f"{self.state_dir}/blackbox" if self.state_dir else "blackbox"
