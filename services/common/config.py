"""TOML configuration decoded into msgspec Structs; an unknown or mistyped key fails naming it (docs/architecture.md).

A robot file has one table per concern: ``[robot]`` (geometry and Table 2 limits), ``[zenoh]``, and one table per
service (``[drive]``, ``[lidar]``, ``[localization]``, ``[nav]``, ``[hmi_api]``, ``[sim]``). Each service validates
the tables it reads strictly and checks that no unknown top-level table is present.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, TypeVar

import msgspec

T = TypeVar("T")

#: top-level tables a robot file may contain
KNOWN_SECTIONS = frozenset(
    {"robot", "zenoh", "clock", "liveness", "drive", "lidar", "localization", "nav", "hmi_api", "sim", "launcher",
     "vda5050", "recorder", "foxglove", "fleet"}
)


class ConfigError(ValueError):
    """A configuration file that cannot be used; the message names the file and the offending key."""


def read_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file into a dict; raises ConfigError for a missing file or a syntax error."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise ConfigError(f"config {p}: cannot read: {exc.strerror or exc}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config {p}: TOML syntax error: {exc}") from None


def convert_section(data: dict[str, Any], section: str, t: type[T], source: str = "config") -> T:
    """Validate ``data[section]`` (missing: all defaults) into ``t``.

    Errors read like ``config robot.toml: [drive] Object contains unknown field `rat_hz```, or for a wrong type
    ``[drive.rate_hz] Expected `float`, got `str```.
    """
    raw = data.get(section, {})
    try:
        return msgspec.convert(raw, t, strict=False)
    except msgspec.ValidationError as exc:
        msg = str(exc)
        where = ""
        if " - at `$" in msg:
            msg, path = msg.rsplit(" - at `$", 1)
            where = path.rstrip("`")
        raise ConfigError(f"{source}: [{section}{where}] {msg}") from None


def check_sections(data: dict[str, Any], source: str = "config") -> None:
    """Reject unknown top-level tables (typos such as ``[lidra]``)."""
    unknown = sorted(set(data) - KNOWN_SECTIONS)
    if unknown:
        raise ConfigError(
            f"{source}: unknown table(s) {', '.join(unknown)}; known: {', '.join(sorted(KNOWN_SECTIONS))}"
        )


def load_sections(path: str | Path | None, sections: dict[str, type]) -> dict[str, Any]:
    """Load ``path`` (None: defaults only) and validate each named section into its Struct type."""
    data = read_toml(path) if path else {}
    source = f"config {path}" if path else "config"
    check_sections(data, source)
    return {name: convert_section(data, name, t, source) for name, t in sections.items()}
