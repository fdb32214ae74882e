"""``python -m services.nav``: the navigation service (costmaps, A*, DWA, goals, waypoints)."""

from __future__ import annotations

from services.common.service import ServiceContext, ServiceSpec
from services.nav.config import NavConfig


async def run(ctx: ServiceContext) -> None:
    from services.nav.node import run as run_node

    await run_node(ctx)


SERVICE = ServiceSpec("nav", {"nav": NavConfig}, run)

if __name__ == "__main__":
    SERVICE.main()
