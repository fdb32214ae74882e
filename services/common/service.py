"""Entry point shared by every service: arguments, config, session, clock, node, signals, systemd.

Each service's ``__main__`` defines ``SERVICE = ServiceSpec("drive", {"drive": DriveConfig}, run)`` where
``run(ctx)`` is its async main, and runs ``SERVICE.main()``. Common options: ``--config FILE`` (robot TOML),
``--robot-id``, ``--connect ENDPOINT`` (repeatable), ``--use-sim-time``, ``--check-config`` (validate and exit).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import sys
from collections.abc import Callable, Coroutine, Sequence
from dataclasses import dataclass, field
from typing import Any

import msgspec
import zenoh

from proto.keys import Keys
from services.common import systemd
from services.common.clock import SimClock, WallClock
from services.common.config import ConfigError
from services.common.lifetime import die_with_parent, supervisor_pid
from services.common.liveness import LivenessLimits, LoopWatchdog
from services.common.logs import setup_logging
from services.common.node import Node
from services.common.robot import RobotSpec
from services.common.session import open_session
from services.common.settings import ClockSettings, LivenessSettings, ZenohSettings

log = logging.getLogger("zagv.service")

#: a service's async main: ``async def run(ctx: ServiceContext) -> None``
ServiceMain = Callable[["ServiceContext"], Coroutine[Any, Any, None]]


@dataclass
class ServiceContext:
    """What a service's main gets: its node, the robot spec and its validated config tables."""

    node: Node
    robot: RobotSpec
    config: dict[str, Any]
    config_path: str | None
    stop: asyncio.Event = field(default_factory=asyncio.Event)

    @property
    def clock(self):  # Clock protocol
        return self.node.clock


def parse_args(name: str, argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog=f"python -m services.{name}", description=f"zagv {name} service")
    p.add_argument("--config", help="robot TOML file (default: built-in defaults)")
    p.add_argument("--robot-id", help="robot id, the <id> of agv/<id>/... (default: [robot] robot_id)")
    p.add_argument("--connect", action="append", help="Zenoh endpoint to connect to (repeatable)")
    p.add_argument("--use-sim-time", action="store_true", default=None, help="follow the simulator's clock topic")
    p.add_argument("--check-config", action="store_true", help="validate the configuration and exit")
    p.add_argument("--set", action="append", default=[], metavar="TABLE[.SUBTABLE].KEY=VALUE",
                   help="override one config value (TOML literal), e.g. --set lidar.port=2112")
    return p.parse_args(argv)


def load_config(
    name: str, sections: dict[str, type], args: argparse.Namespace
) -> tuple[RobotSpec, ZenohSettings, ClockSettings, dict[str, Any]]:
    """Robot spec, Zenoh and clock settings and the service's tables (``[liveness]`` among them when valid)."""
    import tomllib

    from services.common.config import check_sections, convert_section, read_toml

    data = read_toml(args.config) if args.config else {}
    source = f"config {args.config}" if args.config else "config"
    for item in args.set:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise ConfigError(f"--set {item!r}: expected TABLE.KEY=VALUE")
        dotted, value = item.split("=", 1)
        *tables, key = dotted.strip().split(".")  # nav.dwa.vx_samples: key vx_samples of [nav.dwa]
        try:
            parsed = tomllib.loads(f"v = {value}")["v"]
        except tomllib.TOMLDecodeError:
            parsed = value
        node = data
        for i, table in enumerate(tables):
            node = node.setdefault(table, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item!r}: {'.'.join(tables[:i + 1])} is a value, not a table")
        node[key] = parsed
    check_sections(data, source)
    robot = convert_section(data, "robot", RobotSpec, source)
    zenoh_settings = convert_section(data, "zenoh", ZenohSettings, source)
    clock_settings = convert_section(data, "clock", ClockSettings, source)
    sections = {"liveness": LivenessSettings, **sections}
    tables = {sec: convert_section(data, sec, t, source) for sec, t in sections.items()}
    if args.robot_id:
        robot = msgspec.structs.replace(robot, robot_id=args.robot_id)
    if args.connect:
        zenoh_settings.connect = list(args.connect)
    if args.use_sim_time:
        clock_settings.use_sim_time = True
    return robot, zenoh_settings, clock_settings, tables


@dataclass(frozen=True)
class ServiceSpec:
    """What a service is to the launchers: its name, its config tables and its async main.

    Each service's ``__main__`` defines ``SERVICE = ServiceSpec(...)``; ``python -m services.<name>`` runs it in a
    process of its own (``main``), and a container (``services.launch.container``) runs several in one process."""

    name: str
    sections: dict[str, type]
    run: ServiceMain
    #: arguments the service accepts and ignores (the simulator is the clock master: ``--use-sim-time``)
    ignored_args: tuple[str, ...] = ()

    def args(self, argv: list[str]) -> list[str]:
        return [a for a in argv if a not in self.ignored_args]

    def main(self, argv: list[str] | None = None) -> None:
        service_main(self.name, self.sections, self.run, self.args(sys.argv[1:] if argv is None else argv))


@dataclass
class PreparedService:
    """A service's validated configuration, ready to run (``prepare``)."""

    name: str
    run: ServiceMain
    robot: RobotSpec
    zenoh: ZenohSettings
    clock: ClockSettings
    tables: dict[str, Any]
    config_path: str | None
    check_only: bool = False


