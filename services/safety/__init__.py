"""The safety service: a collision monitor between the velocity commands (nav, HMI jog) and the drive."""
