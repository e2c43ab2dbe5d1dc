"""Simulated in-hand exploration sessions with exact ground truth."""
