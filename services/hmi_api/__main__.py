"""``python -m services.hmi_api``: the HTTP/WebSocket API and web HMI."""

from services.common.service import service_main
from services.hmi_api.config import HmiApiConfig
from services.hmi_api.node import run

if __name__ == "__main__":
    service_main("hmi_api", {"hmi_api": HmiApiConfig}, run)
