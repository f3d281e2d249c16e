"""Output message definitions (JSON schema, ROS 1 and ROS 2 .msg): the one source for writers."""
