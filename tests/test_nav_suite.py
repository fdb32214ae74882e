"""The robustness suite end to end on a slice small enough for ``make test``: ``zagv scenario suite`` generates a
goal on a built-in world, drives it in the simulated stack and judges it by the ground truth; the whole suite is
the ``long`` test below (``make test-long``) and ``zagv scenario suite --maps-dir DIR``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def run_suite(tmp_path: Path, *args: str, timeout_s: float) -> tuple[subprocess.CompletedProcess, dict]:
    out = tmp_path / "suite.json"
    done = subprocess.run([sys.executable, "-m", "services.cli", "scenario", "suite", "scenarios/suite.toml",
                           "--json", str(out), "--run-dir", str(tmp_path / "run"), *args],
                          capture_output=True, text=True, timeout=timeout_s, cwd=REPO_ROOT)
    assert out.exists(), done.stdout + done.stderr
    return done, json.loads(out.read_text())


@pytest.mark.integration
@pytest.mark.slow
def test_suite_slice_reaches_a_generated_goal_judged_by_ground_truth(tmp_path: Path) -> None:
    done, result = run_suite(tmp_path, "--only", "cluttered_hall", "--seeds", "4", "--goals", "1", "--max-leg", "5",
                               timeout_s=600)
    context = done.stdout + done.stderr
    (row,) = result["rows"]
    assert row["map"] == "cluttered_hall" and row["goals"] == 1, context
    (goal,) = result["maps"][0]["runs"][0]["goals"]
    assert goal["reached"] and goal["claimed"] == "succeeded", context
    assert abs(goal["error"][0]) < 0.05 and abs(goal["error"][1]) < 0.05 and abs(goal["error"][2]) < 0.05
    assert goal["collisions"] == 0 and goal["driven_m"] > 2.0 and goal["loc_error_max_m"] is not None
    bench = {b["name"]: b["value"] for b in result["bench"]}
    assert bench["scenario.suite_reached_pct"] == 100.0 and bench["nav.time_per_metre_s"] >= 5.0  # 0.2 m/s at best
    assert "cluttered_hall" in done.stdout and done.returncode == 0, context


@pytest.mark.long
def test_whole_suite_meets_the_robustness_acceptance(shared_dir: Path, tmp_path: Path) -> None:
    maps = shared_dir / "data" / "maps"
    done, result = run_suite(tmp_path, "--maps-dir", str(maps), timeout_s=float(os.environ.get("ZAGV_SUITE_S", 14400)))
    bench = {b["name"]: b["value"] for b in result["bench"]}
    context = done.stdout[-6000:]
    assert bench["scenario.suite_maps"] >= 8 and bench["scenario.suite_goals"] >= 120, context
    assert bench["scenario.suite_collisions"] == 0 and bench["scenario.suite_claimed_outside"] == 0, context
    assert bench["scenario.suite_reached_pct"] >= 97.0, context
