"""What the ``zagv`` commands that talk to a running robot do (their arguments are in services/cli): topic
inspection, a goal followed to its end, the services' health, the black box save, ``zagv map`` (a map's summary and
the offline SLAM entry point run as a subprocess). Not a service; it imports no service package."""
