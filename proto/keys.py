"""Key expressions: every key lives under ``agv/<robot_id>/`` (docs/architecture.md)."""

from __future__ import annotations

from dataclasses import dataclass

DEFAULT_ROBOT_ID = "r1"
ROOT = "agv"
HEALTH = "@health"


@dataclass(frozen=True)
class Keys:
    """Builds full key expressions for one robot: ``Keys("r1")("cmd_vel") == "agv/r1/cmd_vel"``."""

    robot_id: str = DEFAULT_ROBOT_ID

    def __post_init__(self) -> None:
        if not self.robot_id or any(c in self.robot_id for c in "/*$?#"):
            raise ValueError(f"robot id {self.robot_id!r} must be a non-empty key chunk without / * $ ? #")

    @property
    def prefix(self) -> str:
        return f"{ROOT}/{self.robot_id}"

    def __call__(self, name: str) -> str:
        return f"{self.prefix}/{name}"

    def health(self, service: str) -> str:
        """Liveliness token key of a service: ``agv/<id>/@health/<service>``."""
        return f"{self.prefix}/{HEALTH}/{service}"

    @property
    def health_all(self) -> str:
        return f"{self.prefix}/{HEALTH}/*"

    @property
    def everything(self) -> str:
        return f"{self.prefix}/**"


def split_key(key: str) -> tuple[str, str]:
    """Split ``agv/<id>/<name...>`` into (robot_id, name); raises ValueError for foreign keys."""
    parts = str(key).split("/", 2)
    if len(parts) < 3 or parts[0] != ROOT:
        raise ValueError(f"key {key!r} is not of the form {ROOT}/<robot_id>/<name>")
    return parts[1], parts[2]
