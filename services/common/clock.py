"""One clock for every service: wall time, or simulated time from the ``clock`` topic (``use_sim_time``).

``now()`` is seconds (wall: Unix time; sim: seconds since the simulation started). ``sleep``/``sleep_until``
wait on that clock, so a service runs unchanged when the simulator runs faster than real time.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import logging
import math
import time
from typing import Protocol

log = logging.getLogger(__name__)


def is_fresh(stamp_s: float, now_s: float, max_age_s: float) -> bool:
    """|now - stamp| <= max_age: young enough, and not from ahead of now.

    A stamp further ahead of ``now`` than ``max_age_s`` was taken before the clock restarted (a simulator restart
    sets sim time back to 0); counting it as fresh would keep an old command or scan alive until the new clock
    caught up with it."""
    return abs(now_s - stamp_s) <= max_age_s


def due(now_s: float, next_s: float, period_s: float) -> bool:
    """Whether a periodic action scheduled for ``next_s`` is due at ``now_s``: its time has come, or ``next_s`` lies
    more than one ``period_s`` ahead of now (the clock restarted: a schedule left from the old run would otherwise
    wait until the new run's clock caught up with it)."""
    return now_s >= next_s or next_s - now_s > period_s


class Clock(Protocol):
    """What services read time through: ``now()`` in s, sleeps, and whether it is the simulator's clock."""

    is_sim: bool

    def now(self) -> float: ...

    async def wait_started(self) -> None: ...

    async def sleep_until(self, t: float) -> None: ...

    async def sleep(self, dt: float) -> None: ...


class WallClock:
    """System time; sleeps with the event loop's monotonic timer."""

    is_sim = False

    def now(self) -> float:
        return time.time()

    async def wait_started(self) -> None:
        """Wall time runs from the start."""

    async def sleep(self, dt: float) -> None:
        await asyncio.sleep(max(0.0, dt))

    async def sleep_until(self, t: float) -> None:
        await asyncio.sleep(max(0.0, t - time.time()))


class SimClock:
    """Time driven by ``advance(t)`` (the ``clock`` topic); waiters wake when sim time reaches their target."""

    is_sim = True

    def __init__(self) -> None:
        self._now = 0.0
        self.speed_factor = 1.0
        self._waiters: list[tuple[float, int, asyncio.Future[None]]] = []
        self._seq = itertools.count()
        self._started = asyncio.Event()
        # the earliest sleeper's target: written on the loop thread, read by ``advance_threadsafe``
        self._due_s = math.inf
        self._loop: asyncio.AbstractEventLoop | None = None
        self.loop_wakeups = 0  # clock messages that had to wake the loop (``advance_threadsafe``)

    def now(self) -> float:
        return self._now

    @property
    def started(self) -> bool:
        return self._started.is_set()

    async def wait_started(self) -> None:
        """Wait for the first clock message."""
        await self._started.wait()

    def advance(self, t: float, speed_factor: float | None = None) -> None:
        """Set sim time to ``t`` (monotonic: an older stamp is ignored) and wake due sleepers. Loop thread only."""
        if speed_factor is not None:
            self.speed_factor = speed_factor
        if t < self._now:
            if t >= self._now - 1.0:
                return
            # the simulator restarted: jump back, and keep each sleeper's remaining time in the new epoch (a sleeper
            # left at its old target would wait until the new run's clock caught up with the old one)
            log.warning("sim clock jumped back from %.3f to %.3f s", self._now, t)
            shift_s = t - self._now
            self._waiters = [(target + shift_s, seq, fut) for target, seq, fut in self._waiters]
            heapq.heapify(self._waiters)
        self._now = t
        self._wake_due()

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        """The event loop ``advance_threadsafe`` wakes."""
        self._loop = loop

    def advance_threadsafe(self, t: float, speed_factor: float | None = None) -> None:
        """``advance`` from the clock's reader thread: the new time is taken at once, and the loop is woken only
        when a sleeper is due (t >= its target), on the first message and when the clock jumps back.

        A 100 Hz clock thus costs a service one loop wake-up per due sleeper instead of one per message. Under the
        GIL the two sides are ordered: this writes ``_now`` before reading ``_due_s``, and ``sleep_until`` writes
        ``_due_s`` before reading ``_now`` again, so a sleeper added while the clock passes its target is woken
        by one side or the other."""
        loop = self._loop
        if loop is None:
            raise RuntimeError("SimClock.advance_threadsafe before bind(loop)")
        if self._now - 1.0 <= t < self._now:
            return  # an older stamp (``advance`` ignores it too)
        if t < self._now or not self._started.is_set():
            # a simulator restart, or the first tick (which sets ``started``): ``advance`` on the loop
            loop.call_soon_threadsafe(self.advance, t, speed_factor)
            self.loop_wakeups += 1
            return
        if speed_factor is not None:
            self.speed_factor = speed_factor
        self._now = t
        if t >= self._due_s:
            self._due_s = math.inf  # one wake-up per due sleeper; _wake_due sets the next target
            loop.call_soon_threadsafe(self._wake_due)
            self.loop_wakeups += 1

    def _wake_due(self) -> None:
        """Set the started flag and resolve every sleeper whose target has come (loop thread)."""
        self._started.set()
        now = self._now
        while self._waiters and self._waiters[0][0] <= now:
            _, _, fut = heapq.heappop(self._waiters)
            if not fut.done():
                fut.set_result(None)
        self._due_s = self._waiters[0][0] if self._waiters else math.inf

    async def sleep_until(self, t: float) -> None:
        if t <= self._now and self.started:
            await asyncio.sleep(0)
            return
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        heapq.heappush(self._waiters, (t, next(self._seq), fut))
        self._due_s = self._waiters[0][0]
        if t <= self._now and self.started:  # the reader thread advanced past t meanwhile (advance_threadsafe)
            self._wake_due()
        await fut

    async def sleep(self, dt: float) -> None:
        await self.sleep_until(self._now + max(0.0, dt))


class Rate:
    """Fixed-rate loop timing on a clock. ``await rate.sleep()`` once per cycle.

    An overrun (a cycle that ends after its deadline) is counted in ``overruns`` and the schedule is re-anchored
    at now, so a slow cycle does not cause a burst of catch-up cycles.
    """

    def __init__(self, clock: Clock, hz: float) -> None:
        if not hz > 0:
            raise ValueError(f"rate must be > 0 Hz, got {hz}")
        self.clock = clock
        self.period_s = 1.0 / hz
        self.overruns = 0
        self.cycles = 0
        self._next: float | None = None

    async def sleep(self) -> None:
        now = self.clock.now()
        self.cycles += 1
        if self._next is None or self._next - now > 2.0 * self.period_s:  # first cycle, or the clock jumped back
            self._next = now + self.period_s
        elif now > self._next + self.period_s * 0.5:
            self.overruns += 1
            self._next = now + self.period_s
        await self.clock.sleep_until(self._next)
        self._next += self.period_s
