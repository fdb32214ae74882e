"""``python -m services.sim``: the simulator (world, swerve physics, emulated RoboteQ, LMS111 and Razor IMU).

The simulator is the clock master: ``--use-sim-time`` (which ``zagv up --sim`` gives every service) is accepted
and ignored, so the service does not subscribe to the ``clock`` it publishes itself.
"""

from services.common.service import ServiceSpec
from services.sim.node import SimConfig, run

SERVICE = ServiceSpec("sim", {"sim": SimConfig}, run, ignored_args=("--use-sim-time",))

if __name__ == "__main__":
    SERVICE.main()
