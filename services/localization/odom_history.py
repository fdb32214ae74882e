"""Recent odometry poses by stamp, for placing a scan with the odometry at its stamp (localization's sync)."""

from __future__ import annotations

import bisect
import collections

from services.common.se2 import wrap_angle

Pose = tuple[float, float, float]


class OdomHistory:
    """Recent odometry poses by stamp; ``at(t)`` interpolates (x, y linearly, theta along the shorter arc)."""

    def __init__(self, keep_s: float) -> None:
        self.keep_s = keep_s
        self.stamps: collections.deque[float] = collections.deque()
        self.poses: collections.deque[Pose] = collections.deque()

    def add(self, stamp: float, pose: Pose) -> None:
        if self.stamps and stamp <= self.stamps[-1]:
            if stamp < self.stamps[-1] - self.keep_s:  # the clock went back (sim restart): start over
                self.stamps.clear()
                self.poses.clear()
            else:
                return
        self.stamps.append(stamp)
        self.poses.append(pose)
        while self.stamps and self.stamps[0] < stamp - self.keep_s:
            self.stamps.popleft()
            self.poses.popleft()

    @property
    def latest_stamp(self) -> float | None:
        return self.stamps[-1] if self.stamps else None

    def at(self, t: float, tolerance_s: float) -> Pose | None:
        """Odom pose at ``t``; None when ``t`` is outside the history by more than ``tolerance_s``."""
        if not self.stamps:
            return None
        if t >= self.stamps[-1]:
            return self.poses[-1] if t - self.stamps[-1] <= tolerance_s else None
        if t <= self.stamps[0]:
            return self.poses[0] if self.stamps[0] - t <= tolerance_s else None
        i = bisect.bisect_right(self.stamps, t)
        t0, t1 = self.stamps[i - 1], self.stamps[i]
        p0, p1 = self.poses[i - 1], self.poses[i]
        f = (t - t0) / (t1 - t0) if t1 > t0 else 1.0
        return (p0[0] + f * (p1[0] - p0[0]), p0[1] + f * (p1[1] - p0[1]),
                float(wrap_angle(p0[2] + f * float(wrap_angle(p1[2] - p0[2])))))
