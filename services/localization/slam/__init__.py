"""Graph SLAM core for 2-D lidar: scan-to-map matching on a multi-resolution grid, a keyframe pose graph with
loop closures, sparse least-squares optimisation, and a log-odds occupancy grid rendered from the optimised poses.

Core modules (``se2``, ``likelihood``, ``matcher``, ``pose_graph``, ``occupancy``, ``mapper``, ``evaluation``) do no
I/O; ``logs`` reads CARMEN / ROS 1 bag files and ``map_files`` writes the ROS map_server format.
"""
