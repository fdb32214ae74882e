"""Process supervisor for ``zagv up`` and the test fixtures.

Each child runs in its own process; its output is prefixed with its name; a child that exits while the supervisor
is running is restarted with exponential backoff (0.5 s doubling to 8 s, reset after 30 s of good running) and the
exit is logged. Children get SIGKILL from the kernel if the supervisor dies (PR_SET_PDEATHSIG), so no orphan
outlives it, even one blocked in a system call (each child arms that itself through ``services.common.lifetime``).
Each start gets ``ZAGV_START_COUNT`` (1, 2, ...) so that a restarted service knows it is one (drive then stays
disabled). ``stop()`` sends SIGTERM, waits a grace period, then SIGKILLs what is left.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from services.common.logs import print_line

log = logging.getLogger("zagv.supervisor")


@dataclass
class ChildSpec:
    """A supervised command: ``name`` prefixes its log lines."""

    name: str
    argv: list[str]
    env: dict[str, str] = field(default_factory=dict)
    cwd: str | None = None
    restart: bool = True


@dataclass
class ChildState:
    spec: ChildSpec
    proc: asyncio.subprocess.Process | None = None
    starts: int = 0
    exits: list[tuple[float, int]] = field(default_factory=list)
    task: asyncio.Task[None] | None = None

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc and self.proc.returncode is None else None


def describe_exit(code: int) -> str:
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exited with code {code}"


class Supervisor:
    """Starts, watches, restarts and stops child processes."""

    def __init__(
        self,
        *,
        out: Callable[[str], None] | None = None,
        backoff_initial_s: float = 0.5,
        backoff_max_s: float = 8.0,
        stable_after_s: float = 30.0,
    ) -> None:
        self.children: dict[str, ChildState] = {}
        self.out = out or print_line
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self.stable_after_s = stable_after_s
        self._stopping = False
        self.width = 12

    def add(self, spec: ChildSpec) -> ChildState:
        if spec.name in self.children:
            raise ValueError(f"duplicate child {spec.name!r}")
        state = ChildState(spec)
        self.children[spec.name] = state
        self.width = max(self.width, len(spec.name))
        state.task = asyncio.get_running_loop().create_task(self._watch(state))
        return state

    def emit(self, name: str, line: str) -> None:
        self.out(f"{name:<{self.width}} | {line}")

    async def _pump(self, name: str, stream: asyncio.StreamReader) -> None:
        while True:
            try:
                raw = await stream.readline()
            except ValueError:  # a line over the stream limit
                raw = await stream.read(65536)
            if not raw:
                return
            self.emit(name, raw.decode(errors="replace").rstrip())

    async def _spawn(self, state: ChildState) -> asyncio.subprocess.Process:
        spec = state.spec
        # ZAGV_PARENT_PID lets the child ask the kernel for SIGKILL when we die (services.common.lifetime)
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "ZAGV_PARENT_PID": str(os.getpid()),
               "ZAGV_START_COUNT": str(state.starts + 1), **spec.env}
        proc = await asyncio.create_subprocess_exec(
            *spec.argv,
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.STDOUT,
            env=env,
            cwd=spec.cwd,
            process_group=0,  # Ctrl-C in the terminal reaches only the supervisor, which stops the children
            limit=1 << 20,
        )
        state.proc = proc
        state.starts += 1
        self.emit("zagv", f"started {spec.name} (pid {proc.pid})")
        return proc

    async def _watch(self, state: ChildState) -> None:
        backoff = self.backoff_initial_s
        while not self._stopping:
            started = time.monotonic()
            try:
                proc = await self._spawn(state)
            except OSError as exc:
                self.emit("zagv", f"cannot start {state.spec.name}: {exc}")
                return
            assert proc.stdout is not None
            pump = asyncio.get_running_loop().create_task(self._pump(state.spec.name, proc.stdout))
            code = await proc.wait()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(pump, 1.0)
            state.exits.append((time.time(), code))
            if self._stopping:
                return
            if time.monotonic() - started > self.stable_after_s:
                backoff = self.backoff_initial_s
            if not state.spec.restart:
                self.emit("zagv", f"{state.spec.name} {describe_exit(code)}")
                return
            self.emit("zagv", f"{state.spec.name} {describe_exit(code)}; restarting in {backoff:.1f} s")
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2.0, self.backoff_max_s)

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        """Send ``sig`` to one child (it is restarted by its watcher)."""
        pid = self.children[name].pid
        if pid:
            os.kill(pid, sig)

    async def stop(self, timeout_s: float = 5.0) -> None:
        """SIGTERM every child, wait up to ``timeout_s``, SIGKILL the rest, and reap them all."""
        self._stopping = True
        procs = [s.proc for s in self.children.values() if s.proc and s.proc.returncode is None]
        for p in procs:
            with contextlib.suppress(ProcessLookupError):
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        for p in procs:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(p.wait(), max(0.01, deadline - time.monotonic()))
        for p in procs:
            if p.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    p.kill()
                await p.wait()
        for s in self.children.values():
            if s.task:
                s.task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await s.task


def python_module(module: str, *args: str) -> list[str]:
    """argv running ``python -m module args`` with this interpreter."""
    return [sys.executable, "-m", module, *args]
