"""``python -m services.launch.container [--name NAME] [--shared-loop A,B ...] SERVICE ARGS... :: SERVICE ARGS...``.

Services in one process.

Composition, as Nav2's component container runs its servers in one process (``use_composition``): each service
keeps its own node, clock, health token and liveness watchdog, and takes the same arguments as
``python -m services.<name>``. By default each service also has an event loop of its own, on a thread of its own
(ROS 2's ``component_container_isolated``), so one service's long step does not stall another's loop.
``--shared-loop A,B,...`` (repeatable, one loop per list) runs the services named there on one event loop instead
(ROS 2's single-threaded ``component_container``): a message they all read wakes one loop instead of one per
service, and they never wait for the GIL on one another. Every wake-up of a loop costs about 0.1 ms of CPU on a
small PC and each thread that waits for the GIL is switched out and in again, which is most of what isolated loops
cost beyond their own work (docs/performance.md, "Shared event loops"). The price is that a long step of one delays the
others; ``zagv up`` therefore runs the lidar and the collision monitor (the path from a scan to a stop, short
steps only) on one loop and localization, nav and the rest on another.
What they share is the process and one Zenoh session:
- a message reaches the process once, and Zenoh hands it to every subscriber in the process (the separate processes
  each pay one receive per message: about 0.1 ms of CPU each on a small PC, docs/performance.md);
- a message between two services of the container never leaves the process;
- one interpreter with numpy, zenoh and msgspec loaded, instead of one per service.
The price is isolation: a crash or a liveness kill of one service restarts the others with it, and the services
share one GIL. ``zagv up --compose`` keeps the drive (its control loop and the CAN link) in a process of its own.

SIGINT/SIGTERM stop every service; the process exits 0 once all stopped, or 1 as soon as one service ends on its
own (its failure is logged), so that the supervisor restarts the container. Under systemd, READY=1 is sent once
every service in the container is ready.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import msgspec

from services.common import systemd
from services.common.config import ConfigError
from services.common.lifetime import die_with_parent
from services.common.logs import setup_logging
from services.common.service import PreparedService, ServiceContext, ServiceSpec, prepare, run_service
from services.common.session import open_session

log = logging.getLogger("zagv.container")

SEPARATOR = "::"


def _drive() -> ServiceSpec:
    from services.drive.__main__ import SERVICE
    return SERVICE


def _lidar() -> ServiceSpec:
    from services.lidar.__main__ import SERVICE
    return SERVICE


def _safety() -> ServiceSpec:
    from services.safety.__main__ import SERVICE
    return SERVICE


def _localization() -> ServiceSpec:
    from services.localization.__main__ import SERVICE
    return SERVICE


def _nav() -> ServiceSpec:
    from services.nav.__main__ import SERVICE
    return SERVICE


def _recorder() -> ServiceSpec:
    from services.recorder.__main__ import SERVICE
    return SERVICE


def _hmi_api() -> ServiceSpec:
    from services.hmi_api.__main__ import SERVICE
    return SERVICE


def _foxglove_bridge() -> ServiceSpec:
    from services.foxglove_bridge.__main__ import SERVICE
    return SERVICE


def _vda5050() -> ServiceSpec:
    from services.vda5050.__main__ import SERVICE
    return SERVICE


#: the services a container may run, each imported only when asked for; not the simulator (the clock master and
#: simulated hardware)
SERVICE_SPECS: dict[str, Callable[[], ServiceSpec]] = {
    "drive": _drive, "lidar": _lidar, "safety": _safety, "localization": _localization, "nav": _nav,
    "recorder": _recorder, "hmi_api": _hmi_api, "foxglove_bridge": _foxglove_bridge, "vda5050": _vda5050}
COMPOSABLE = tuple(SERVICE_SPECS)


def split_groups(argv: list[str]) -> list[tuple[str, list[str]]]:
    """``[name, args..., "::", name, args...]`` as (service name, its arguments) pairs."""
    groups: list[list[str]] = [[]]
    for arg in argv:
        if arg == SEPARATOR:
            groups.append([])
        else:
            groups[-1].append(arg)
    out: list[tuple[str, list[str]]] = []
    for group in groups:
        if not group:
            raise ConfigError(f"an empty service between '{SEPARATOR}' separators")
        name, *args = group
        if name not in COMPOSABLE:
            raise ConfigError(f"{name!r} cannot run in a container (composable: {', '.join(COMPOSABLE)})")
        if name in (n for n, _ in out):
            raise ConfigError(f"{name} is given twice")
        out.append((name, args))
    return out


def service_spec(name: str) -> ServiceSpec:
    """``services.<name>.__main__.SERVICE``."""
    if name not in SERVICE_SPECS:
        raise ConfigError(f"{name!r} cannot run in a container (composable: {', '.join(COMPOSABLE)})")
    return SERVICE_SPECS[name]()


def parse_shared_loops(values: list[str], names: list[str]) -> list[list[str]]:
    """The ``--shared-loop`` groups: each comma-separated services of this container, none named twice."""
    groups: list[list[str]] = []
    seen: set[str] = set()
    for value in values:
        shared = [n.strip() for n in value.split(",") if n.strip()]
        if not shared:
            raise ConfigError("--shared-loop names no service")
        for name in shared:
            if name not in names:
                raise ConfigError(f"--shared-loop: {name!r} is not a service of this container ({', '.join(names)})")
            if name in seen:
                raise ConfigError(f"--shared-loop: {name} is given twice")
            seen.add(name)
        groups.append(shared)
    return groups


def prepare_all(groups: list[tuple[str, list[str]]]) -> list[PreparedService]:
    """Each service's validated config; they must agree on the Zenoh session they share."""
    prepared: list[PreparedService] = []
    for name, args in groups:
        spec = service_spec(name)
        try:
            prepared.append(prepare(spec.name, spec.sections, spec.run, spec.args(args)))
        except (ConfigError, ValueError) as exc:
            raise ConfigError(f"{name}: {exc}") from None
    first = prepared[0]
    for other in prepared[1:]:
        if msgspec.to_builtins(other.zenoh) != msgspec.to_builtins(first.zenoh):
            raise ConfigError(f"{other.name} and {first.name} have different [zenoh] settings; services that share a "
                              "container share one session")
    return prepared


