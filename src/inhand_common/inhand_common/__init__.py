"""Shared pieces of the in-hand exploration workspace."""
