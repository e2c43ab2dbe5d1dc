"""Bag replay and recording, topic echo, map metrics and map renders."""
