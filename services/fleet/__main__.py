"""``python -m services.fleet --robot-id site``: the site's fleet view (every robot on the shared map)."""

from services.common.service import service_main
from services.fleet.config import FleetConfig
from services.fleet.node import run

if __name__ == "__main__":
    service_main("fleet", {"fleet": FleetConfig}, run)
