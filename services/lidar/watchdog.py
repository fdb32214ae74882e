"""Scan-arrival watchdog (pure): expired when no scan came for ``timeout_s`` on both the service and the wall clock.

Requiring both keeps a simulator that runs slower than real time (service clock barely moving) from looking like a
dead link, while a real scanner (service clock = wall clock) is judged on wall time as usual.
"""

from __future__ import annotations


class ScanWatchdog:
    def __init__(self, timeout_s: float) -> None:
        if not timeout_s > 0:
            raise ValueError(f"watchdog timeout must be > 0 s, got {timeout_s}")
        self.timeout_s = timeout_s
        self._clock_s: float | None = None
        self._wall_s: float | None = None

    def feed(self, clock_s: float, wall_s: float) -> None:
        """A scan arrived (or the link was just set up) at these times."""
        self._clock_s = clock_s
        self._wall_s = wall_s

    def expired(self, clock_s: float, wall_s: float) -> bool:
        if self._clock_s is None or self._wall_s is None:
            return False
        return clock_s - self._clock_s > self.timeout_s and wall_s - self._wall_s > self.timeout_s

    def silence_s(self, wall_s: float) -> float:
        """Wall seconds since the last feed (0 before the first)."""
        return 0.0 if self._wall_s is None else wall_s - self._wall_s
