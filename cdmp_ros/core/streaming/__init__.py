"""Online streaming of the active primitive (the streamer node's logic without ROS)."""
