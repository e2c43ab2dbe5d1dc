"""Probabilistic volumetric maps of objects from in-hand exploration."""
