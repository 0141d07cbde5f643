"""Doors that let tools of the ROS world reach the robot's graph: rosbridge v2 (and later Foxglove, MCAP)."""
