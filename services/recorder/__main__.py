"""``python -m services.recorder``: the black box service."""

from services.common.service import service_main
from services.recorder.config import RecorderConfig
from services.recorder.node import run

if __name__ == "__main__":
    service_main("recorder", {"recorder": RecorderConfig}, run)
