"""Process lifetime: die with the supervisor that started us, so that no orphan outlives ``zagv up``."""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import sys

_PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """If started by a zagv supervisor ($ZAGV_PARENT_PID), get SIGTERM when it exits (Linux prctl)."""
    parent = os.environ.get("ZAGV_PARENT_PID")
    if not parent or not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != int(parent):  # the parent died before prctl took effect
        os.kill(os.getpid(), signal.SIGTERM)
