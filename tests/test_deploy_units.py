"""``zagv install-units``: the rendered systemd units carry what the deployment relies on, and systemd accepts them."""

from __future__ import annotations

import contextlib
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from services.cli.main import main
from services.launch import install_units
from services.launch.install_units import SERVICES, InstallError, UnitOptions, check_options, render_units
from tests.support.stack import free_port
from tests.support.waiting import wait_for_sync

HARDENING = {
    "NoNewPrivileges": "yes",
    "ProtectSystem": "strict",
    "ProtectHome": "yes",
    "PrivateTmp": "yes",
    "PrivateDevices": "yes",
    "CapabilityBoundingSet": "",
}


def parse_unit(text: str) -> dict[str, dict[str, list[str]]]:
    """section -> key -> every value given (systemd lets keys repeat)."""
    sections: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] | None = None
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
            continue
        assert current is not None, f"key outside a section: {line!r}"
        key, _, value = line.partition("=")
        current.setdefault(key.strip(), []).append(value.strip())
    return sections


def one(unit: dict[str, dict[str, list[str]]], section: str, key: str) -> str:
    values = unit.get(section, {}).get(key, [])
    assert len(values) == 1, f"[{section}] {key}: expected one value, got {values}"
    return values[0]


def words(unit: dict[str, dict[str, list[str]]], section: str, key: str) -> list[str]:
    return [w for value in unit.get(section, {}).get(key, []) for w in value.split()]


@pytest.fixture
def venv(tmp_path: Path) -> Path:
    """A venv-shaped folder whose bin/python is this interpreter (so ExecStart points at an executable)."""
    root = tmp_path / "venv"
    (root / "bin").mkdir(parents=True)
    (root / "bin" / "python").symlink_to(sys.executable)
    return root


@pytest.fixture
def fake_zenohd(tmp_path: Path) -> Path:
    path = tmp_path / "bin" / "zenohd"
    path.parent.mkdir()
    path.write_text("#!/bin/sh\nexit 0\n")
    path.chmod(0o755)
    return path


def options(venv: Path, **changes) -> UnitOptions:
    # one unit per service (--no-compose), so that each service's own unit is checked; the composed default has its
    # own tests below
    base: dict = dict(venv=venv, user="zagv", config="/etc/zagv/robot.toml", can_interface="can1", drive_cpu=3,
                      compose=False)
    base.update(changes)
    return UnitOptions(**base)


def rendered(opts: UnitOptions) -> dict[str, dict[str, dict[str, list[str]]]]:
    return {name: parse_unit(text) for name, text in render_units(opts).items()}


def test_every_unit_is_rendered_without_leftover_placeholders(venv: Path) -> None:
    texts = render_units(options(venv))
    assert sorted(texts) == sorted(["zagv-router.service", "zagv.target",
                                    *(f"zagv-{name}.service" for name in SERVICES)])
    for name, text in texts.items():
        assert "@@" not in text, f"{name} has an unrendered placeholder"


def test_services_notify_with_watchdog_restart_with_limits_and_follow_the_router(venv: Path) -> None:
    units = rendered(options(venv))
    for name in SERVICES:
        unit = units[f"zagv-{name}.service"]
        assert one(unit, "Service", "Type") == "notify"
        assert one(unit, "Service", "NotifyAccess") == "main"
        assert one(unit, "Service", "WatchdogSec").endswith("s")
        assert one(unit, "Service", "Restart") == "on-failure"
        assert int(one(unit, "Unit", "StartLimitBurst")) > 0
        assert one(unit, "Unit", "StartLimitIntervalSec")
        assert "zagv-router.service" in words(unit, "Unit", "After")
        assert "zagv-router.service" in words(unit, "Unit", "Wants")
        assert one(unit, "Unit", "PartOf") == "zagv.target"
        assert one(unit, "Service", "User") == "zagv"
        assert one(unit, "Service", "ExecStart").startswith(
            f"{venv}/bin/python -m services.{name} --config /etc/zagv/robot.toml")
    target = units["zagv.target"]
    assert set(words(target, "Unit", "Wants")) == {"zagv-router.service", *(f"zagv-{n}.service" for n in SERVICES)}
    assert one(target, "Install", "WantedBy") == "multi-user.target"


