"""``zagv install-units``: render the systemd units of ``deploy/systemd/`` for one robot (or, with ``--site``,
for the site server: its router and the fleet view, deploy/site.md).

Templates are ``deploy/systemd/*.in`` with ``@@NAME@@`` placeholders (``$`` and ``%`` stay systemd's own). The
rendered files go to ``--dest`` (default /etc/systemd/system); then ``systemctl daemon-reload`` and
``systemctl enable --now zagv.target`` start the router and every service.
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

#: the services that get a unit, in start order after the router
SERVICES = ["drive", "lidar", "safety", "localization", "nav", "recorder", "hmi_api", "vda5050"]
#: composed (the default; ``--no-compose`` gives each a unit): these run in one unit, ``zagv-components.service``
#: (the others need the LAN or a real-time CPU)
COMPOSED = ["safety", "localization", "nav", "recorder"]
DEFAULT_DEST = "/etc/systemd/system"
DEFAULT_CONFIG = "/etc/zagv/robot.toml"
DEFAULT_ZENOH_CONFIG = "/etc/zagv/zenoh/router-loopback.json5"
DEFAULT_SITE_CONFIG = "/etc/zagv/site.toml"
DEFAULT_SITE_ZENOH_CONFIG = "/etc/zagv/zenoh/site-router-tls.json5"
#: a SCHED_FIFO priority below the kernel's threaded IRQ handlers (50)
DEFAULT_DRIVE_RT_PRIORITY = 40
ROUTER_WATCHDOG_S = 10
PLACEHOLDER = re.compile(r"@@([A-Z_]+)@@")
#: a systemd network interface name: what may follow sys-subsystem-net-devices- unescaped
INTERFACE_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.:]{0,14}$")
#: paths that ProtectHome=yes hides from the services
HIDDEN_BY_PROTECT_HOME = ("/home", "/root", "/run/user")


class InstallError(Exception):
    """A bad option or a missing template: the message says which."""


@dataclass(frozen=True)
class UnitOptions:
    venv: Path
    user: str
    config: str = DEFAULT_CONFIG
    can_interface: str = "can0"
    router: str = "zagv"  # "zagv" (zagv router) or "zenohd"
    zenohd: str = ""  # path of zenohd when router == "zenohd"
    zenoh_config: str = DEFAULT_ZENOH_CONFIG
    drive_cpu: int = 1
    drive_rt_priority: int = DEFAULT_DRIVE_RT_PRIORITY
    #: the site server's units instead of a robot's
    site: bool = False
    #: ``COMPOSED`` in one unit (zagv-components.service) instead of one unit each
    compose: bool = True
    #: idle CPUs poll while the drive runs (every CPU's PM QoS resume latency n/a, back to 0 when it stops)
    cpu_poll: bool = True

    @property
    def python(self) -> Path:
        return self.venv / "bin" / "python"


def default_templates_dir() -> Path:
    """``deploy/systemd`` of the checkout this module belongs to."""
    return Path(__file__).resolve().parents[2] / "deploy" / "systemd"


def unit_names(site: bool = False, compose: bool = True) -> list[str]:
    """Every unit rendered: the router, one per service (with ``compose``: ``COMPOSED`` as one
    zagv-components.service), and the target (a site: its router, the fleet view and zagv-site.target)."""
    if site:
        return ["zagv-site-router.service", "zagv-fleet.service", "zagv-site.target"]
    services = [f"zagv-{name}.service" for name in SERVICES if not (compose and name in COMPOSED)]
    if compose:
        services.insert(1, "zagv-components.service")  # after the drive, where safety started
    return ["zagv-router.service", *services, "zagv.target"]


def check_options(opts: UnitOptions) -> list[str]:
    """Raise InstallError for options that cannot work; return warnings for ones that probably will not."""
    warnings: list[str] = []
    if not opts.venv.is_absolute():
        raise InstallError(f"--venv {opts.venv}: must be an absolute path (systemd runs it from /)")
    if not opts.user or not re.fullmatch(r"[a-z_][a-z0-9_-]*[$]?", opts.user) or opts.user == "root":
        raise InstallError(f"--user {opts.user!r}: a dedicated, unprivileged system user name (not root)")
    if not opts.config.startswith("/") or any(c.isspace() for c in opts.config):
        raise InstallError(f"--config {opts.config!r}: an absolute path without spaces")
    if not opts.zenoh_config.startswith("/") or any(c.isspace() for c in opts.zenoh_config):
        raise InstallError(f"--zenoh-config {opts.zenoh_config!r}: an absolute path without spaces")
    if not INTERFACE_NAME.match(opts.can_interface):
        raise InstallError(f"--can-interface {opts.can_interface!r}: a network interface name such as can0")
    if opts.router not in ("zagv", "zenohd"):
        raise InstallError(f"--router {opts.router!r}: zenohd or zagv")
    if opts.router == "zenohd" and not opts.zenohd:
        raise InstallError("--router zenohd: zenohd is not on PATH (install it or use --router zagv)")
    if opts.drive_cpu < 0:
        raise InstallError(f"--drive-cpu {opts.drive_cpu}: a CPU index >= 0")
    if not 1 <= opts.drive_rt_priority <= 99:
        raise InstallError(f"--drive-rt-priority {opts.drive_rt_priority}: a SCHED_FIFO priority in 1..99")
    if any(c.isspace() for c in str(opts.venv)):
        raise InstallError(f"--venv {opts.venv}: a path without spaces")
    if not opts.python.exists():
        warnings.append(f"{opts.python} does not exist (yet): the services will not start without it")
    venv = str(opts.venv)
    if any(venv == p or venv.startswith(p + "/") for p in HIDDEN_BY_PROTECT_HOME):
        warnings.append(f"{opts.venv} is under a home folder, which ProtectHome=yes hides from the services: "
                        "install the venv elsewhere, e.g. /opt/zagv/venv")
    return warnings


#: every CPU's PM QoS resume latency (sysfs): ``n/a`` = no idle state may add wake-up latency, 0 = no constraint
CPU_RESUME_LATENCY_GLOB = "/sys/devices/system/cpu/cpu[0-9]*/power/pm_qos_resume_latency_us"


def cpu_poll_lines(cpu_poll: bool) -> str:
    """The drive unit's lines that keep idle CPUs polling while it runs. ``+`` runs them with full privileges (the
    service itself has none), ``-`` lets the drive start on a kernel without the files; ``$$`` is systemd's literal $.
    """
    if not cpu_poll:
        return "# idle CPUs sleep as usual while the drive runs (install-units --no-cpu-poll)"
    def loop(value: str) -> str:
        return f"/bin/sh -c 'for f in {CPU_RESUME_LATENCY_GLOB}; do echo {value} > \"$$f\"; done'"
    return ("# while the drive runs, idle CPUs poll instead of sleeping: a command never waits for a CPU to leave\n"
            "# a deep idle state (0.1 ms typical, milliseconds in the tail); it costs power (--no-cpu-poll: off)\n"
            f"ExecStartPre=-+{loop('n/a')}\n"
            f"ExecStopPost=-+{loop('0')}")


def substitutions(opts: UnitOptions) -> dict[str, str]:
    if opts.router == "zenohd":
        router_exec = f"{opts.zenohd} -c {opts.zenoh_config}"
        router_type = "exec"
        router_watchdog = "# zenohd does not notify systemd: no watchdog, started once exec() succeeded"
    else:
        router_exec = f"{opts.python} -m services.cli router --config {opts.zenoh_config}"
        router_type = "notify"
        router_watchdog = f"NotifyAccess=main\nWatchdogSec={ROUTER_WATCHDOG_S}s"
    return {
        "PYTHON": str(opts.python),
        "USER": opts.user,
        "CONFIG": opts.config,
        "CAN_INTERFACE": opts.can_interface,
        "DRIVE_CPU": str(opts.drive_cpu),
        "DRIVE_RT_PRIORITY": str(opts.drive_rt_priority),
        "CPU_POLL": cpu_poll_lines(opts.cpu_poll),
        "ROUTER_KIND": "zenohd" if opts.router == "zenohd" else "zagv router",
        "ROUTER_TYPE": router_type,
        "ROUTER_EXEC": router_exec,
        "ROUTER_WATCHDOG": router_watchdog,
        "UNITS": " ".join(n for n in unit_names(opts.site, opts.compose) if not n.endswith(".target")),
    }


def render_text(template: str, values: dict[str, str], name: str) -> str:
    """Replace every ``@@NAME@@``; an unknown placeholder is an error naming the template."""
    def replace(match: re.Match[str]) -> str:
        key = match.group(1)
        if key not in values:
            raise InstallError(f"template {name}: unknown placeholder @@{key}@@")
        return values[key]

    return PLACEHOLDER.sub(replace, template)


def render_units(opts: UnitOptions, templates: Path | None = None) -> dict[str, str]:
    """Unit file name -> rendered text for every unit of ``unit_names()``."""
    templates = templates or default_templates_dir()
    values = substitutions(opts)
    units: dict[str, str] = {}
    for name in unit_names(opts.site, opts.compose):
        path = templates / f"{name}.in"
        if not path.is_file():
            raise InstallError(f"template {path} not found (run from a zagv checkout or pass --templates DIR)")
        units[name] = render_text(path.read_text(), values, path.name)
    return units


def write_units(units: dict[str, str], dest: Path) -> list[Path]:
    dest.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in units.items():
        path = dest / name
        path.write_text(text)
        path.chmod(0o644)
        written.append(path)
    return written


def run(args: argparse.Namespace) -> int:
    zenohd = shutil.which("zenohd") or ""
    router = args.router or ("zenohd" if zenohd else "zagv")
    config = args.config or (DEFAULT_SITE_CONFIG if args.site else DEFAULT_CONFIG)
    zenoh_config = args.zenoh_config or (DEFAULT_SITE_ZENOH_CONFIG if args.site else DEFAULT_ZENOH_CONFIG)
    opts = UnitOptions(venv=Path(args.venv), user=args.user, config=config, can_interface=args.can_interface,
                       router=router, zenohd=zenohd, zenoh_config=zenoh_config, drive_cpu=args.drive_cpu,
                       drive_rt_priority=args.drive_rt_priority, site=args.site,
                       compose=args.compose, cpu_poll=args.cpu_poll)
    try:
        warnings = check_options(opts)
        units = render_units(opts, Path(args.templates) if args.templates else None)
        written = write_units(units, Path(args.dest))
    except (InstallError, OSError) as exc:
        print(f"zagv install-units: {exc}", file=sys.stderr)
        return 2
    for warning in warnings:
        print(f"zagv install-units: warning: {warning}", file=sys.stderr)
    for path in written:
        print(f"wrote {path}")
    target = "zagv-site.target" if opts.site else "zagv.target"
    print(f"router: {opts.router}; next: systemctl daemon-reload && systemctl enable --now {target}")
    return 0
