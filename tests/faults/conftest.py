"""The ``fault_figures`` fixture: measured recovery times, printed and collected in ``fault_figures.txt``.

Each figure is printed (visible with ``-s``), attached to the test report with ``record_property`` and appended
to ``<pytest base temp>/fault_figures.txt`` so one run leaves a summary of every measurement.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest


@pytest.fixture
def fault_figures(request: pytest.FixtureRequest, record_property: Callable[[str, object], None],
                  tmp_path_factory: pytest.TempPathFactory) -> Callable[[str, float, str], None]:
    summary: Path = tmp_path_factory.getbasetemp() / "fault_figures.txt"

    def record(name: str, value: float, unit: str = "s") -> None:
        line = f"{request.node.name}: {name} = {value:.3f} {unit}"
        print(f"\nfault figure: {line}", flush=True)
        record_property(name, f"{value:.3f} {unit}")
        with summary.open("a") as f:
            f.write(line + "\n")

    return record
