"""cdmp_ros.nodes."""
