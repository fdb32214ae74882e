"""``python -m services.hmi_api``: the HTTP/WebSocket API and web HMI."""

from services.common.service import ServiceSpec
from services.hmi_api.config import HmiApiConfig
from services.hmi_api.node import run

SERVICE = ServiceSpec("hmi_api", {"hmi_api": HmiApiConfig}, run)

if __name__ == "__main__":
    SERVICE.main()
