"""``python -m services.drive``: the drive service (CAN link, swerve control loop, odometry)."""

from services.common.service import ServiceSpec
from services.drive.config import DriveConfig
from services.drive.node import run

SERVICE = ServiceSpec("drive", {"drive": DriveConfig}, run)

if __name__ == "__main__":
    SERVICE.main()
