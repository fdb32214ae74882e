"""Liveness watchdog: a thread that notices when a service's event loop stops turning.

A task on the loop stamps a heartbeat every ``period_s`` (wall time). The watchdog thread reads that stamp: when
the loop has not beaten for ``stall_s`` the service withdraws its health token (``zagv status``, the HMI and
``zagv up`` see it unhealthy); when it recovers the token comes back; past ``kill_s`` the process kills itself
with SIGKILL, so that the supervisor (``zagv up``) or systemd restarts it. The thread runs even while the loop is
blocked in a system call (``read()`` releases the GIL) or in a long pure-Python computation (the interpreter switches
threads every few ms).

The watchdog also ends a process whose supervisor is gone (its parent pid changed): SIGTERM first, SIGKILL after
``orphan_grace_s`` when no handler ran.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

#: (stall_s, kill_s) per service: the loop may be busy this long before the token goes, and before the process is
#: killed. Generous against a loaded machine; localization's filter and SLAM steps may hold the loop the longest.
DEFAULT_LIMITS_S: dict[str, tuple[float, float]] = {
    "drive": (3.0, 10.0), "lidar": (5.0, 15.0), "nav": (5.0, 15.0), "hmi_api": (5.0, 15.0),
    "localization": (10.0, 30.0), "sim": (5.0, 15.0),
}
FALLBACK_LIMITS_S = (5.0, 15.0)


@dataclass
class LivenessLimits:
    stall_s: float
    kill_s: float
    period_s: float = 0.25
    orphan_grace_s: float = 3.0

    @classmethod
    def for_service(cls, name: str, stall_s: float = 0.0, kill_s: float = 0.0,
                    loop_mates: Sequence[str] = ()) -> LivenessLimits:
        """Per-service defaults, overridden by non-zero ``stall_s`` / ``kill_s`` ([liveness] table). A service that
        shares its event loop with ``loop_mates`` (services/launch/container.py) waits through their steps too, so
        its defaults are the largest of the loop's: localization's long step does not stall nav's token."""
        limits = [DEFAULT_LIMITS_S.get(n, FALLBACK_LIMITS_S) for n in (name, *loop_mates)]
        default_stall, default_kill = max(stall for stall, _ in limits), max(kill for _, kill in limits)
        stall = stall_s or default_stall
        kill = kill_s or max(default_kill, stall)
        if not 0 < stall <= kill:
            raise ValueError(f"liveness: need 0 < stall_s <= kill_s, got stall_s={stall}, kill_s={kill}")
        return cls(stall_s=stall, kill_s=kill, period_s=min(0.25, stall / 4))


class LoopWatchdog:
    """Watches one event loop from a daemon thread (see the module docstring)."""

    def __init__(self, name: str, loop: asyncio.AbstractEventLoop, limits: LivenessLimits, *,
                 on_stall: Callable[[], None], on_recover: Callable[[], None],
                 parent_pid: int | None = None) -> None:
        self.name = name
        self.loop = loop
        self.limits = limits
        self.on_stall = on_stall
        self.on_recover = on_recover
        self.parent_pid = parent_pid
        self.stalls = 0
        self._beat_at = time.monotonic()
        self._stalled = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name=f"{name}-liveness", daemon=True)
        self._beater: asyncio.Task[None] | None = None

    def start(self) -> None:
        """Start the heartbeat task (call on the loop) and the watching thread."""
        self._beat_at = time.monotonic()
        self._beater = self.loop.create_task(self._beat())
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._beater is not None:
            self._beater.cancel()

    async def _beat(self) -> None:
        while True:
            self._beat_at = time.monotonic()
            await asyncio.sleep(self.limits.period_s)

    def _say(self, text: str) -> None:
        # straight to stderr: the logging machinery may hold a lock that the hung loop owns
        with contextlib.suppress(OSError, ValueError):
            os.write(sys.stderr.fileno(), f"{self.name}: liveness: {text}\n".encode())

    def _watch(self) -> None:
        orphaned_at: float | None = None
        while not self._stop.wait(self.limits.period_s):
            now = time.monotonic()
            if self.parent_pid is not None and os.getppid() != self.parent_pid:
                if orphaned_at is None:
                    orphaned_at = now
                    self._say(f"supervisor {self.parent_pid} is gone; stopping")
                    os.kill(os.getpid(), signal.SIGTERM)
                elif now - orphaned_at > self.limits.orphan_grace_s:
                    self._say("still running after SIGTERM; killing myself")
                    os.kill(os.getpid(), signal.SIGKILL)
            age = now - self._beat_at
            if age > self.limits.kill_s:
                self._say(f"event loop blocked for {age:.1f} s (limit {self.limits.kill_s:g} s); "
                          "killing the process so that it is restarted")
                os.kill(os.getpid(), signal.SIGKILL)
            elif age > self.limits.stall_s and not self._stalled:
                self._stalled = True
                self.stalls += 1
                self._say(f"event loop blocked for {age:.1f} s; health token withdrawn")
                try:
                    self.on_stall()
                except Exception as exc:
                    self._say(f"cannot withdraw the health token: {exc}")
            elif age <= self.limits.stall_s and self._stalled:
                self._stalled = False
                self._say("event loop running again; health token restored")
                self.loop.call_soon_threadsafe(self.on_recover)
