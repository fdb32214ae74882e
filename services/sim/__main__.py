"""``python -m services.sim``: the simulator (world, swerve physics, emulated RoboteQ, LMS111 and Razor IMU)."""

from services.common.service import service_main
from services.sim.node import SimConfig, run

if __name__ == "__main__":
    service_main("sim", {"sim": SimConfig}, run)