def test_every_service_unit_is_hardened_and_keeps_loopback(venv: Path) -> None:
    for name, unit in rendered(options(venv)).items():
        if not name.endswith(".service"):
            continue
        for key, value in HARDENING.items():
            assert one(unit, "Service", key) == value, f"{name}: {key}"
        assert one(unit, "Service", "User") == "zagv"
        assert "ReadWritePaths" not in unit["Service"], f"{name}: writes only to its StateDirectory"
        families = words(unit, "Service", "RestrictAddressFamilies")
        assert {"AF_UNIX", "AF_INET"} <= set(families), f"{name}: needs the loopback TCP to the router"
        if "IPAddressDeny" in unit["Service"]:
            assert "localhost" in words(unit, "Service", "IPAddressAllow"), f"{name}: IP filter would cut loopback"


def test_drive_runs_real_time_on_its_cpu_bound_to_the_can_interface(venv: Path) -> None:
    units = rendered(options(venv, drive_rt_priority=45))
    drive = units["zagv-drive.service"]
    assert one(drive, "Service", "CPUSchedulingPolicy") == "fifo"
    assert one(drive, "Service", "CPUSchedulingPriority") == "45"
    assert one(drive, "Service", "LimitRTPRIO") == "45"
    assert one(drive, "Service", "CPUAffinity") == "3"
    assert one(drive, "Unit", "BindsTo") == "sys-subsystem-net-devices-can1.device"
    assert "sys-subsystem-net-devices-can1.device" in words(drive, "Unit", "After")
    assert "AF_CAN" in words(drive, "Service", "RestrictAddressFamilies")
    exec_start = one(drive, "Service", "ExecStart")
    assert "--set drive.can_interface=socketcan" in exec_start and "--set drive.can_channel=can1" in exec_start
    for name in SERVICES[1:]:
        other = units[f"zagv-{name}.service"]
        assert "CPUSchedulingPolicy" not in other["Service"], f"only drive is real time, not {name}"
        assert one(other, "Service", "RestrictRealtime") == "yes"


def test_localization_and_hmi_api_keep_state_in_their_state_directory(venv: Path) -> None:
    units = rendered(options(venv))
    for name in ("localization", "hmi_api"):
        unit = units[f"zagv-{name}.service"]
        assert one(unit, "Service", "StateDirectory") == f"zagv/{name}"
        assert f"--set {name}.state_dir=${{STATE_DIRECTORY}}" in one(unit, "Service", "ExecStart")
    for name in ("drive", "lidar", "nav"):
        assert "StateDirectory" not in units[f"zagv-{name}.service"]["Service"]


