"""``python -m services.lidar``: the LMS111 CoLa A client publishing ``scan``."""

from services.common.service import ServiceSpec
from services.lidar.config import LidarConfig
from services.lidar.node import run

SERVICE = ServiceSpec("lidar", {"lidar": LidarConfig}, run)

if __name__ == "__main__":
    SERVICE.main()
