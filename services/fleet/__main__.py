"""``python -m services.fleet --robot-id site``: the site's fleet view (every robot on the shared map)."""

from __future__ import annotations

from services.common.service import ServiceContext, service_main
from services.fleet.config import FleetConfig


async def run(ctx: ServiceContext) -> None:
    from services.fleet.node import run as run_node

    await run_node(ctx)


def main() -> None:
    service_main("fleet", {"fleet": FleetConfig}, run)


if __name__ == "__main__":
    main()
