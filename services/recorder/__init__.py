"""Recording: rosbag2/MCAP bags of the robot's topics (``zagv record``, ``zagv replay``) and the black box service."""
