"""The ROS node of the driver: a thin adapter from the driver core to messages."""
