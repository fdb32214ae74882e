"""Waiting on conditions with a deadline (tests never sleep for a fixed time and hope)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable


async def wait_for(condition: Callable[[], object], *, timeout_s: float, poll_s: float = 0.02,
                   message: str = "") -> object:
    """Poll ``condition`` until it is truthy; raise AssertionError naming it after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(message or f"condition not met within {timeout_s} s")
        await asyncio.sleep(poll_s)


def wait_for_sync(condition: Callable[[], object], *, timeout_s: float, poll_s: float = 0.02,
                  message: str = "") -> object:
    """Blocking variant of ``wait_for``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(message or f"condition not met within {timeout_s} s")
        time.sleep(poll_s)
