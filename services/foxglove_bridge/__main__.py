"""``python -m services.foxglove_bridge``: the Foxglove WebSocket bridge service."""

from services.common.service import service_main
from services.foxglove_bridge.config import FoxgloveConfig
from services.foxglove_bridge.node import run

if __name__ == "__main__":
    service_main("foxglove_bridge", {"foxglove": FoxgloveConfig}, run)
