"""Every zagv process runs OpenBLAS with one thread (``services/__init__.py``): a service calls numpy from its event
loop and its Zenoh reader threads, and OpenBLAS has returned wrong results to concurrent callers."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]


def _run(code: str, **env_changes: str | None) -> str:
    """stdout of ``python -c code`` in the repo, with environment variables set (a value) or removed (None)."""
    env = dict(os.environ)
    for name, value in env_changes.items():
        if value is None:
            env.pop(name, None)
        else:
            env[name] = value
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=REPO_ROOT,
                          check=True, timeout=60).stdout.strip()


def test_importing_the_services_makes_blas_single_threaded() -> None:
    code = "import os, services.nav.costmap, numpy, scipy.ndimage; print(len(os.listdir('/proc/self/task')))"
    assert _run(code, OPENBLAS_NUM_THREADS=None, OMP_NUM_THREADS=None) == "1"


def test_a_blas_thread_count_set_by_the_environment_is_kept() -> None:
    assert _run("import os, services; print(os.environ['OPENBLAS_NUM_THREADS'])", OPENBLAS_NUM_THREADS="3") == "3"
