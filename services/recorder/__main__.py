"""``python -m services.recorder``: the black box service."""

from services.common.service import ServiceSpec
from services.recorder.config import RecorderConfig
from services.recorder.node import run

SERVICE = ServiceSpec("recorder", {"recorder": RecorderConfig}, run)

if __name__ == "__main__":
    SERVICE.main()
