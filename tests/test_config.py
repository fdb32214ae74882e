"""Config files: an unknown or mistyped key fails at start with a message naming it."""

from __future__ import annotations

import msgspec
import pytest

from services.common.config import ConfigError, check_sections, convert_section, read_toml
from services.common.robot import RobotSpec
from services.common.settings import ZenohSettings


class Demo(msgspec.Struct, forbid_unknown_fields=True):
    rate_hz: float = 100.0
    name: str = "x"


def test_unknown_key_is_named():
    with pytest.raises(ConfigError, match=r"\[demo\].*rat_hz"):
        convert_section({"demo": {"rat_hz": 5}}, "demo", Demo, "config robot.toml")


def test_mistyped_value_is_named():
    with pytest.raises(ConfigError, match=r"\[demo.rate_hz\] Expected `float`, got `str`"):
        convert_section({"demo": {"rate_hz": "fast"}}, "demo", Demo)


def test_an_out_of_range_value_is_named():
    from services.nav.config import NavConfig

    with pytest.raises(ConfigError, match=r"nav.cost_weight must be a finite number >= 0, got -1.0"):
        convert_section({"nav": {"cost_weight": -1.0}}, "nav", NavConfig)


def test_unknown_table_is_named():
    with pytest.raises(ConfigError, match="lidra"):
        check_sections({"lidra": {}})


def test_syntax_error_and_missing_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[robot\n")
    with pytest.raises(ConfigError, match="TOML syntax error"):
        read_toml(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        read_toml(tmp_path / "missing.toml")


def test_defaults_and_clamp():
    robot = convert_section({}, "robot", RobotSpec)
    assert robot.chassis_radius_m == 0.63 and len(robot.modules) == 2
    assert robot.twist_limits().clamp(1.0, -1.0, float("nan")) == (0.2, -0.2, 0.0)
    assert robot.twist_limits().clamp(float("inf"), 0.1, -9.0) == (0.0, 0.1, -0.5)
    assert convert_section({}, "zenoh", ZenohSettings).connect == ["tcp/127.0.0.1:7447"]


def test_service_refuses_bad_config_at_start(tmp_path):
    cfg = tmp_path / "robot.toml"
    cfg.write_text("[robot]\nchassis_radius = 0.5\n")
    from services.common.service import load_config, parse_args

    with pytest.raises(ConfigError, match="chassis_radius"):
        load_config("demo", {}, parse_args("demo", ["--config", str(cfg)]))
    with pytest.raises(ConfigError, match="TABLE.KEY=VALUE"):
        load_config("demo", {}, parse_args("demo", ["--set", "nodot"]))
    robot, zs, clock, tables = load_config("drive", {"drive": Demo}, parse_args(
        "drive", ["--set", "drive.rate_hz=50", "--set", "drive.name=abc", "--use-sim-time", "--robot-id", "r9"]))
    assert tables["drive"] == Demo(rate_hz=50.0, name="abc") and clock.use_sim_time and robot.robot_id == "r9"


def test_check_config_exits_with_the_reason(tmp_path):
    cfg = tmp_path / "robot.toml"
    cfg.write_text('[zenoh]\nmode = "satellite"\n')
    from services.common.service import service_main

    async def never(ctx):  # pragma: no cover - must not run
        raise AssertionError("service ran with a bad config")

    with pytest.raises(SystemExit) as info:
        service_main("drive", {}, never, ["--config", str(cfg)])
    assert info.value.code == 2


def test_set_reaches_nested_tables():
    from services.common.service import load_config, parse_args
    from services.nav.config import NavConfig

    _, _, _, tables = load_config("nav", {"nav": NavConfig}, parse_args(
        "nav", ["--set", "nav.dwa.vx_samples=7", "--set", "nav.global_costmap.update_frequency_hz=0.5",
                "--set", "nav.planner_frequency_hz=2.0"]))
    nav = tables["nav"]
    assert nav.dwa.vx_samples == 7 and nav.global_costmap.update_frequency_hz == 0.5
    assert nav.planner_frequency_hz == 2.0 and nav.dwa.vy_samples == 5  # the rest keeps its defaults
    with pytest.raises(ConfigError, match="nav.planner_frequency_hz is a value"):
        load_config("nav", {"nav": NavConfig}, parse_args("nav", ["--set", "nav.planner_frequency_hz=2.0", "--set",
                                                                  "nav.planner_frequency_hz.x=1"]))
    with pytest.raises(ConfigError, match="vx_sample"):
        load_config("nav", {"nav": NavConfig}, parse_args("nav", ["--set", "nav.dwa.vx_sample=7"]))
