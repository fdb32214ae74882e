"""Fault injection against real ``zagv up`` stacks: what the robot survives, and how long each recovery takes."""
