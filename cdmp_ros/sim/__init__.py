"""cdmp_ros.sim."""
