"""cdmp_ros.bag."""
