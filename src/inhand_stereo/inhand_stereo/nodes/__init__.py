"""The ROS node of the stereo pipeline: a thin adapter from messages to the library calls."""