def test_drive_knows_a_restart_from_its_runtime_folder(venv: Path, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    drive = rendered(options(venv))["zagv-drive.service"]
    assert one(drive, "Service", "RuntimeDirectory") == "zagv-drive"
    assert one(drive, "Service", "RuntimeDirectoryPreserve") == "restart"  # kept on restarts, removed on stop
    from services.common.lifetime import is_restart

    monkeypatch.delenv("ZAGV_START_COUNT", raising=False)
    monkeypatch.setenv("RUNTIME_DIRECTORY", str(tmp_path))
    assert not is_restart("drive")  # the first start leaves its marker
    assert is_restart("drive")  # a restart finds it
    (tmp_path / "drive.started").unlink()  # the unit was stopped: systemd removed the folder's content
    assert not is_restart("drive")


def test_router_unit_is_notify_for_zagv_router_and_exec_for_zenohd(venv: Path, fake_zenohd: Path) -> None:
    zagv = rendered(options(venv, router="zagv", zenoh_config="/etc/zagv/zenoh/router-lan-tls.json5"))
    router = zagv["zagv-router.service"]
    assert one(router, "Service", "Type") == "notify"
    assert one(router, "Service", "WatchdogSec")
    assert one(router, "Service", "ExecStart") == (
        f"{venv}/bin/python -m services.cli router --config /etc/zagv/zenoh/router-lan-tls.json5")
    zenohd = rendered(options(venv, router="zenohd", zenohd=str(fake_zenohd)))["zagv-router.service"]
    assert one(zenohd, "Service", "Type") == "exec"
    assert "WatchdogSec" not in zenohd["Service"], "zenohd sends no keep-alives"
    assert one(zenohd, "Service", "ExecStart") == f"{fake_zenohd} -c /etc/zagv/zenoh/router-loopback.json5"


@pytest.mark.parametrize("change, message", [
    ({"user": "root"}, "--user"),
    ({"can_interface": "can0; rm"}, "--can-interface"),
    ({"venv": Path("relative/venv")}, "--venv"),
    ({"config": "robot.toml"}, "--config"),
    ({"router": "zenohd", "zenohd": ""}, "zenohd"),
    ({"drive_rt_priority": 0}, "--drive-rt-priority"),
])
def test_bad_options_are_refused_with_the_option_named(venv: Path, change: dict, message: str) -> None:
    with pytest.raises(InstallError, match=message):
        check_options(options(**{"venv": venv, **change}))


def test_a_venv_under_home_gets_a_warning(tmp_path: Path) -> None:
    warnings = check_options(UnitOptions(venv=Path("/home/robot/venv"), user="zagv"))
    assert any("ProtectHome" in w for w in warnings)


def test_cli_writes_every_unit_and_names_them(venv: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(install_units.shutil, "which", lambda _name: None)  # no zenohd: falls back to zagv router
    dest = tmp_path / "units"
    code = main(["install-units", "--venv", str(venv), "--user", "zagv", "--dest", str(dest),
                 "--can-interface", "can0", "--config", "/etc/zagv/robot.toml"])
    out = capsys.readouterr().out
    assert code == 0
    # composed by default, as zagv up
    assert sorted(p.name for p in dest.iterdir()) == sorted(install_units.unit_names())
    assert "zagv-components.service" in install_units.unit_names() and "zagv-nav.service" not in out
    for name in install_units.unit_names():
        assert f"wrote {dest / name}" in out
    assert "-m services.cli router" in (dest / "zagv-router.service").read_text()
    isolated = tmp_path / "isolated"
    assert main(["install-units", "--venv", str(venv), "--user", "zagv", "--dest", str(isolated), "--no-compose"]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in isolated.iterdir()) == sorted(install_units.unit_names(compose=False))
    assert "zagv-nav.service" in install_units.unit_names(compose=False)
    assert "pm_qos_resume_latency_us" in (isolated / "zagv-drive.service").read_text()
    sleeping = tmp_path / "sleeping"
    assert main(["install-units", "--venv", str(venv), "--user", "zagv", "--dest", str(sleeping), "--no-cpu-poll"]) == 0
    capsys.readouterr()
    assert "pm_qos_resume_latency_us" not in (sleeping / "zagv-drive.service").read_text()
    assert main(["install-units", "--venv", str(venv), "--user", "root", "--dest", str(dest)]) == 2
    assert "--user" in capsys.readouterr().err


def test_drive_unit_keeps_idle_cpus_polling_while_it_runs_unless_told_not_to(venv: Path, tmp_path: Path) -> None:
    """ExecStartPre / ExecStopPost set every CPU's PM QoS resume latency to n/a and back to 0: run both scripts as
    systemd would (after its $$ -> $) on a sysfs-shaped folder of three CPUs."""
    drive = rendered(options(venv))["zagv-drive.service"]
    start, stop = one(drive, "Service", "ExecStartPre"), one(drive, "Service", "ExecStopPost")
    sysfs = tmp_path / "cpu"
    files = []
    for name in ("cpu0", "cpu1", "cpu11", "cpufreq"):
        path = sysfs / name / "power" / "pm_qos_resume_latency_us"
        path.parent.mkdir(parents=True)
        path.write_text("0\n")
        files.append(path)

    def run_as_systemd(line: str) -> None:
        assert line.startswith("-+/bin/sh -c "), line  # full privileges, a failure does not stop the drive
        script = shlex.split(line[2:])[2].replace("$$", "$").replace("/sys/devices/system/cpu/", f"{sysfs}/")
        subprocess.run(["/bin/sh", "-c", script], check=True, timeout=10)

    run_as_systemd(start)
    assert [f.read_text() for f in files] == ["n/a\n", "n/a\n", "n/a\n", "0\n"]  # every CPU, nothing else
    run_as_systemd(stop)
    assert [f.read_text() for f in files] == ["0\n"] * 4
    quiet = rendered(options(venv, cpu_poll=False))["zagv-drive.service"]
    assert "ExecStartPre" not in quiet["Service"] and "ExecStopPost" not in quiet["Service"]


def systemd_analyze_verify(unit_dir: Path) -> subprocess.CompletedProcess[str]:
    exe = shutil.which("systemd-analyze")
    if not exe:
        pytest.skip("systemd-analyze not installed: the rendered units were not checked by systemd")
    units = sorted(str(p) for p in unit_dir.iterdir())
    # SYSTEMD_LOG_LEVEL keeps warnings (unknown keys, bad values) visible; they do not change the exit code
    env = {**os.environ, "SYSTEMD_LOG_LEVEL": "notice"}
    return subprocess.run([exe, "verify", *units], capture_output=True, text=True, timeout=60, env=env)


@pytest.mark.parametrize("router", ["zagv", "zenohd"])
def test_systemd_analyze_verify_accepts_the_rendered_units(venv: Path, fake_zenohd: Path, tmp_path: Path,
                                                           router: str) -> None:
    dest = tmp_path / "units"
    install_units.write_units(render_units(options(venv, router=router, zenohd=str(fake_zenohd))), dest)
    result = systemd_analyze_verify(dest)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output
    # systemd only warns about unknown keys or unparsable values: any line about our units is a failure
    complaints = [line for line in output.splitlines() if "zagv" in line]
    assert not complaints, "\n".join(complaints)


@pytest.mark.parametrize("name", SERVICES)
def test_each_service_accepts_its_units_command_line(venv: Path, tmp_path: Path, name: str) -> None:
    """The unit's ExecStart (with the example robot file) passes the service's own --check-config."""
    repo = Path(__file__).resolve().parents[1]
    entry = repo / "services" / name / "__main__.py"
    assert entry.is_file(), f"the unit runs services.{name}, which has no entry point"
    unit = rendered(options(venv))[f"zagv-{name}.service"]
    argv = one(unit, "Service", "ExecStart").replace("${STATE_DIRECTORY}", str(tmp_path)).split()
    argv[argv.index("--config") + 1] = str(repo / "deploy" / "robot.example.toml")
    assert argv[0] == str(venv / "bin" / "python")
    argv[0] = sys.executable  # the fixture's venv is only venv-shaped; run the same command with this interpreter
    result = subprocess.run([*argv, "--check-config"], capture_output=True, text=True, timeout=120, cwd=repo,
                            env={**os.environ, "PYTHONPATH": str(repo)})
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.integration
def test_router_notifies_ready_and_keeps_the_watchdog_fed(tmp_path: Path) -> None:
    """What Type=notify + WatchdogSec in zagv-router.service rely on: READY=1, then WATCHDOG=1 every period/2."""
    repo = Path(__file__).resolve().parents[1]
    sock_dir = Path(tempfile.mkdtemp(prefix="zagv-notify-"))  # AF_UNIX paths are limited to 108 bytes
    notify_path = sock_dir / "notify"
    received: list[str] = []
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(str(notify_path))
        sock.settimeout(0.05)
        env = {**os.environ, "PYTHONPATH": str(repo), "NOTIFY_SOCKET": str(notify_path), "WATCHDOG_USEC": "400000"}
        env.pop("WATCHDOG_PID", None)
        proc = subprocess.Popen([sys.executable, "-m", "services.cli", "router", "--listen",
                                 f"tcp/127.0.0.1:{free_port()}"], cwd=repo, env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL)

        def got_ready_then_watchdog() -> bool:
            with contextlib.suppress(TimeoutError):
                received.append(sock.recv(256).decode())
            return "READY=1" in received and "WATCHDOG=1" in received[received.index("READY=1"):]

        try:
            wait_for_sync(got_ready_then_watchdog, timeout_s=30, poll_s=0.0,
                          message=f"router notifications: {received}")
        finally:
            proc.terminate()
            proc.wait(timeout=15)
    shutil.rmtree(sock_dir, ignore_errors=True)


def test_systemd_rates_every_service_unit_well_hardened(venv: Path, tmp_path: Path) -> None:
    """``systemd-analyze security --offline`` exposure (0 = locked down, 10 = unprotected) stays at 'OK' (< 3)."""
    exe = shutil.which("systemd-analyze")
    if not exe:
        pytest.skip("systemd-analyze not installed: exposure not rated")
    dest = tmp_path / "units"
    install_units.write_units(render_units(options(venv)), dest)
    for path in sorted(dest.glob("*.service")):
        result = subprocess.run([exe, "security", "--offline=true", "--no-pager", str(path)],
                                capture_output=True, text=True, timeout=60)
        if "--offline" in result.stderr and result.returncode != 0:
            pytest.skip(f"this systemd-analyze has no offline security rating: {result.stderr.strip()}")
        match = re.search(r"Overall exposure level for \S+: (\d+(?:\.\d+)?)", result.stdout)
        assert match, result.stdout[-500:] + result.stderr
        assert float(match.group(1)) < 3.0, f"{path.name}: exposure {match.group(1)}"


def test_the_site_servers_units_run_its_router_and_the_fleet_view(venv: Path, tmp_path: Path) -> None:
    """``install-units --site``: the site router and the fleet view under zagv-site.target, as hardened as a robot's
    units; systemd accepts them and the fleet's command line passes --check-config with the example site file."""
    repo = Path(__file__).resolve().parents[1]
    opts = options(venv, site=True, config="/etc/zagv/site.toml",
                   zenoh_config="/etc/zagv/zenoh/site-router-tls.json5")
    texts = render_units(opts)
    assert sorted(texts) == ["zagv-fleet.service", "zagv-site-router.service", "zagv-site.target"]
    assert all("@@" not in text for text in texts.values())
    units = {name: parse_unit(text) for name, text in texts.items()}
    assert words(units["zagv-site.target"], "Unit", "Wants") == ["zagv-site-router.service", "zagv-fleet.service"]
    router = units["zagv-site-router.service"]
    assert one(router, "Service", "ExecStart").endswith("router --config /etc/zagv/zenoh/site-router-tls.json5")
    fleet = units["zagv-fleet.service"]
    assert one(fleet, "Unit", "After") == "zagv-site-router.service"
    assert one(fleet, "Service", "StateDirectory") == "zagv/fleet"
    for unit in (router, fleet):
        assert one(unit, "Service", "NoNewPrivileges") == "yes" and one(unit, "Install", "WantedBy") == \
            "zagv-site.target"
    argv = one(fleet, "Service", "ExecStart").replace("${STATE_DIRECTORY}", str(tmp_path)).split()
    argv[argv.index("--config") + 1] = str(repo / "deploy" / "site.example.toml")
    argv[0] = sys.executable
    result = subprocess.run([*argv, "--check-config"], capture_output=True, text=True, timeout=120, cwd=repo,
                            env={**os.environ, "PYTHONPATH": str(repo)})
    assert result.returncode == 0, result.stdout + result.stderr
    dest = tmp_path / "units"
    install_units.write_units(texts, dest)
    verified = systemd_analyze_verify(dest)
    assert verified.returncode == 0, verified.stdout + verified.stderr
    assert not [line for line in (verified.stdout + verified.stderr).splitlines() if "zagv" in line]


def test_compose_runs_safety_localization_nav_and_recorder_in_one_unit(venv: Path, fake_zenohd: Path,
                                                                       tmp_path: Path) -> None:
    opts = options(venv, compose=True)
    units = rendered(opts)
    composed = [f"zagv-{n}.service" for n in install_units.COMPOSED]
    assert "zagv-components.service" in units and not set(composed) & set(units)
    assert set(words(units["zagv.target"], "Unit", "Wants")) == {
        n for n in units if n.endswith(".service")}
    unit = units["zagv-components.service"]
    for key, value in HARDENING.items():
        assert one(unit, "Service", key) == value, key
    assert one(unit, "Service", "Type") == "notify" and one(unit, "Service", "NotifyAccess") == "main"
    assert words(unit, "Service", "IPAddressAllow") == ["localhost"]
    exec_start = one(unit, "Service", "ExecStart")
    assert exec_start.startswith(f"{venv}/bin/python -m services.launch.container --name components "
                                 "--shared-loop localization,nav,recorder safety ")
    members = [exec_start.split()[i + 1] for i, w in enumerate(exec_start.split()) if w == "::"]
    assert ["safety", *members] == install_units.COMPOSED

    # the command line passes every composed service's own --check-config
    repo = Path(__file__).resolve().parents[1]
    argv = [sys.executable, *exec_start.split()[1:],
            "--check-config"]  # the last service's options; the container then checks them all
    argv = [str(repo / "deploy" / "robot.example.toml") if a == "/etc/zagv/robot.toml" else a for a in argv]
    result = subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=repo,
                            env={**os.environ, "PYTHONPATH": str(repo)})
    assert result.returncode == 0 and "config ok" in result.stdout, result.stdout + result.stderr

    dest = tmp_path / "units"
    install_units.write_units(render_units(options(venv, compose=True, router="zenohd", zenohd=str(fake_zenohd))),
                              dest)
    verify = systemd_analyze_verify(dest)
    output = verify.stdout + verify.stderr
    assert verify.returncode == 0, output
    assert not [line for line in output.splitlines() if "zagv" in line], output
