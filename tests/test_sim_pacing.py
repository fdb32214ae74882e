"""The simulator's wall-clock pacing (services/sim/pacing.py)."""

from __future__ import annotations

import pytest

from services.sim.pacing import MIN_SLEEP_WALL_S, Pacer


def test_steps_are_due_at_the_speed_factor() -> None:
    p = Pacer(2.0, now_wall_s=100.0, sim_now_s=0.0)
    assert p.wait_s(100.0, 0.0, 0.01, steps=0) == pytest.approx(0.005)  # 10 ms of sim at 2x: 5 ms of wall
    assert p.wait_s(100.0, 0.0, 0.001, steps=0) == MIN_SLEEP_WALL_S  # never a shorter sleep: catch up in a burst
    assert p.wait_s(100.02, 0.03, 0.01, steps=4) == 0.0  # on time: yield every 4 steps
    assert p.wait_s(100.02, 0.03, 0.01, steps=5) is None


def test_a_late_loop_reanchors_instead_of_bursting() -> None:
    p = Pacer(1.0, now_wall_s=0.0, sim_now_s=0.0)
    assert p.wait_s(1.0, 0.0, 0.01, steps=1) is None and p.behind == 1
    assert p.wait_s(1.0, 0.0, 0.01, steps=1) == pytest.approx(0.01)  # due again from the new anchor


def test_free_run_yields_and_the_factor_is_measured_each_wall_second() -> None:
    free = Pacer(0.0, now_wall_s=0.0, sim_now_s=0.0)
    assert free.free_run and free.achieved == 1.0 and free.wait_s(5.0, 0.0, 0.01, steps=3) == 0.0
    p = Pacer(3.0, now_wall_s=0.0, sim_now_s=0.0)
    assert p.achieved == 3.0 and not p.measure(0.5, 1.5)
    assert p.measure(1.0, 2.5) and p.achieved == pytest.approx(2.5)
