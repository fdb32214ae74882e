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
