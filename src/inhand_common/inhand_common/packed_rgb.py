"""Colours packed as PCL and RViz expect them in a point cloud's ``rgb`` field.

A float32 whose 32 bits hold 0x00RRGGBB (the PCL/RViz convention; Foxglove reads it too).
Plain numpy, no ROS: the map layouts and the stereo node share it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ['colours_of_rgb', 'pack_rgb', 'rgb_of_colours']


def pack_rgb(red: ArrayLike, green: ArrayLike, blue: ArrayLike) -> NDArray[np.float32]:
    """float32 holding packed 0x00RRGGBB: the PCL/RViz ``rgb`` field convention."""
    packed = (np.asarray(red, dtype=np.uint32) << 16) | \
        (np.asarray(green, dtype=np.uint32) << 8) | np.asarray(blue, dtype=np.uint32)
    return packed.astype(np.uint32).view(np.float32)


def rgb_of_colours(colours: ArrayLike) -> NDArray[np.float32]:
    """``pack_rgb`` of (N, 3) RGB rows."""
    rows = np.asarray(colours).reshape(-1, 3)
    return pack_rgb(rows[:, 0], rows[:, 1], rows[:, 2])


def colours_of_rgb(rgb: ArrayLike) -> NDArray[np.uint8]:
    """(N, 3) RGB rows of a packed ``rgb`` field: the inverse of :func:`rgb_of_colours`."""
    packed = np.ascontiguousarray(rgb, dtype=np.float32).reshape(-1).view(np.uint32)
    return np.stack([(packed >> shift) & 0xFF for shift in (16, 8, 0)], axis=1).astype(np.uint8)
