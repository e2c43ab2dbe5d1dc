"""ROS 2 nodes: translate between messages and the library."""
