"""``python -m services.lidar``: the LMS111 CoLa A client publishing ``scan``."""

from services.common.service import service_main
from services.lidar.config import LidarConfig
from services.lidar.node import run

if __name__ == "__main__":
    service_main("lidar", {"lidar": LidarConfig}, run)
