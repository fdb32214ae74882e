"""Navigation robustness rows for ``zagv bench``: a slice of the robustness suite (services/scenario/suite.py).

``zagv bench --only scenario`` drives 3 generated goals (seed 1) in each of the built-in site-like worlds (warehouse
aisles, office with glass, cluttered hall) and reports the suite summary (``scenario.suite_*``) and
``nav.time_per_metre_s`` (sim seconds per ground-truth metre driven, reached legs). The whole suite over the public
maps as well is ``zagv scenario suite --maps-dir DIR``; its JSON carries the same rows.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from services.common.bench import BenchRow

SUITE = Path(__file__).resolve().parents[2] / "scenarios" / "suite.toml"


def bench_suite_slice() -> list[BenchRow]:
    from services.scenario.suite import run_suite

    with tempfile.TemporaryDirectory(prefix="zagv-bench-suite-") as tmp:
        out = Path(tmp) / "suite.json"
        args = argparse.Namespace(file=str(SUITE), maps_dir=None, only="warehouse,office,cluttered_hall", seeds="1",
                                  goals=3, speed=None, goal_timeout=600.0, set=[], json=str(out), run_dir=tmp)
        run_suite(args)
        rows = json.loads(out.read_text())["bench"]
    return [BenchRow(r["name"], float(r["value"]), r["unit"], r["goal"]) for r in rows]


BENCHES = [("scenario", bench_suite_slice)]
