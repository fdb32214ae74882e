"""``python -m services.drive``: the drive service (CAN link, swerve control loop, odometry)."""

from services.common.service import service_main
from services.drive.config import DriveConfig
from services.drive.node import run

if __name__ == "__main__":
    service_main("drive", {"drive": DriveConfig}, run)
