"""Scans waiting for the odometry of their stamp (core, no I/O): tf2_ros::MessageFilter for localization.

A scan is placed with the odometry pose at its stamp, interpolated between the odom messages around it
(``OdomHistory``). When the scan arrives before the odom that passes its stamp (odom a little late, a loaded
machine), it waits here, in arrival order, instead of being placed with the last odom pose held: a pose held 0.1 s at
0.2 m/s is 2 cm off, and which scans were placed that way would depend on how the two streams happened to interleave,
so a replay of the same messages would place them differently. As in tf2's MessageFilter, a scan leaves the queue
when the odom covers its stamp (``ready``), or, when more than ``max_waiting`` scans wait (the odom stalled), the
oldest leaves to be placed by the history's tolerance or dropped (``push``).
"""

from __future__ import annotations

import collections
from typing import Generic, Protocol, TypeVar


class Stamped(Protocol):
    stamp: float


S = TypeVar("S", bound=Stamped)


class ScanQueue(Generic[S]):
    """Scans waiting for odometry, oldest first."""

    def __init__(self, max_waiting: int) -> None:
        if max_waiting < 0:
            raise ValueError(f"max_waiting must be >= 0, got {max_waiting}")
        self.max_waiting = max_waiting
        self.waiting: collections.deque[S] = collections.deque()

    def __len__(self) -> int:
        return len(self.waiting)

    def push(self, scan: S) -> list[S]:
        """Queue ``scan``; returns the oldest scans that no longer fit (to place now with the tolerance)."""
        self.waiting.append(scan)
        out = []
        while len(self.waiting) > self.max_waiting:
            out.append(self.waiting.popleft())
        return out

    def ready(self, latest_odom_stamp: float | None) -> list[S]:
        """The waiting scans, oldest first, up to the first one stamped after ``latest_odom_stamp``."""
        out = []
        while self.waiting and latest_odom_stamp is not None and self.waiting[0].stamp <= latest_odom_stamp:
            out.append(self.waiting.popleft())
        return out

    def has_ready(self, latest_odom_stamp: float | None) -> bool:
        """Whether the oldest waiting scan is stamped at or before ``latest_odom_stamp``."""
        return bool(self.waiting) and latest_odom_stamp is not None and self.waiting[0].stamp <= latest_odom_stamp

    def pop_ready(self, latest_odom_stamp: float | None) -> S | None:
        """The oldest waiting scan when the odom covers its stamp (``has_ready``), else None."""
        return self.waiting.popleft() if self.has_ready(latest_odom_stamp) else None

    def clear(self) -> None:
        self.waiting.clear()
