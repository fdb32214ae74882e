"""AMCL benchmarks: one sensor update plus resampling on a synthetic corridor map (no files needed)."""

from __future__ import annotations

import math

import numpy as np

from services.common.bench import BenchRow, time_calls
from services.localization.amcl import AmclParams, ParticleFilter, beam_indices
from services.localization.map_io import OccupancyMap


def bench_map() -> OccupancyMap:
    """A 40 m x 20 m map (0.05 m cells): outer walls, a corridor and a few boxes."""
    res = 0.05
    data = np.zeros((400, 800), dtype=np.int8)
    data[:2, :] = data[-2:, :] = data[:, :2] = data[:, -2:] = 100
    data[180:184, 100:700] = 100
    for i in range(6):
        data[60 + 40 * (i % 3): 80 + 40 * (i % 3), 120 + 100 * i: 140 + 100 * i] = 100
    return OccupancyMap(data, res, (-5.0, -5.0, 0.0))


def update_ms(particles: int, beams: int = 60, repeat: int = 200) -> float:
    """Median ms of sensor_update + resample with ``particles`` kept (min = max) and ``beams`` beams."""
    params = AmclParams(min_particles=particles, max_particles=particles, max_beams=beams, random_seed=1)
    pf = ParticleFilter(bench_map(), params)
    pf.init_gaussian((10.0, 3.0, 0.3), np.diag([0.5, 0.5, 0.3]))
    idx = beam_indices(541, beams)
    bearings = -math.radians(135) + idx * math.radians(0.5)
    ranges = np.random.default_rng(2).uniform(0.5, 15.0, size=idx.size)

    def one() -> None:
        pf.sensor_update(ranges, bearings, (0.45, 0.0, 0.0), 20.0)
        pf.resample()

    return float(np.median(time_calls(one, repeat=repeat, warmup=10, max_s=5.0)) * 1e3)


def run() -> list[BenchRow]:
    return [
        BenchRow("amcl.update_ms", update_ms(2000), "ms", "<= 3 (2000 particles x 61 beams, update + resample)"),
        BenchRow("amcl.update_ms_5000", update_ms(5000, repeat=100), "ms", "5000 particles x 61 beams"),
    ]


BENCHES = [("amcl", run)]
