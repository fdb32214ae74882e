"""Every zagv process runs OpenBLAS with one thread (``services/__init__.py``): a service calls numpy from its event
loop and its Zenoh reader threads, and OpenBLAS has returned wrong results to concurrent callers."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
COUNT_THREADS = "import os; {imports}; print(len(os.listdir('/proc/self/task')))"


def _threads_after(imports: str) -> int:
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
    done = subprocess.run([sys.executable, "-c", COUNT_THREADS.format(imports=imports)], capture_output=True,
                          text=True, env=env, cwd=REPO_ROOT, check=True, timeout=60)
    return int(done.stdout)


def test_importing_the_services_makes_blas_single_threaded() -> None:
    assert _threads_after("import services.nav.costmap, numpy, scipy.ndimage") == 1


def test_a_blas_thread_count_set_by_the_environment_is_kept() -> None:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="3")
    done = subprocess.run([sys.executable, "-c", "import os, services; print(os.environ['OPENBLAS_NUM_THREADS'])"],
                          capture_output=True, text=True, env=env, cwd=REPO_ROOT, check=True, timeout=60)
    assert done.stdout.strip() == "3"

