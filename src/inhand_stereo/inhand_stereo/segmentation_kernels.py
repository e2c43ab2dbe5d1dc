"""Compiled loops of the scene segmentation (numba), used only by scene_segmentation.py and
shot_placement.py.

Why compiled: a 640x480 shot has 307,200 pixels, and each step of the segmentation (the
points back-projected into the map, their cells, the RANSAC scores of 256 planes on 4,096
points, the plane's refit) was a few numpy passes with full-size temporaries: 34 ms for
one shot, three times the 10 ms a camera at 15 Hz leaves it. Each loop here does in one
pass what those expressions did; the arithmetic is theirs (sums may be added in another
order, which moves a result by an ulp, never a point across a tolerance in practice: the
tests compare the segmentation with the numpy one on real and synthetic shots).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from inhand_stereo.vision_kernels import _compiled

__all__ = ['back_project', 'count_inliers', 'grid_points', 'nearest_per_label', 'plane_moments']

Floats = NDArray[np.float64]
Indices = NDArray[np.int64]


@_compiled
def back_project(depth: NDArray[np.float32], P: Floats, matrix: Floats, offset: Floats,
                 points: Floats) -> None:
    """``points`` (H * W, 3): each pixel's measured point in the map frame (NaN where the
    depth is missing), for a rectified camera ``P`` and ``p_camera = matrix p_map +
    offset`` (``matrix`` a rotation: ``p_map = matrix^T (p_camera - offset)``)."""
    height, width = depth.shape
    fx, cx, fy, cy = P[0, 0], P[0, 2], P[1, 1], P[1, 2]
    for v in range(height):
        ray_y = (v - cy) / fy
        for u in range(width):
            z = float(depth[v, u])
            row = v * width + u
            camera_x = (u - cx) / fx * z - offset[0]
            camera_y = ray_y * z - offset[1]
            camera_z = z - offset[2]
            for axis in range(3):
                points[row, axis] = (camera_x * matrix[0, axis] + camera_y * matrix[1, axis]
                                     + camera_z * matrix[2, axis])


@_compiled
def grid_points(points: Floats, origin: Floats, resolution: float, n: int
                ) -> tuple[Indices, Indices, Floats]:
    """(rows, cells (M, 3), the points themselves (M, 3)) of the finite points (N, 3) that
    fall in a cell of the n^3 grid at ``origin``: ``GridSpec.cell_indices`` and
    ``GridSpec.holds`` in one pass."""
    rows = np.empty(points.shape[0], dtype=np.int64)
    cells = np.empty((points.shape[0], 3), dtype=np.int64)
    inside_points = np.empty((points.shape[0], 3))
    kept = 0
    for r in range(points.shape[0]):
        # np.floor and float bounds (not math.floor, an int, and a break per axis): three
        # times as fast on a shot's points; NaN fails every comparison
        x = np.floor((points[r, 0] - origin[0]) / resolution)
        y = np.floor((points[r, 1] - origin[1]) / resolution)
        z = np.floor((points[r, 2] - origin[2]) / resolution)
        if (0.0 <= x < n) & (0.0 <= y < n) & (0.0 <= z < n):
            rows[kept] = r
            cells[kept, 0], cells[kept, 1], cells[kept, 2] = int(x), int(y), int(z)
            for axis in range(3):
                inside_points[kept, axis] = points[r, axis]
            kept += 1
    return rows[:kept], cells[:kept], inside_points[:kept]


@_compiled
def count_inliers(points: Floats, normals: Floats, offsets: Floats, tolerance: float
                  ) -> Indices:
    """For each plane (``normals`` (H, 3), ``offsets`` (H,)), how many of ``points`` (S, 3)
    lie within ``tolerance`` of it."""
    counts = np.zeros(normals.shape[0], dtype=np.int64)
    for h in range(normals.shape[0]):
        a, b, c, d = normals[h, 0], normals[h, 1], normals[h, 2], offsets[h]
        count = 0
        for s in range(points.shape[0]):
            if abs(points[s, 0] * a + points[s, 1] * b + points[s, 2] * c + d) < tolerance:
                count += 1
        counts[h] = count
    return counts


@_compiled
def plane_moments(points: Floats, normal: Floats, offset: float, tolerance: float
                  ) -> tuple[int, Floats, Floats]:
    """(count, centre (3,), scatter (3, 3)) of the points within ``tolerance`` of the plane
    ``normal . p + offset = 0``: the refit's inputs, without copying the inliers out."""
    count = 0
    centre = np.zeros(3)
    for r in range(points.shape[0]):
        x, y, z = points[r, 0], points[r, 1], points[r, 2]
        if abs(x * normal[0] + y * normal[1] + z * normal[2] + offset) < tolerance:
            count += 1
            centre[0] += x
            centre[1] += y
            centre[2] += z
    scatter = np.zeros((3, 3))
    if count == 0:
        return 0, centre, scatter
    centre /= count
    for r in range(points.shape[0]):
        x, y, z = points[r, 0], points[r, 1], points[r, 2]
        if abs(x * normal[0] + y * normal[1] + z * normal[2] + offset) < tolerance:
            dx, dy, dz = x - centre[0], y - centre[1], z - centre[2]
            scatter[0, 0] += dx * dx
            scatter[0, 1] += dx * dy
            scatter[0, 2] += dx * dz
            scatter[1, 1] += dy * dy
            scatter[1, 2] += dy * dz
            scatter[2, 2] += dz * dz
    scatter[1, 0] = scatter[0, 1]
    scatter[2, 0] = scatter[0, 2]
    scatter[2, 1] = scatter[1, 2]
    return count, centre, scatter


@_compiled
def nearest_per_label(labels: Indices, distance: Floats, count: int) -> Floats:
    """(count + 1,) the smallest ``distance`` of each label 0..count (inf: none)."""
    nearest = np.full(count + 1, np.inf)
    for r in range(labels.shape[0]):
        if distance[r] < nearest[labels[r]]:
            nearest[labels[r]] = distance[r]
    return nearest
