"""Shared fixtures: free loopback ports, the shared data folder, and real-process stacks."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.common import ports
from services.common.session import open_session, router_settings

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("ZAGV_SHARED", REPO_ROOT.parent / "shared"))

pytest_plugins = ["tests.support.stack"]


@pytest.fixture
def free_port() -> int:
    return ports.free_port()


@pytest.fixture
def router(free_port: int) -> Iterator[str]:
    """An in-process Zenoh router listening on a free loopback port; yields its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port}"
    session = open_session(router_settings([endpoint]))
    yield endpoint
    session.close()


@pytest.fixture
def shared_dir() -> Path:
    """The development data folder (ZAGV_SHARED); skipped with a message where it is absent."""
    if not (SHARED / "data").is_dir():
        pytest.skip(f"development data not found at {SHARED} (set ZAGV_SHARED); a user checkout has none")
    return SHARED
