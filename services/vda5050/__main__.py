"""``python -m services.vda5050``: the VDA 5050 2.0 vehicle interface (MQTT to a master control)."""

from __future__ import annotations

from services.common.service import ServiceContext, ServiceSpec
from services.vda5050.config import Vda5050Config


async def run(ctx: ServiceContext) -> None:
    from services.vda5050.node import run as run_node

    await run_node(ctx)


SERVICE = ServiceSpec("vda5050", {"vda5050": Vda5050Config}, run)

if __name__ == "__main__":
    SERVICE.main()
