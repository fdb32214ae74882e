"""Shared fixtures: free loopback ports, the shared data folder, and real-process stacks."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("ZAGV_SHARED", REPO_ROOT.parent / "shared"))

pytest_plugins = ["tests.support.stack"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def free_port() -> int:
    return _free_port()


@pytest.fixture
def shared_dir() -> Path:
    """The project's development data (../shared); skipped with a message where it is absent."""
    if not (SHARED / "data").is_dir():
        pytest.skip(f"development data not found at {SHARED} (set ZAGV_SHARED); a user checkout has none")
    return SHARED
