"""``zagv scenario run|generate|suite``: the arguments; the work is in services.scenario.

``run`` executes a scenario file (services.scenario.execute), ``generate`` writes one of reachable goals on a map
(services.scenario.generate), ``suite`` runs the robustness benchmark (services.scenario.suite).
"""

from __future__ import annotations

import argparse

from services.scenario import generate


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scenario", help="run navigation scenarios in the simulator")
    ssub = p.add_subparsers(dest="scenario_command", required=True, metavar="ACTION")
    _add_run(ssub)
    _add_generate(ssub)
    _add_suite(ssub)


def _add_run(ssub: argparse._SubParsersAction) -> None:
    rp = ssub.add_parser("run", help="run a scenario file and print the error table")
    rp.add_argument("file", help="scenario TOML")
    rp.add_argument("--json", help="write the per-run results to this file")
    rp.add_argument("--maps-dir", help="folder the scenario's map path is relative to when it is not next to the "
                    "file (default: $ZAGV_MAPS_DIR)")
    rp.add_argument("--plots", help="write per-leg path and velocity plots (PNG) into this folder")
    rp.add_argument("--goal-timeout", type=float, default=900.0, help="sim seconds per goal (default %(default)s)")
    rp.add_argument("--repeats", type=int, help="override the file's repeats")
    rp.add_argument("--speed", type=float, help="override the file's sim speed factor")
    rp.add_argument("--set", action="append", default=[], metavar="SERVICE.KEY=VALUE",
                    help="config override passed to the stack (zagv up --set)")
    rp.add_argument("--run-dir", help="folder for the stack's run state and log (default: temporary)")
    rp.add_argument("--start-seed", type=int, help="start the stack's services in a random order (zagv up)")
    rp.add_argument("--start-delay-max", type=float, default=0.0, metavar="S",
                    help="with --start-seed: random 0..S s delay before each service (zagv up)")
    rp.add_argument("--no-compose", action="store_true",
                    help="every service in a process of its own (zagv up --no-compose; the default composes every "
                         "service but the drive in one process)")
    rp.add_argument("--mqtt-broker", metavar="HOST:PORT",
                    help="[vda5050] scenarios: the MQTT broker of the robots and the master (default: embedded)")
    rp.set_defaults(func=run)

def _add_generate(ssub: argparse._SubParsersAction) -> None:
    gp = ssub.add_parser("generate", help="write a scenario of reachable goals on a map or built-in world")
    gp.add_argument("map", nargs="?", help="ROS map YAML (or give --world)")
    gp.add_argument("--world", help="built-in sim world instead of a map")
    gp.add_argument("--goals", type=int, required=True, help="number of goals")
    gp.add_argument("--seed", type=int, default=1)
    gp.add_argument("--start", help="start pose x,y,theta (default: drawn from the largest drivable region)")
    gp.add_argument("--out", help="scenario TOML to write (default: <map name>_s<seed>.toml here)")
    gp.add_argument("--robot-radius", type=float, default=generate.DEFAULT_ROBOT_RADIUS_M,
                    help="m (default %(default)s)")
    gp.add_argument("--corridor-margin", type=float, default=generate.DEFAULT_CORRIDOR_MARGIN_M,
                    help="clearance beyond the radius for the connecting free space, m (default %(default)s)")
    gp.add_argument("--goal-margin", type=float, default=generate.DEFAULT_GOAL_MARGIN_M,
                    help="clearance beyond the radius at each goal, m (default %(default)s)")
    gp.add_argument("--min-leg", type=float, default=3.0, help="m between consecutive goals (default %(default)s)")
    gp.add_argument("--max-leg", type=float, default=20.0, help="m between consecutive goals (default %(default)s)")
    gp.add_argument("--speed", type=float, default=4.0, help="sim speed factor written to the file")
    gp.add_argument("--robots", type=int, default=1, help="robots (> 1: a [[robots]] scenario, ids r1..rN, --goals "
                    "each, starts and goals 2 x radius + 0.6 m apart; default %(default)s)")
    gp.set_defaults(func=run_generate)


def _add_suite(ssub: argparse._SubParsersAction) -> None:
    sp = ssub.add_parser("suite", help="the robustness benchmark: generated goals on many maps, one table")
    sp.add_argument("file", nargs="?", default="scenarios/suite.toml", help="suite TOML (default %(default)s)")
    sp.add_argument("--maps-dir", help="folder the suite's map paths are relative to")
    sp.add_argument("--only", help="comma-separated map names to run")
    sp.add_argument("--seeds", help="comma-separated seeds (override the file)")
    sp.add_argument("--goals", type=int, help="goals per seed and map (override the file)")
    sp.add_argument("--speed", type=float, help="sim speed factor (override the file)")
    sp.add_argument("--max-leg", type=float, default=20.0,
                    help="m in a straight line between consecutive goals at most (default %(default)s)")
    sp.add_argument("--goal-timeout", type=float, default=600.0, help="sim seconds per goal (default %(default)s)")
    sp.add_argument("--set", action="append", default=[], metavar="SERVICE.KEY=VALUE", help="stack config override")
    sp.add_argument("--json", help="write the rows, bench rows and every goal's result to this file")
    sp.add_argument("--run-dir", help="folder for generated scenarios and stack logs (default: temporary)")
    sp.set_defaults(func=run_suite)




def run(args: argparse.Namespace) -> int:
    from services.scenario.execute import run_file

    return run_file(args)


def run_generate(args: argparse.Namespace) -> int:
    return generate.run_generate(args)


def run_suite(args: argparse.Namespace) -> int:
    from services.scenario.suite import run_suite as suite

    return suite(args)
