"""The sim clock across a simulator restart: sleepers and fixed-rate loops carry on in the new epoch."""

from __future__ import annotations

import asyncio

from services.common.clock import Rate, SimClock, is_fresh


def test_a_sleeper_keeps_its_remaining_time_when_the_simulator_restarts() -> None:
    async def scenario() -> tuple[bool, bool]:
        clock = SimClock()
        clock.advance(24.0)
        sleeper = asyncio.ensure_future(clock.sleep(0.5))  # due at 24.5 s of the old run
        await asyncio.sleep(0)
        clock.advance(0.01)  # the simulator restarted: its clock starts again near 0
        clock.advance(0.3)
        await asyncio.sleep(0)
        early = sleeper.done()
        clock.advance(0.52)
        await asyncio.sleep(0)
        return early, sleeper.done()

    early, woke = asyncio.run(scenario())
    assert not early, "woke before its 0.5 s had passed in the new run"
    assert woke, "still asleep 0.51 s into the new run: it waits for the old run's 24.5 s"


def test_a_rate_loop_runs_on_after_the_clock_jumps_back() -> None:
    async def scenario() -> int:
        clock = SimClock()
        clock.advance(24.0)
        rate = Rate(clock, hz=10.0)
        cycles = 0

        async def loop() -> None:
            nonlocal cycles
            while True:
                await rate.sleep()
                cycles += 1

        task = asyncio.ensure_future(loop())
        for k in range(1, 6):  # 0.5 s of the old run
            clock.advance(24.0 + 0.1 * k)
            await asyncio.sleep(0)
        clock.advance(0.0)  # restart
        before = cycles
        for k in range(1, 11):  # 1 s of the new run
            clock.advance(0.1 * k)
            for _ in range(3):
                await asyncio.sleep(0)
        task.cancel()
        return cycles - before

    cycles_after_restart = asyncio.run(scenario())
    assert cycles_after_restart >= 8, f"{cycles_after_restart} cycles in the first 1 s after the restart (10 Hz)"


def test_a_small_backwards_stamp_is_ignored() -> None:
    clock = SimClock()
    clock.advance(5.0)
    clock.advance(4.5)  # reordered clock message, not a restart
    assert clock.now() == 5.0


def test_freshness_refuses_a_stamp_from_before_a_clock_restart() -> None:
    assert is_fresh(24.0, 24.1, 0.2)
    assert not is_fresh(24.0, 24.3, 0.2)  # too old
    assert not is_fresh(24.0, 0.05, 0.2)  # from the old run, far ahead of the restarted clock


def _drive_from_thread(clock: SimClock, stamps: list[float], period_s: float) -> None:
    """Feed ``stamps`` to ``advance_threadsafe`` from another thread, one per ``period_s`` of wall time."""
    import threading
    import time

    def feed() -> None:
        for t in stamps:
            clock.advance_threadsafe(t)
            time.sleep(period_s)

    threading.Thread(target=feed, daemon=True).start()


def test_a_clock_advanced_from_another_thread_wakes_the_loop_only_for_due_sleepers() -> None:
    async def scenario() -> tuple[list[float], int, float]:
        clock = SimClock()
        clock.bind(asyncio.get_running_loop())
        rate = Rate(clock, hz=10.0)
        woke_at: list[float] = []
        _drive_from_thread(clock, [0.01 * k for k in range(1, 121)], 0.001)  # 1.2 s of a 100 Hz clock
        await clock.wait_started()
        while len(woke_at) < 10:
            await asyncio.wait_for(rate.sleep(), timeout=5.0)
            woke_at.append(clock.now())
        return woke_at, clock.loop_wakeups, clock.now()

    woke_at, wakeups, _ = asyncio.run(scenario())
    periods = [b - a for a, b in zip(woke_at, woke_at[1:], strict=False)]
    assert all(0.05 < p < 0.2 for p in periods), f"a 10 Hz loop on the sim clock woke {periods} s apart"
    # one wake-up for the first tick and about one per 10 Hz cycle, not one per 100 Hz message
    assert wakeups <= 2 * len(woke_at) + 3, f"{wakeups} loop wake-ups for {len(woke_at)} due sleepers"


def test_a_sleeper_added_as_the_thread_passes_its_target_is_not_missed() -> None:
    async def scenario() -> int:
        clock = SimClock()
        clock.bind(asyncio.get_running_loop())
        _drive_from_thread(clock, [0.001 * k for k in range(1, 3001)], 0.0)  # as fast as the thread runs
        await clock.wait_started()
        woken = 0
        while clock.now() < 2.9:
            # a target a hair ahead of now: the reader thread overtakes it while sleep_until pushes it
            await asyncio.wait_for(clock.sleep_until(clock.now() + 0.0005), timeout=2.0)
            woken += 1
        return woken

    assert asyncio.run(scenario()) > 0


def test_the_thread_path_hands_a_restart_to_the_loop() -> None:
    async def scenario() -> tuple[float, bool]:
        clock = SimClock()
        clock.bind(asyncio.get_running_loop())
        clock.advance(24.0)
        sleeper = asyncio.ensure_future(clock.sleep(0.5))
        await asyncio.sleep(0)
        clock.advance_threadsafe(0.01)  # the simulator restarted
        clock.advance_threadsafe(0.02)  # a later stamp of the new run, before the loop saw the restart
        for _ in range(3):
            await asyncio.sleep(0)
        clock.advance_threadsafe(0.6)
        await asyncio.wait_for(sleeper, timeout=2.0)
        return clock.now(), sleeper.done()

    now, woke = asyncio.run(scenario())
    assert now == 0.6 and woke
