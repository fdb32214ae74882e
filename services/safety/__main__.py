"""``python -m services.safety``: the collision monitor between ``cmd_vel`` and the drive (``safety/cmd_vel``)."""

from __future__ import annotations

from services.common.service import ServiceContext, ServiceSpec
from services.safety.config import SafetyConfig


async def run(ctx: ServiceContext) -> None:
    from services.safety.node import run as run_node

    await run_node(ctx)


SERVICE = ServiceSpec("safety", {"safety": SafetyConfig}, run)

if __name__ == "__main__":
    SERVICE.main()
