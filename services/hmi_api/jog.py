"""The jog dead-man (paper §4.1 "action commands", made safe for a browser link).

While jog requests keep arriving, the latest (clamped) twist is published at a fixed rate. When none has arrived
for ``timeout_s``, the gate publishes a zero twist for ``zero_repeats`` cycles (so that one lost sample cannot
leave the last command standing) and then goes silent, leaving ``cmd_vel`` to nav.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class JogGate:
    """Decides, each publish cycle, what jog publishes: a twist, a zero twist, or nothing (None).

    Times are seconds on one monotonic clock supplied by the caller.
    """

    timeout_s: float = 0.3
    zero_repeats: int = 3
    _twist: tuple[float, float, float] | None = None
    _last_request_s: float = float("-inf")
    _zeros_left: int = 0

    def command(self, twist: tuple[float, float, float], now_s: float) -> bool:
        """Take a jog request; returns True when it starts a new jog (no jog was active)."""
        started = not self.active(now_s)
        self._twist = twist
        self._last_request_s = now_s
        self._zeros_left = self.zero_repeats
        return started

    def stop(self) -> None:
        """End the jog now (e-stop, disable): the next cycles publish zeros, then nothing."""
        if self._twist is not None:
            self._twist = None
            self._last_request_s = float("-inf")

    def active(self, now_s: float) -> bool:
        return self._twist is not None and now_s - self._last_request_s <= self.timeout_s

    def current(self) -> tuple[float, float, float]:
        return self._twist if self._twist is not None else (0.0, 0.0, 0.0)

    def next_output(self, now_s: float) -> tuple[float, float, float] | None:
        """What to publish this cycle: the jog twist, zeros after the timeout, then None (silence)."""
        if self.active(now_s):
            return self._twist
        self._twist = None
        if self._zeros_left > 0:
            self._zeros_left -= 1
            return (0.0, 0.0, 0.0)
        return None