def prepare(name: str, sections: dict[str, type], run: ServiceMain,
            argv: list[str] | None) -> PreparedService:
    """Parse ``argv`` and load the config; raises ConfigError (or ValueError) naming what is wrong."""
    args = parse_args(name, argv)
    robot, zenoh_settings, clock_settings, tables = load_config(name, sections, args)
    Keys(robot.robot_id)
    return PreparedService(name, run, robot, zenoh_settings, clock_settings, tables, args.config, args.check_config)


def service_main(
    name: str,
    sections: dict[str, type],
    run: ServiceMain,
    argv: list[str] | None = None,
) -> None:
    """Parse arguments, validate config, then run ``run(ctx)`` until it returns or SIGINT/SIGTERM arrives."""
    die_with_parent()
    setup_logging(name)
    try:
        prepared = prepare(name, sections, run, argv)
    except (ConfigError, ValueError) as exc:
        print(f"zagv {name}: {exc}", file=sys.stderr)
        sys.exit(2)
    if prepared.check_only:
        print(f"zagv {name}: config ok")
        return
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(_amain(prepared))


async def _amain(prepared: PreparedService) -> None:
    """One service in a process of its own: its session, and SIGINT/SIGTERM set its stop event."""
    session = open_session(prepared.zenoh)
    try:
        await run_service(prepared, session, handle_signals=True)
    finally:
        session.close()


async def run_service(prepared: PreparedService, session: zenoh.Session, *, handle_signals: bool,
                      on_context: Callable[[ServiceContext], None] | None = None,
                      notify_ready: Callable[[], None] | None = None, loop_mates: Sequence[str] = ()) -> None:
    """Run one service on the current loop until its main returns or ``ctx.stop`` is set.

    ``handle_signals``: SIGINT/SIGTERM set ``ctx.stop`` (the main thread's loop only). A container passes False,
    gets the context through ``on_context`` to stop it itself, and tells systemd READY=1 through
    ``notify_ready`` once every service it runs is ready, and names the services sharing this loop in
    ``loop_mates`` (their steps count against this one's liveness limits)."""
    name, run, robot = prepared.name, prepared.run, prepared.robot
    clock_settings, tables = prepared.clock, prepared.tables
    loop = asyncio.get_running_loop()
    clock = SimClock() if clock_settings.use_sim_time else WallClock()
    node = Node(name, session, Keys(robot.robot_id), clock)
    if notify_ready is not None:
        node.notify_ready = notify_ready
    ctx = ServiceContext(node=node, robot=robot, config=tables, config_path=prepared.config_path)
    if on_context is not None:
        on_context(ctx)
    main = asyncio.current_task()
    stopping = False

    def on_signal(signum: int) -> None:
        nonlocal stopping
        if not stopping:
            stopping = True
            log.info("%s: %s, stopping", name, signal.Signals(signum).name)
            ctx.stop.set()
            assert main is not None
            loop.call_later(5.0, main.cancel)  # a service that ignores ctx.stop is cancelled

    stop_watch: asyncio.Task[None] | None = None
    if handle_signals:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, on_signal, sig)
    else:
        async def cancel_when_ignored() -> None:
            await ctx.stop.wait()
            await asyncio.sleep(5.0)
            assert main is not None
            main.cancel()  # a service that ignores ctx.stop is cancelled

        stop_watch = loop.create_task(cancel_when_ignored())
    watchdog = None
    period = systemd.watchdog_period_s()
    settings: LivenessSettings = tables.get("liveness") or LivenessSettings()
    limits = LivenessLimits.for_service(name, settings.stall_s, settings.kill_s, loop_mates)
    if period:  # under systemd, WatchdogSec is the limit: the kill comes from systemd then
        limits.kill_s = max(limits.stall_s, min(limits.kill_s, 2 * period))
    liveness = LoopWatchdog(name, loop, limits, on_stall=node.withdraw_health, on_recover=node.restore_health,
                            parent_pid=supervisor_pid())
    liveness.start()
    if period:
        async def feed() -> None:
            while True:
                if node.ready_at is not None:  # keep-alives follow READY=1 (sent by Node.ready)
                    systemd.notify("WATCHDOG=1")
                await asyncio.sleep(period)

        watchdog = loop.create_task(feed())
    # READY=1 comes with the health token, from the service itself once it is ready (Node.ready)
    node.log.info("started (robot %s, %s clock)", robot.robot_id, "sim" if clock_settings.use_sim_time else "wall")
    runner = loop.create_task(run(ctx))
    stopper = loop.create_task(ctx.stop.wait())
    try:
        done, _ = await asyncio.wait({runner, stopper}, return_when=asyncio.FIRST_COMPLETED)
        if runner in done:
            runner.result()
        else:
            # give the service a moment to finish on its own (it sees ctx.stop), then cancel it
            with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                await asyncio.wait_for(asyncio.shield(runner), 2.0)
            runner.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await runner
    except asyncio.CancelledError:
        runner.cancel()
    finally:
        stopper.cancel()
        liveness.stop()
        if watchdog:
            watchdog.cancel()
        if stop_watch is not None:
            stop_watch.cancel()
        systemd.notify("STOPPING=1")
        node.close()
        node.log.info("stopped")