@dataclass
class Container:
    """The services of one process: those of each ``shared_loops`` group on one thread and event loop, each other
    one on a thread and event loop of its own."""

    services: list[PreparedService]
    shared_loops: list[list[str]] = field(default_factory=list)
    stopping: threading.Event = field(default_factory=threading.Event)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _contexts: dict[str, tuple[asyncio.AbstractEventLoop, ServiceContext]] = field(default_factory=dict)
    _ready: set[str] = field(default_factory=set)
    _ended: dict[str, BaseException | None] = field(default_factory=dict)
    _wake: threading.Event = field(default_factory=threading.Event)

    def _register(self, name: str, ctx: ServiceContext) -> None:
        loop = asyncio.get_running_loop()
        with self._lock:
            self._contexts[name] = (loop, ctx)
            if self.stopping.is_set():
                ctx.stop.set()

    def _on_ready(self, name: str) -> None:
        with self._lock:
            self._ready.add(name)
            all_ready = len(self._ready) == len(self.services)
        if all_ready:
            systemd.notify("READY=1")

    async def _run_one(self, prepared: PreparedService, session, loop_mates: list[str]) -> None:
        """Run one service on the current loop; how it ended is left for the main thread to report."""
        name = prepared.name
        error: BaseException | None = None
        try:
            await run_service(prepared, session, handle_signals=False,
                              on_context=lambda ctx: self._register(name, ctx),
                              notify_ready=lambda: self._on_ready(name), loop_mates=loop_mates)
        except BaseException as exc:  # reported by the main thread, which stops the rest
            error = exc
        with self._lock:
            self._ended[name] = error
        self._wake.set()

    def _thread_main(self, group: list[PreparedService], session) -> None:
        """One event loop running every service of ``group`` until each has ended."""
        async def run_group() -> None:
            names = [p.name for p in group]
            await asyncio.gather(*(self._run_one(p, session, [n for n in names if n != p.name]) for p in group))

        asyncio.run(run_group())

    def loop_groups(self) -> list[list[PreparedService]]:
        """The services of each event loop, in the order of the services: a shared loop where its first one is."""
        loop_of = {name: k for k, names in enumerate(self.shared_loops) for name in names}
        groups: list[list[PreparedService]] = []
        shared: dict[int, list[PreparedService]] = {}
        for prepared in self.services:
            k = loop_of.get(prepared.name)
            if k is None:
                groups.append([prepared])
            elif k in shared:
                shared[k].append(prepared)
            else:
                shared[k] = [prepared]
                groups.append(shared[k])
        return groups

    def stop(self) -> None:
        """Set every service's stop event (any thread)."""
        self.stopping.set()
        self._wake.set()
        with self._lock:
            contexts = list(self._contexts.values())
        for loop, ctx in contexts:
            if not loop.is_closed():
                loop.call_soon_threadsafe(ctx.stop.set)

    def run(self) -> int:
        """Run until a signal or until one service ends; 0 after a requested stop, 1 when a service ended."""
        session = open_session(self.services[0].zenoh)
        threads = [threading.Thread(target=self._thread_main, args=(group, session), daemon=True,
                                    name="+".join(p.name for p in group))
                   for group in self.loop_groups()]
        for thread in threads:
            thread.start()
        failed = False
        try:
            while not self.stopping.is_set():
                self._wake.wait(timeout=1.0)
                self._wake.clear()
                with self._lock:
                    ended = dict(self._ended)
                if ended and not self.stopping.is_set():
                    for name, error in ended.items():
                        reason = f"failed: {error!r}" if error is not None else "ended on its own"
                        log.error("%s %s; stopping the container", name, reason)
                    failed = True
                    break
        finally:
            self.stop()
            for thread in threads:
                thread.join(timeout=10.0)
            alive = [t.name for t in threads if t.is_alive()]
            if alive:
                log.error("still running 10 s after the stop: %s", ", ".join(alive))
                failed = True
            session.close()
        return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    die_with_parent()
    argv = sys.argv[1:] if argv is None else argv
    container_name = "container"
    shared_values: list[str] = []
    while argv[:1] in (["--name"], ["--shared-loop"]) and len(argv) > 1:
        if argv[0] == "--name":
            container_name = argv[1]
        else:
            shared_values.append(argv[1])
        argv = argv[2:]
    setup_logging(container_name, show_logger=True)
    try:
        groups = split_groups(argv)
        shared = parse_shared_loops(shared_values, [n for n, _ in groups])
        services = prepare_all(groups)
    except ConfigError as exc:
        print(f"zagv container: {exc}", file=sys.stderr)
        return 2
    if any(p.check_only for p in services):
        print(f"zagv {container_name}: config ok")
        return 0
    container = Container(services, shared)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: container.stop())
    log.info("running %s in one process%s", ", ".join(p.name for p in services),
             "".join(f" ({', '.join(group)} on one event loop)" for group in shared))
    return container.run()


if __name__ == "__main__":
    sys.exit(main())
