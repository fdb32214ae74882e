"""``zagv up``: the embedded router plus every service as a supervised process.

In sim mode it also starts the simulated CAN bus (a python-can-remote server over a virtual bus on 127.0.0.1) and
the simulator; every service then follows the simulator's clock. ``zagv: ready`` is printed once each service's
health token (``agv/<id>/@health/<service>``) is up; Ctrl-C or SIGTERM stops everything.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import random
import signal
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from proto.keys import Keys
from services.common.lifetime import die_with_parent
from services.common.logs import print_line
from services.common.session import open_session, router_settings
from services.common.settings import ZenohSettings
from services.launch.container import COMPOSABLE, SEPARATOR
from services.launch.fleet import RobotSlot, fleet_slots, parse_robot_arg, resolve_starts, sim_robots_toml, world_robots
from services.launch.supervisor import ChildSpec, Supervisor, python_module

#: services in start order (each is ``python -m services.<name>``)
SERVICES = ["sim", "drive", "lidar", "safety", "localization", "nav", "recorder", "hmi_api"]
REPO_ROOT = Path(__file__).resolve().parents[2]


@dataclass
class StackPlan:
    """Everything needed to start one robot's stack: ports, options, and the children to run."""

    robot_id: str = "r1"
    sim: bool = True
    world: str = "corridor"
    map_yaml: str | None = None
    config: str | None = None
    speed: float = 1.0
    headless: bool = False
    mapping: bool = False
    zenoh_port: int = 7447
    can_port: int = 54701
    lidar_port: int = 2111
    http_port: int = 8080
    run_dir: str = ""
    extra_sets: list[str] = field(default_factory=list)
    only: list[str] | None = None
    #: a router to use instead of the embedded one (e.g. ``tcp/127.0.0.1:7447`` of ``zagv router`` or zenohd)
    external_router: str | None = None
    #: Foxglove WebSocket port of the foxglove_bridge service (0: the bridge is not started)
    foxglove_port: int = 0
    #: start-order testing: shuffle the services' start order with this seed (the simulated CAN bus, being
    #: hardware, stays first) and delay each start by a random 0..``start_delay_max_s`` s
    start_seed: int | None = None
    start_delay_max_s: float = 0.0
    #: VDA 5050 interface (services/vda5050), with an embedded MQTT broker on ``mqtt_port`` unless ``mqtt_embedded``
    #: is off (then the [vda5050] broker of the config is used)
    vda5050: bool = False
    mqtt_port: int = 1883
    mqtt_embedded: bool = True

    #: several robots in one world (services/launch/fleet.py): ``robot_count`` (--robots), explicit ``robot_slots``
    #: (--robot); ``fleet`` is the resolved list (ids and start poses), empty for the single robot of ``robot_id``
    robot_count: int = 1
    robot_slots: list[RobotSlot] = field(default_factory=list)
    fleet: list[RobotSlot] = field(default_factory=list)
    #: composition: each group's services run in one process (``services.launch.container``), per robot
    compose: list[list[str]] = field(default_factory=list)
    #: in a composed process, the services of each SHARED_LOOPS tuple run on one event loop; off: each on its own
    shared_loop: bool = True

    @property
    def endpoint(self) -> str:
        return self.external_router or f"tcp/127.0.0.1:{self.zenoh_port}"

    @property
    def can_channel(self) -> str:
        return f"ws://127.0.0.1:{self.can_port}/"

    @property
    def robot_ids(self) -> list[str]:
        return [s.id for s in self.fleet] or [self.robot_id]

    def robot_run_dir(self, k: int) -> str:
        """Robot k's state folder: the run folder itself for a single robot, ``<run folder>/<id>`` in a fleet."""
        return str(Path(self.run_dir) / self.fleet[k].id) if self.fleet else self.run_dir

    def child_name(self, k: int, service: str) -> str:
        return f"{self.fleet[k].id}.{service}" if self.fleet else service

    def services(self) -> list[str]:
        names = list(SERVICES)
        if not self.sim:
            names = [s for s in names if s != "sim"]
        if self.headless:
            names = [s for s in names if s != "hmi_api"]
        if self.foxglove_port:  # opt-in: it opens a port
            names.insert(len(names) - ("hmi_api" in names), "foxglove_bridge")
        if self.vda5050:
            names.append("vda5050")
        if self.only is not None:
            names = [s for s in names if s in self.only]
        return names

    def expected_tokens(self) -> set[str]:
        """The health tokens ``zagv: ready`` waits for, named as ``HealthWatch`` names them (the simulator
        raises one per robot)."""
        if not self.fleet:
            return set(self.services())
        return {f"{rid}.{name}" for rid in self.robot_ids for name in self.services()}

    def common_args(self, k: int = 0) -> list[str]:
        args = ["--connect", self.endpoint, "--robot-id", self.robot_ids[k]]
        if self.config:
            args += ["--config", self.config]
        if self.sim:
            args += ["--use-sim-time"]
        return args

    def service_sets(self, name: str, k: int = 0) -> list[str]:
        """``--set`` overrides that wire a service (of robot k in a fleet) to this plan's ports and files."""
        sets: list[str] = []
        run_dir = self.robot_run_dir(k)
        can_channel = f"ws://127.0.0.1:{self.can_port + k}/"
        if name == "sim":
            sets += [f"sim.can_channel={_toml_str(self.can_channel)}", f"sim.lidar_port={self.lidar_port}",
                     f"sim.speed_factor={self.speed}"]
            sets += [f"sim.map_yaml={_toml_str(self.map_yaml)}"] if self.map_yaml else \
                [f"sim.world={_toml_str(self.world)}"]
            if self.fleet:
                n = len(self.fleet)
                sets += ["sim.robots=" + sim_robots_toml(self.fleet, [f"ws://127.0.0.1:{self.can_port + i}/"
                                                                      for i in range(n)],
                                                         [self.lidar_port + i for i in range(n)])]
        elif name == "drive":
            if self.sim:
                sets += ["drive.can_interface=\"remote\"", f"drive.can_channel={_toml_str(can_channel)}"]
            if "safety" not in self.services():  # a subset without the collision monitor (benches, tests)
                sets += ["drive.command_source=\"cmd_vel\""]
        elif name == "lidar" and self.sim:
            sets += ["lidar.host=\"127.0.0.1\"", f"lidar.port={self.lidar_port + k}"]
        elif name == "localization":
            map_yaml = self.map_yaml or (str(Path(self.run_dir) / "world.yaml") if self.sim else None)
            if map_yaml:
                sets += [f"localization.map_yaml={_toml_str(map_yaml)}"]
            sets += [f"localization.state_dir={_toml_str(run_dir)}"]
            if self.mapping:
                sets += ["localization.mode=\"mapping\""]
            start = self.fleet[k].start if self.fleet else None
            if start is not None:  # each robot of a fleet starts where the simulator put it
                sets += [f"localization.initial_pose_x={start[0]!r}", f"localization.initial_pose_y={start[1]!r}",
                         f"localization.initial_pose_yaw={start[2]!r}"]
        elif name == "recorder":
            sets += [f"recorder.state_dir={_toml_str(run_dir)}"]
        elif name == "foxglove_bridge":
            sets += [f"foxglove.port={self.foxglove_port + k}"]
        elif name == "hmi_api":
            sets += [f"hmi_api.port={self.http_port + k}", f"hmi_api.state_dir={_toml_str(run_dir)}"]
        elif name == "vda5050":
            if self.mqtt_embedded:
                sets += ["vda5050.broker_host=\"127.0.0.1\"", f"vda5050.broker_port={self.mqtt_port}"]
            if self.fleet:  # one broker, one topic tree per robot: {interface}/{major}/{manufacturer}/<robot id>/...
                sets += [f"vda5050.serial_number={_toml_str(self.fleet[k].id)}"]
        prefix = f"{name}."
        sets += [s for s in self.extra_sets if s.startswith(prefix)]
        return [a for s in sets for a in ("--set", s)]

    def composed_groups(self) -> list[list[str]]:
        """The ``compose`` groups cut to the services this plan starts; a group left with one service is dropped
        (that service runs on its own)."""
        started = self.services()
        groups = [[s for s in group if s in started] for group in self.compose]
        return [g for g in groups if len(g) > 1]

    def children(self) -> list[ChildSpec]:
        env = {"PYTHONPATH": os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")]))}
        specs = []
        robots = range(len(self.robot_ids))
        if self.sim:
            for k in robots:
                specs.append(ChildSpec(self.child_name(k, "canbus"),
                                       python_module("services.sim.canbus", "--port", str(self.can_port + k)), env=env))
        if "vda5050" in self.services() and self.mqtt_embedded:
            specs.append(ChildSpec("mqtt", python_module("services.vda5050.broker", "--port", str(self.mqtt_port)),
                                   env=env))
        groups = self.composed_groups()
        group_of = {name: group for group in groups for name in group}
        for name in self.services():
            if name == "sim":  # one simulator for every robot: one world, one clock
                specs.append(ChildSpec(name, python_module("services.sim", *self.common_args(0),
                                                           *self.service_sets(name, 0)), env=env))
                continue
            if name in group_of:
                group = group_of[name]
                if name == group[0]:  # the container starts where its first service would have
                    for k in robots:
                        argv = [a for member in group for a in
                                (SEPARATOR, member, *self.common_args(k), *self.service_sets(member, k))]
                        child = self.child_name(k, container_name(groups.index(group)))
                        loop_args = shared_loop_args(group) if self.shared_loop else []
                        specs.append(ChildSpec(child, python_module("services.launch.container", "--name", child,
                                                                    *loop_args, *argv[1:]), env=env))
                continue
            for k in robots:
                argv = python_module(f"services.{name}", *self.common_args(k), *self.service_sets(name, k))
                extra = {key: os.environ.get(key, value) for key, value in SERVICE_ENV.get(name, {}).items()}
                specs.append(ChildSpec(self.child_name(k, name), argv, env={**env, **extra}))
        return specs


#: ``zagv up --compose`` without a list: every service but the drive in one process. The drive keeps a process of
#: its own: its control loop and CAN link should not wait for another service's step under the shared GIL.
DEFAULT_COMPOSITION = ["lidar", "safety", "localization", "nav", "recorder", "hmi_api", "foxglove_bridge", "vda5050"]


#: the services that share an event loop in a composed process (``--shared-loop``), one loop per tuple: their steps
#: may wait for one another's. The path from a scan to a stop (the lidar and the collision monitor, short steps
#: only) never waits for localization, nav or the interfaces (a localization update takes a few ms, a relocalization
#: more); a service composed with none of its tuple keeps a loop of its own.
SHARED_LOOPS = (("lidar", "safety"), ("localization", "nav", "recorder", "hmi_api", "foxglove_bridge", "vda5050"))


def shared_loop_args(group: list[str]) -> list[str]:
    """The container's ``--shared-loop`` arguments for a composed ``group``: one per SHARED_LOOPS tuple of which the
    group holds two services or more."""
    args: list[str] = []
    for names in SHARED_LOOPS:
        shared = [s for s in group if s in names]
        if len(shared) > 1:
            args += ["--shared-loop", ",".join(shared)]
    return args


def container_name(index: int) -> str:
    """The supervisor's name for the ``index``-th composed process: ``components``, ``components-2``, ..."""
    return "components" if index == 0 else f"components-{index + 1}"


def parse_compose(values: list[str] | None) -> list[list[str]]:
    """``--compose`` values as groups: ``default`` is DEFAULT_COMPOSITION, otherwise comma-separated service names;
    ValueError names a service that cannot be composed or one given in two groups."""
    composable = set(COMPOSABLE)
    groups: list[list[str]] = []
    seen: set[str] = set()
    for value in values or []:
        group = list(DEFAULT_COMPOSITION) if value == "default" else [s.strip() for s in value.split(",") if s.strip()]
        for name in group:
            if name not in composable:
                raise ValueError(f"--compose: {name!r} cannot run in a container "
                                 f"(composable: {', '.join(sorted(composable))})")
            if name in seen:
                raise ValueError(f"--compose: {name} is in two groups")
            seen.add(name)
        groups.append(group)
    return groups


#: per-service environment, as the systemd units set it (the caller's own value wins). hmi_api: glibc keeps at most
#: 2 malloc arenas instead of 8 per core for its threads, 108-109 MB resident in every run against up to 129 without
#: (zagv bench stack, docs/performance.md); the same setting took nav from 127 to 145 MB, so it is not set for others.
SERVICE_ENV: dict[str, dict[str, str]] = {"hmi_api": {"MALLOC_ARENA_MAX": "2"}}


def _toml_str(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def render_world_map(plan: StackPlan) -> None:
    """Have the simulator write its world's map (YAML + PGM) into the run folder for localization."""
    if not plan.sim or plan.map_yaml:
        return
    import subprocess

    subprocess.run(
        python_module("services.sim.render_map", "--world", plan.world, "--out", str(Path(plan.run_dir) / "world")),
        check=True, cwd=REPO_ROOT,
    )


def resolve_fleet(plan: StackPlan) -> None:
    """Fill ``plan.fleet`` (ids and start poses) when several robots are asked for: ``--robots N``, ``--robot``,
    or a built-in world with ``[[robots]]``. A single robot leaves the plan as it is."""
    if not plan.sim:
        if plan.robot_count > 1 or plan.robot_slots:
            raise ValueError("several robots need the simulator (--sim)")
        return
    from_world = world_robots(plan.world, plan.map_yaml)
    if plan.robot_count <= 1 and not plan.robot_slots and not from_world:
        return
    if plan.vda5050 and any(s.startswith("vda5050.serial_number=") for s in plan.extra_sets):
        raise ValueError("several robots cannot share one VDA 5050 serialNumber: in a fleet each robot's is its id "
                         "(drop --set vda5050.serial_number)")
    count = max(plan.robot_count, len(plan.robot_slots) or len(from_world))
    slots = fleet_slots(count, plan.robot_slots, from_world)
    plan.fleet = resolve_starts(slots, plan.world, plan.map_yaml, _chassis_radius_m(plan.config))


def _chassis_radius_m(config: str | None) -> float:
    from services.common.robot import RobotSpec

    radius = RobotSpec().chassis_radius_m
    if config:
        import tomllib

        with open(config, "rb") as f:
            data = tomllib.load(f)
        radius = float(data.get("robot", {}).get("chassis_radius_m", radius))
        radius = float(data.get("sim", {}).get("footprint_radius_m", 0.0)) or radius
    return radius


class HealthWatch:
    """Tracks liveliness tokens under ``agv/<id>/@health/*`` (thread-safe set); with ``fleet``, every robot's
    (``agv/*/@health/*``), named ``<id>.<service>``."""

    def __init__(self, session: zenoh.Session, keys: Keys, on_change, fleet: bool = False) -> None:
        self.alive: set[str] = set()
        self._on_change = on_change
        self._fleet = fleet
        key = keys.health_all.replace(f"/{keys.robot_id}/", "/*/", 1) if fleet else keys.health_all
        self._sub = session.liveliness().declare_subscriber(key, self._on_sample, history=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        parts = str(sample.key_expr).split("/")
        name = f"{parts[1]}.{parts[-1]}" if self._fleet else parts[-1]
        if sample.kind == zenoh.SampleKind.PUT:
            self.alive.add(name)
        else:
            self.alive.discard(name)
        self._on_change(name, sample.kind == zenoh.SampleKind.PUT)

    def close(self) -> None:
        self._sub.undeclare()


async def run_stack(plan: StackPlan, *, ready_timeout_s: float = 120.0, announce=print) -> int:
    """Run the stack until SIGINT/SIGTERM; returns the exit code."""
    loop = asyncio.get_running_loop()
    if plan.external_router:  # a client like the services: the router may stop and come back
        router = open_session(ZenohSettings(mode="client", connect=[plan.endpoint]))
    else:
        router = open_session(router_settings([plan.endpoint]))
    try:
        await loop.run_in_executor(None, resolve_fleet, plan)
    except (ValueError, OSError) as exc:
        announce(f"zagv: cannot start the robots: {exc}")
        router.close()
        return 2
    keys = Keys(plan.robot_ids[0])
    ready_timeout_s *= max(1, len(plan.fleet))  # every robot's stack starts on the same machine
    expected = plan.expected_tokens()
    ready = asyncio.Event()
    stop = asyncio.Event()
    was_ready = False

    def on_change(name: str, up: bool) -> None:
        def update() -> None:
            nonlocal was_ready
            if expected <= watch.alive and not ready.is_set():
                ready.set()
            if was_ready and name in expected and not stop.is_set():
                announce(f"zagv: {name} {'healthy again' if up else 'lost its health token'}")
        loop.call_soon_threadsafe(update)

    watch = HealthWatch(router, keys, on_change, fleet=bool(plan.fleet))
    supervisor = Supervisor()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    code = 0
    try:
        where = "external router at" if plan.external_router else "router on"
        if plan.fleet:
            robots = ", ".join(f"{r.id} at ({', '.join(f'{v:.2f}' for v in r.start or ())})" for r in plan.fleet)
            announce(f"zagv: {where} {plan.endpoint}, {len(plan.fleet)} robots: {robots}; run folder {plan.run_dir}")
        else:
            announce(f"zagv: {where} {plan.endpoint}, robot {plan.robot_id}, run folder {plan.run_dir}")
        await loop.run_in_executor(None, render_world_map, plan)
        await start_children(plan, supervisor, stop, announce)
        started = time.monotonic()
        if expected <= watch.alive:  # nothing to wait for (or every token already up)
            ready.set()
        waiter = loop.create_task(ready.wait())
        stopper = loop.create_task(stop.wait())
        await asyncio.wait({waiter, stopper}, timeout=ready_timeout_s, return_when=asyncio.FIRST_COMPLETED)
        if ready.is_set():
            was_ready = True
            announce(f"zagv: ready ({', '.join(sorted(expected))} healthy in {time.monotonic() - started:.1f} s)")
            if "hmi_api" in plan.services():
                for k, rid in enumerate(plan.robot_ids):
                    who = f" of {rid}" if plan.fleet else ""
                    announce(f"zagv: HMI{who} at http://127.0.0.1:{plan.http_port + k}/")
        elif not stop.is_set():
            missing = sorted(expected - watch.alive)
            announce(f"zagv: not ready after {ready_timeout_s:.0f} s; missing: {', '.join(missing)}")
            code = 1
        if code == 0:
            await stopper
        waiter.cancel()
        stopper.cancel()
    finally:
        stop.set()
        announce("zagv: stopping")
        await supervisor.stop()
        watch.close()
        router.close()
    return code


async def start_children(plan: StackPlan, supervisor: Supervisor, stop: asyncio.Event, announce) -> None:
    """Start every child, in the plan's order or (``start_seed``) in a random order with random delays."""
    specs = plan.children()
    if plan.start_seed is None:
        for spec in specs:
            supervisor.add(spec)
        return
    rng = random.Random(plan.start_seed)
    hardware = [s for s in specs if s.name.endswith("canbus")]
    services = [s for s in specs if not s.name.endswith("canbus")]
    rng.shuffle(services)
    delays = [rng.uniform(0.0, plan.start_delay_max_s) for _ in services]
    announce("zagv: start order " + ", ".join(f"{s.name} +{d:.1f} s" for s, d in zip(services, delays)))
    for spec in hardware:
        supervisor.add(spec)
    for spec, delay in zip(services, delays):
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), delay)  # wall time: process start-up, not robot time
        if stop.is_set():
            return
        supervisor.add(spec)
    announce(f"zagv: every service started ({services[-1].name} last)" if services else "zagv: nothing to start")


def plan_from_args(args: argparse.Namespace) -> StackPlan:
    run_dir = args.run_dir or tempfile.mkdtemp(prefix="zagv-run-")
    Path(run_dir).mkdir(parents=True, exist_ok=True)
    return StackPlan(
        robot_id=args.robot_id, sim=args.sim, world=args.world, map_yaml=args.map_yaml, config=args.config,
        speed=args.speed, headless=args.headless, mapping=args.mapping, zenoh_port=args.zenoh_port,
        can_port=args.can_port, lidar_port=args.lidar_port, http_port=args.http_port, run_dir=run_dir,
        extra_sets=args.set, only=args.only.split(",") if args.only else None,
        external_router=getattr(args, "external_router", None), foxglove_port=getattr(args, "foxglove_port", 0),
        start_seed=getattr(args, "start_seed", None), start_delay_max_s=getattr(args, "start_delay_max", 0.0),
        vda5050=getattr(args, "vda5050", False), mqtt_port=getattr(args, "mqtt_port", 1883),
        mqtt_embedded=not getattr(args, "no_embedded_broker", False),
        robot_count=getattr(args, "robots", 1), robot_slots=[parse_robot_arg(r) for r in getattr(args, "robot", [])],
        compose=compose_from_args(args), shared_loop=not getattr(args, "isolated_loops", False),
    )


def compose_from_args(args: argparse.Namespace) -> list[list[str]]:
    """The composition groups of ``--compose``/``--no-compose``: DEFAULT_COMPOSITION when neither is given (as Nav2's
    bringup composes its servers by default); ValueError when both are."""
    groups: list[str] | None = getattr(args, "compose", None)
    if getattr(args, "no_compose", False):
        if groups:
            raise ValueError("--compose and --no-compose together")
        return []
    return parse_compose(groups or ["default"])


def run(args: argparse.Namespace) -> int:
    die_with_parent()  # started by a tool's Stack (scenario, bench, tests): stop when that tool dies
    try:
        plan = plan_from_args(args)
    except ValueError as exc:
        print(f"zagv up: {exc}", file=sys.stderr)
        return 2
    with contextlib.suppress(KeyboardInterrupt):
        return asyncio.run(run_stack(plan, announce=print_line))
    return 130

