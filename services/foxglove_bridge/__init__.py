"""Live view in Foxglove: the robot's topics over the Foxglove WebSocket protocol (``foxglove-sdk``)."""
