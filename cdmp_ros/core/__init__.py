"""Numerical core of cdmp_ros: numpy and scipy only, no ROS, no pybullet."""
