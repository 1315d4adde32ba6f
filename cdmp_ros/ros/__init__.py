"""cdmp_ros.ros."""
