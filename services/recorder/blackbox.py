"""The black box: a rolling window of raw payloads, saved as a bag on demand (an I/O-free core plus ``save``).

``add(name, payload, t_ns)`` keeps every payload newer than ``window_s`` before the newest; the newest payload of
each topic that fell out of the window is kept too (a latched ``map`` published once at start is in every saved
bag). Triggers (``Triggers``) turn drive, nav and health changes into save reasons; repeated triggers within
``cooldown_s`` of clock time are merged into one save.
"""

from __future__ import annotations

import collections
import re
import threading
from dataclasses import dataclass
from pathlib import Path

from proto import codec
from proto.messages import NavStatus, WheelStates
from services.recorder.bag import BagRecorder

Item = tuple[int, str, bytes]


class RingBuffer:
    """Payloads of the last ``window_s`` (thread-safe: Zenoh threads add, the loop snapshots)."""

    def __init__(self, window_s: float) -> None:
        if not window_s > 0:
            raise ValueError(f"window_s must be > 0, got {window_s}")
        self.window_ns = int(window_s * 1e9)
        self._items: collections.deque[Item] = collections.deque()
        self._evicted: dict[str, Item] = {}
        self._lock = threading.Lock()
        self.bytes = 0

    def add(self, name: str, payload: bytes, t_ns: int) -> None:
        with self._lock:
            if self._items and t_ns < self._items[-1][0] - self.window_ns:  # the clock went back: start over
                self._items.clear()
                self._evicted.clear()
                self.bytes = 0
            self._items.append((t_ns, name, payload))
            self.bytes += len(payload)
            horizon = t_ns - self.window_ns
            while self._items and self._items[0][0] < horizon:
                old = self._items.popleft()
                self.bytes -= len(old[2])
                self._evicted[old[1]] = old

    def snapshot(self) -> list[Item]:
        """The window, preceded by the newest evicted payload of each topic no longer in it."""
        with self._lock:
            items = list(self._items)
            present = {name for _, name, _ in items}
            start = items[0][0] if items else 0
            older = sorted((start, n, p) for n, (_, _, p) in self._evicted.items() if n not in present)
        return older + items

    def __len__(self) -> int:
        return len(self._items)


def save(items: list[Item], out: Path, robot_id: str) -> tuple[Path, int]:
    """Write ``items`` as one rosbag2/MCAP bag at ``out``; returns (path, messages). Bad payloads are skipped."""
    written = 0
    with BagRecorder(out, robot_id=robot_id) as bag:
        for t_ns, name, payload in items:
            try:
                msg = codec.decode(name, payload)
            except (codec.ProtoDecodeError, KeyError):
                continue
            bag.write(name, msg, t_ns)
            written += 1
    return out, written


_SAFE = re.compile(r"[^A-Za-z0-9_.-]+")


def bag_name(stamp: str, reason: str) -> str:
    """``blackbox_<stamp>_<reason>`` with the reason reduced to file-name characters."""
    return f"blackbox_{stamp}_{_SAFE.sub('-', reason).strip('-')[:40] or 'save'}"


@dataclass
class Triggers:
    """Edge detection of save reasons: e-stop, drive fault, failed goal."""

    estopped: bool = False
    fault: str = ""
    nav_failed_goal: str | None = None

    def on_wheels(self, w: WheelStates) -> str | None:
        reason = None
        if w.estopped and not self.estopped:
            reason = "estop"
        elif w.fault and w.fault != self.fault:
            reason = "drive-fault"
        self.estopped, self.fault = w.estopped, w.fault
        return reason

    def on_nav_status(self, s: NavStatus) -> str | None:
        if s.state != "failed":
            self.nav_failed_goal = None
            return None
        if self.nav_failed_goal == s.goal_id:
            return None
        self.nav_failed_goal = s.goal_id
        return "goal-failed"
