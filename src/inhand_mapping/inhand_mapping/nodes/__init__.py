"""The ROS nodes of the mapping graph: thin adapters from messages to the library calls."""
