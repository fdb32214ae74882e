"""``python -m services.fleet --robot-id site``: the site's fleet view (every robot on the shared map)."""

from services.common.service import ServiceSpec
from services.fleet.config import FleetConfig
from services.fleet.node import run

SERVICE = ServiceSpec("fleet", {"fleet": FleetConfig}, run)

if __name__ == "__main__":
    SERVICE.main()
