"""Wall-clock pacing of the simulation at ``speed_factor`` sim seconds per wall second, as plain code.

Step k is due at ``wall0 + (t_k - sim0) / speed_factor``. Before a step the loop sleeps until it is due (at least
``MIN_SLEEP_WALL_S``: at high factors it wakes every 2 ms and catches up in a burst), yields to the event loop every
4 steps when on time, and re-anchors (``wall0, sim0 = now``) when more than ``MAX_BEHIND_S`` late rather than
bursting. A non-positive or non-finite factor runs free (a yield per step). The achieved factor is measured over
each wall second.
"""

from __future__ import annotations

import math

MIN_SLEEP_WALL_S = 0.002
MAX_BEHIND_S = 0.25
YIELD_EVERY_STEPS = 4


class Pacer:
    """When to sleep before the next step, and the achieved speed factor (module docstring)."""

    def __init__(self, speed_factor: float, now_wall_s: float, sim_now_s: float) -> None:
        self.speed_factor = speed_factor
        self.free_run = not (speed_factor > 0 and math.isfinite(speed_factor))
        self.wall0_s, self.sim0_s = now_wall_s, sim_now_s
        self.meas_wall_s, self.meas_sim_s = now_wall_s, sim_now_s
        #: the measured factor after the first wall second; the requested one (1 when free) until then
        self.achieved = 1.0 if self.free_run else speed_factor
        self.behind = 0

    def wait_s(self, now_wall_s: float, sim_now_s: float, dt_s: float, steps: int) -> float | None:
        """Wall seconds to sleep before the step from ``sim_now_s`` (0: only yield), or None: step at once."""
        if self.free_run:
            return 0.0
        due = self.wall0_s + (sim_now_s + dt_s - self.sim0_s) / self.speed_factor
        delay = due - now_wall_s
        if delay > 0.0:
            return max(delay, MIN_SLEEP_WALL_S)
        if delay < -MAX_BEHIND_S:  # cannot keep up: re-anchor rather than burst
            self.behind += 1
            self.wall0_s, self.sim0_s = now_wall_s, sim_now_s
            return None
        return 0.0 if steps % YIELD_EVERY_STEPS == 0 else None

    def measure(self, now_wall_s: float, sim_now_s: float) -> bool:
        """Update ``achieved`` once per wall second; True when it did."""
        if now_wall_s - self.meas_wall_s < 1.0:
            return False
        self.achieved = (sim_now_s - self.meas_sim_s) / (now_wall_s - self.meas_wall_s)
        self.meas_wall_s, self.meas_sim_s = now_wall_s, sim_now_s
        return True
