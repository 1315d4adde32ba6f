"""cdmp_ros.cli."""
