"""The ``stack_factory`` fixture: real ``zagv up`` stacks on free loopback ports, always torn down."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from services.common.ports import free_port
from services.launch.stack_process import Stack

__all__ = ["Stack", "free_port", "stack_factory"]


@pytest.fixture
def stack_factory(tmp_path: Path) -> Iterator:
    """``stack_factory(services=[...], **options).start()``; every stack is stopped at teardown."""
    stacks: list[Stack] = []

    def make(services: list[str] | None = None, **kwargs) -> Stack:
        run_dir = tmp_path / f"stack{len(stacks)}"
        run_dir.mkdir()
        st = Stack(run_dir, services, **kwargs)
        stacks.append(st)
        return st

    yield make
    for st in stacks:
        st.stop()
