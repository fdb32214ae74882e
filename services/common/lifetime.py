"""Process lifetime: die with the supervisor that started us, so that no orphan outlives ``zagv up``.

The kernel sends SIGKILL, not SIGTERM, when the supervisor dies: a process blocked in a system call, stopped, or
otherwise unable to run a signal handler still goes. (A clean ``zagv up`` stop sends SIGTERM first and waits, so
services get to stop their motors and save their state; this is only for a supervisor that died itself. The
RoboteQ controllers' own CAN watchdog then stops the wheels.) The liveness watchdog (``services.common.liveness``)
checks the parent pid as well.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import sys

_PR_SET_PDEATHSIG = 1


def supervisor_pid() -> int | None:
    """The pid of the zagv supervisor that started this process ($ZAGV_PARENT_PID), if any."""
    parent = os.environ.get("ZAGV_PARENT_PID", "")
    return int(parent) if parent.isdigit() else None


def die_with_parent() -> None:
    """If started by a zagv supervisor ($ZAGV_PARENT_PID), get SIGKILL when it exits (Linux prctl)."""
    parent = supervisor_pid()
    if parent is None or not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # the parent died before prctl took effect
        os.kill(os.getpid(), signal.SIGKILL)


def start_count() -> int:
    """How many times the supervisor has started this service, this start included ($ZAGV_START_COUNT; 1 if
    unknown)."""
    count = os.environ.get("ZAGV_START_COUNT", "")
    return int(count) if count.isdigit() else 1


def is_restart(name: str) -> bool:
    """True when this process replaces an earlier instance of service ``name`` of the same stack or boot.

    Under ``zagv up`` the supervisor counts starts ($ZAGV_START_COUNT). Under systemd the unit's runtime folder
    ($RUNTIME_DIRECTORY, kept across automatic restarts with ``RuntimeDirectoryPreserve=restart`` and emptied when
    the unit stops) holds a marker that the first instance writes.
    """
    if start_count() > 1:
        return True
    runtime = os.environ.get("RUNTIME_DIRECTORY", "").split(":")[0]
    if not runtime or not os.path.isdir(runtime):
        return False
    marker = os.path.join(runtime, f"{name}.started")
    if os.path.exists(marker):
        return True
    with contextlib.suppress(OSError), open(marker, "w") as f:
        f.write(f"{os.getpid()}\n")
    return False
