"""``zagv install-units``: the arguments; rendering the systemd units is services.launch.install_units."""

from __future__ import annotations

import argparse

from services.launch import install_units


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("install-units", help="render the systemd units (router, services, zagv.target)",
                       description="Render deploy/systemd/*.in for this robot and write the units to --dest.")
    p.add_argument("--venv", required=True, help="the virtualenv zagv is installed in (absolute path)")
    p.add_argument("--user", required=True, help="the dedicated system user the services run as")
    p.add_argument("--dest", default=install_units.DEFAULT_DEST, help="where to write the units (default %(default)s)")
    p.add_argument("--site", action="store_true",
                   help="the site server's units (site router, fleet view, zagv-site.target; deploy/site.md)")
    p.add_argument("--config", help=f"robot TOML file (default {install_units.DEFAULT_CONFIG}; with --site "
                                    f"{install_units.DEFAULT_SITE_CONFIG})")
    p.add_argument("--can-interface", default="can0", help="CAN interface of the drive (default %(default)s)")
    p.add_argument("--router", choices=["zenohd", "zagv"],
                   help="router program (default: zenohd when on PATH, else zagv router)")
    p.add_argument("--zenoh-config", help=f"router json5 config (default {install_units.DEFAULT_ZENOH_CONFIG}; "
                                          f"with --site {install_units.DEFAULT_SITE_ZENOH_CONFIG}; see deploy/zenoh/)")
    p.add_argument("--drive-cpu", type=int, default=1, help="CPU the drive is pinned to (default %(default)s)")
    p.add_argument("--drive-rt-priority", type=int, default=install_units.DEFAULT_DRIVE_RT_PRIORITY,
                   help="SCHED_FIFO priority of the drive (default %(default)s)")
    p.add_argument("--cpu-poll", action=argparse.BooleanOptionalAction, default=True,
                   help="while the drive runs, idle CPUs poll instead of sleeping, so that no command waits for a "
                        "CPU to wake (the PM QoS resume latency of every CPU set to n/a; costs power). The "
                        "default; --no-cpu-poll leaves the CPUs' idle states alone")
    p.add_argument("--compose", action=argparse.BooleanOptionalAction, default=True,
                   help=f"run {', '.join(install_units.COMPOSED)} in one process, zagv-components.service "
                        "(composition: less memory and CPU; a crash restarts them together). The default; "
                        "--no-compose gives each its own unit")
    p.add_argument("--templates", help="folder of the *.in templates (default: deploy/systemd of this checkout)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    return install_units.run(args)
