"""Benchmark rows for ``zagv bench``.

A module ``services/<name>/bench.py`` (or a whole-stack or log bench listed in services/launch/bench.py) exposes
``BENCHES: list[tuple[str, Callable[[], list[BenchRow]]]]``: a group name (the prefix of its rows, e.g.
``"kinematics"``) and a function that measures and returns rows. ``zagv bench --only PREFIX`` runs the groups whose
name starts with PREFIX or that PREFIX starts with.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BenchRow:
    """One measured figure: ``name`` like ``amcl.update_ms``, its value and unit, and the goal as text."""

    name: str
    value: float
    unit: str
    goal: str = ""


def time_calls(fn: Callable[[], object], *, repeat: int = 200, warmup: int = 10, max_s: float = 10.0) -> np.ndarray:
    """Wall time of each of ``repeat`` calls of ``fn`` in seconds (after ``warmup`` calls; stops at ``max_s``)."""
    for _ in range(warmup):
        fn()
    out = []
    start = time.perf_counter()
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
        if time.perf_counter() - start > max_s:
            break
    return np.asarray(out)
