"""``zagv up``: the arguments; starting and supervising the stack is services.launch.up."""

from __future__ import annotations

import argparse

from services.launch import up


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("up", help="start the router and every service (supervised)")
    add_stack_options(p)
    p.set_defaults(func=run)


def add_stack_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sim", action="store_true", help="simulated robot: sim, CAN bus and LMS111 emulation")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--world", default="corridor", help="built-in sim world (default %(default)s)")
    g.add_argument("--map", dest="map_yaml", help="ROS map YAML to simulate and localize on")
    p.add_argument("--config", help="robot TOML file")
    p.add_argument("--speed", type=float, default=1.0, help="sim speed factor (sim s per wall s)")
    p.add_argument("--headless", action="store_true", help="no HMI (hmi_api not started)")
    p.add_argument("--mapping", action="store_true", help="start localization in SLAM (mapping) mode")
    p.add_argument("--robot-id", default="r1", help="robot id (default %(default)s)")
    p.add_argument("--robots", type=int, default=1, metavar="N",
                   help="with --sim: N robots in the one world, ids r1..rN (or the world's [[robots]]), each a full "
                        "stack; robot k uses the CAN, LMS111, HMI and Foxglove base ports + k")
    p.add_argument("--robot", action="append", default=[], metavar="ID[:X,Y,THETA]",
                   help="with --sim: a robot of the world with its start pose (repeatable; without a pose it is "
                        "placed next to the others)")
    p.add_argument("--zenoh-port", type=int, default=7447, help="router TCP port on 127.0.0.1 (default %(default)s)")
    p.add_argument("--external-router", metavar="ENDPOINT",
                   help="connect everything to this running router (e.g. tcp/127.0.0.1:7447 of `zagv router`) "
                        "instead of embedding one; --zenoh-port is then unused")
    p.add_argument("--can-port", type=int, default=54701, help="simulated CAN bus port (default %(default)s)")
    p.add_argument("--lidar-port", type=int, default=2111, help="emulated LMS111 port (default %(default)s)")
    p.add_argument("--http-port", type=int, default=8080, help="HMI port (default %(default)s)")
    p.add_argument("--run-dir", help="folder for run state (default: a new temporary folder)")
    p.add_argument("--set", action="append", default=[], metavar="SERVICE.KEY=VALUE",
                   help="config override passed to the service it names")
    p.add_argument("--only", help="comma-separated subset of services to start")
    p.add_argument("--compose", action="append", nargs="?", const="default", metavar="SERVICE,SERVICE,...",
                   help="run these services in one process (composition, services/launch/container.py); "
                        "repeatable, one process per group. Without a list, and the default: every service but the "
                        "drive (and the simulator) in one process")
    p.add_argument("--no-compose", action="store_true",
                   help="every service in a process of its own (isolation: a crash restarts only that service)")
    p.add_argument("--isolated-loops", action="store_true",
                   help="in a composed process, run every service on an event loop of its own (by default the "
                        "lidar and safety share one, localization, nav, recorder and hmi_api another)")
    p.add_argument("--foxglove-port", type=int, default=0,
                   help="serve Foxglove (WebSocket, 127.0.0.1) on this port (default: no Foxglove bridge)")
    p.add_argument("--start-seed", type=int, help="start the services in a random order drawn with this seed "
                                                   "(start-order testing)")
    p.add_argument("--start-delay-max", type=float, default=0.0, metavar="S",
                   help="with --start-seed: delay each service's start by a random 0..S s (default %(default)s)")
    p.add_argument("--vda5050", action="store_true", help="also start the VDA 5050 interface with an embedded MQTT "
                   "broker on 127.0.0.1 (services/vda5050); with several robots one per robot, its serialNumber "
                   "the robot's id, all on the one broker")
    p.add_argument("--mqtt-port", type=int, default=1883, help="embedded MQTT broker port (default %(default)s)")
    p.add_argument("--no-embedded-broker", action="store_true",
                   help="with --vda5050: use the [vda5050] broker of the config (a site broker) instead")


def run(args: argparse.Namespace) -> int:
    return up.run(args)
