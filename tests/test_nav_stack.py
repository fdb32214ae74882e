"""Navigation in the full simulated stack (sim, drive, lidar, localization, nav): ``zagv scenario run`` on a short
corridor scenario with a box that appears on the way; errors are measured against the simulator's ground truth."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.integration, pytest.mark.slow]

REPO_ROOT = Path(__file__).resolve().parents[1]

SCENARIO = """
world = "corridor"
start = [0.0, 3.2, 0.0]
repeats = 1
speed = 3.0
[[goals]]
id = "east"
pose = [13.6, 3.2, -1.0]
[[goals]]
id = "back"
pose = [3.0, 3.5, 3.14]
[[dynamic_obstacles]]
rect = [9.0, 1.6, 10.0, 3.0]
during_goal = 2
appear_after_s = 2.0
"""


def test_scenario_reaches_goals_and_replans_around_a_box(tmp_path: Path) -> None:
    scenario = tmp_path / "short.toml"
    scenario.write_text(SCENARIO)
    out = tmp_path / "result.json"
    done = subprocess.run([sys.executable, "-m", "services.cli", "scenario", "run", str(scenario), "--json", str(out),
                           "--run-dir", str(tmp_path / "run")], capture_output=True, text=True, timeout=900,
                          cwd=REPO_ROOT)
    log = (tmp_path / "run" / "stack.log")
    context = done.stdout + done.stderr + (log.read_text()[-4000:] if log.exists() else "")
    assert done.returncode == 0, context
    result = json.loads(out.read_text())
    (run,) = result["runs"]
    assert run["run"] == 1
    for g in run["goals"]:
        assert {"id", "target", "reached", "claimed", "final", "error", "time_s", "recoveries", "collisions",
                "driven_m", "loc_error_max_m", "loc_error_rms_m"} <= set(g)
        assert g["claimed"] == "succeeded"
        assert g["reached"], context
        assert all(abs(e) <= 0.05 for e in g["error"]), (g, context)
    assert "collisions: 0" in done.stdout
    assert "replanned around the dynamic obstacle in 1/1 legs" in done.stdout, context
