"""``python -m services.foxglove_bridge``: the Foxglove WebSocket bridge service."""

from services.common.service import ServiceSpec
from services.foxglove_bridge.config import FoxgloveConfig
from services.foxglove_bridge.node import run

SERVICE = ServiceSpec("foxglove_bridge", {"foxglove": FoxgloveConfig}, run)

if __name__ == "__main__":
    SERVICE.main()
