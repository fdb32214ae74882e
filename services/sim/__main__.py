"""``python -m services.sim``: the simulator (world, swerve physics, emulated RoboteQ, LMS111 and Razor IMU).

The simulator is the clock master: ``--use-sim-time`` (which ``zagv up --sim`` gives every service) is accepted
and ignored, so the service does not subscribe to the ``clock`` it publishes itself.
"""

import sys

from services.common.service import service_main
from services.sim.node import SimConfig, run

if __name__ == "__main__":
    service_main("sim", {"sim": SimConfig}, run, [a for a in sys.argv[1:] if a != "--use-sim-time"])
