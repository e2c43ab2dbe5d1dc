"""Compiled loops of the texture of the occupied cells (numba), used only by texture.py.

Why compiled: each cell reads the 49 pixels of its footprint, and each pixel's measured
point is tested against the cell's window and against the occupied cells around it
(:func:`window_pixels`), or against the map's own depth image (:func:`map_depth`,
:func:`front_pixels`: the second rule). As numpy passes over (cells, 49, 3) temporaries
that took 150 ms for a 10,000-cell map; one pass here reads each pixel once and keeps only
the pixels that count.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from inhand_stereo.vision_kernels import _compiled, _inlined

__all__ = ['front_pixels', 'map_depth', 'window_pixels']

Floats = NDArray[np.float64]


@_inlined
def _depth_at(depth: NDArray[np.float32], row: int, col: int, fill: float
              ) -> tuple[float, int]:
    """The pixel's depth and flat index, or the depth and index of the nearest pixel with a
    depth within ``fill`` px (the first in scan order among equals: its point and its
    colour stand for this one); depth 0 where there is none (NaN, inf: no depth)."""
    height, width = depth.shape
    d = float(depth[row, col])
    if d > 0.0 and d < math.inf:
        return d, row * width + col
    reach = int(fill)
    best, best_index, best_distance = 0.0, -1, fill * fill + 1e-9
    for dr in range(-reach, reach + 1):
        r = row + dr
        if r < 0 or r >= height:
            continue
        for dc in range(-reach, reach + 1):
            c = col + dc
            distance = float(dr * dr + dc * dc)
            if c < 0 or c >= width or distance >= best_distance:
                continue
            value = float(depth[r, c])
            if value > 0.0 and value < math.inf:
                best, best_index, best_distance = value, r * width + c, distance
    return best, best_index


@_inlined
def _footprint(u: float, v: float, z: float, P: Floats, resolution: float,
               cols: NDArray[np.int64], rows: NDArray[np.int64]) -> None:
    """The columns and rows of a cell's footprint (its face seen at depth ``z``, centred on
    pixel (u, v)), sampled ``len(cols)`` times a side: pixel centres at integers (ROS)."""
    samples = len(cols)
    scale_u = P[0, 0] / z * resolution
    scale_v = P[1, 1] / z * resolution
    for b in range(samples):           # the footprint's columns, then its rows
        cols[b] = math.floor(u + ((b + 0.5) / samples - 0.5) * scale_u + 0.5)
        rows[b] = math.floor(v + ((b + 0.5) / samples - 0.5) * scale_v + 0.5)


@_compiled
def map_depth(u: Floats, v: Floats, z: Floats, P: Floats, resolution: float,
              depth: Floats) -> None:
    """The map's own depth image, in ``depth`` (H, W; +inf where no cell is seen): each
    cell (projection ``u, v, z``; z <= 0 behind the camera) covers its face's square of
    pixels at its depth, and the nearest cell wins (a z-buffer of the occupied cells)."""
    height, width = depth.shape
    depth[:, :] = math.inf
    for k in range(len(u)):
        if not z[k] > 0.0:
            continue
        half_u = P[0, 0] / z[k] * resolution / 2.0
        half_v = P[1, 1] / z[k] * resolution / 2.0
        c0 = max(0, math.floor(u[k] - half_u + 0.5))
        c1 = min(width, math.floor(u[k] + half_u + 0.5))
        r0 = max(0, math.floor(v[k] - half_v + 0.5))
        r1 = min(height, math.floor(v[k] + half_v + 0.5))
        for row in range(r0, r1):
            for col in range(c0, c1):
                if z[k] < depth[row, col]:
                    depth[row, col] = z[k]


@_inlined
def _point_offset(pixel: int, d: float, width: int, inverse: Floats, shift: Floats,
                  cx: float, cy: float, cz: float) -> tuple[float, float, float]:
    """The measured point of ``pixel`` at depth ``d`` (rectified camera frame; ``inverse``
    and ``shift`` undo ``P``) minus the cell centre ``c``."""
    pr, pc = pixel // width, pixel % width
    ox = (inverse[0, 0] * pc + inverse[0, 1] * pr + inverse[0, 2]) * d - shift[0] - cx
    oy = (inverse[1, 0] * pc + inverse[1, 1] * pr + inverse[1, 2]) * d - shift[1] - cy
    oz = (inverse[2, 0] * pc + inverse[2, 1] * pr + inverse[2, 2]) * d - shift[2] - cz
    return ox, oy, oz


@_inlined
def _in_another_cell(ox: float, oy: float, oz: float, home: int, occupied: NDArray[np.bool_],
                     strides: NDArray[np.int64], to_map: Floats, resolution: float,
                     pad: int) -> bool:
    """Whether a point ``o`` off a cell's centre (camera frame; ``to_map`` rotates to the
    map's axes) lies in another occupied cell of the lattice (``home``: the cell's flat
    index; ``pad`` free cells around every occupied one: a point farther along an axis is
    taken at that distance, which is free or the lattice's edge)."""
    offset = 0
    moved = False
    for axis in range(3):
        step = round((ox * to_map[0, axis] + oy * to_map[1, axis] + oz * to_map[2, axis])
                     / resolution)
        step = min(pad, max(-pad, step))
        if step != 0:
            moved = True
        offset += step * strides[axis]
    return bool(moved and occupied[home + offset])


@_compiled
def front_pixels(u: Floats, v: Floats, z: Floats, centres: Floats, homes: NDArray[np.int64],
                 occupied: NDArray[np.bool_], strides: NDArray[np.int64], to_map: Floats,
                 front: Floats, depth: NDArray[np.float32], P: Floats, inverse: Floats,
                 shift: Floats, resolution: float, pad: int, samples: int, ahead: float,
                 tolerance: float, behind: float, reach: float, blind: NDArray[np.bool_],
                 holes: NDArray[np.bool_], pixels: NDArray[np.int64]) -> NDArray[np.int64]:
    """For each cell (its projection ``u, v, z``): the flat indices of the pixels of its
    ``samples`` x ``samples`` footprint where it is the map's front cell (``front``, from
    :func:`map_depth`, is no nearer than ``z - ahead``) and the stereo depth there (or of
    the nearest pixel with one within ``reach`` px) lies at most ``tolerance`` in front of
    ``z`` and at most ``behind`` beyond it, its point (``centres``, ``homes``, ``occupied``,
    ``strides``, ``to_map``, ``inverse``, ``shift``, ``pad`` as for :func:`window_pixels`)
    not in another occupied cell when it is more than ``tolerance`` beyond, or,
    where ``blind[k]`` (the cell clearly faces the camera), there is no depth within
    ``reach`` and the pixel is in one of the depth's ``holes`` (H, W): written to
    ``pixels[k, :count]`` (a filled sample: the pixel that gave it its depth, as in
    :func:`window_pixels`; a blind one: its own); returns the counts (K,)."""
    height, width = depth.shape
    counts = np.zeros(len(u), dtype=np.int64)
    cols = np.empty(samples, dtype=np.int64)
    rows = np.empty(samples, dtype=np.int64)
    for k in range(len(u)):
        _footprint(u[k], v[k], z[k], P, resolution, cols, rows)
        count = 0
        for a in range(samples):
            row = rows[a]
            if row < 0 or row >= height:
                continue
            for b in range(samples):
                col = cols[b]
                if col < 0 or col >= width or front[row, col] < z[k] - ahead:
                    continue
                d, pixel = _depth_at(depth, row, col, reach)
                if d <= 0.0:
                    if not (blind[k] and holes[row, col]):
                        continue
                    pixel = row * width + col     # no depth near: the map's front, its pixel
                elif z[k] - d > tolerance or d - z[k] > behind:
                    continue
                elif d - z[k] > tolerance:
                    # farther than the cell: its own surface unless it lies in another cell
                    ox, oy, oz = _point_offset(pixel, d, width, inverse, shift, centres[k, 0],
                                               centres[k, 1], centres[k, 2])
                    if _in_another_cell(ox, oy, oz, homes[k], occupied, strides, to_map,
                                        resolution, pad):
                        continue
                pixels[k, count] = pixel      # filled: the colour that goes with that depth
                count += 1
        counts[k] = count
    return counts


@_compiled
def window_pixels(u: Floats, v: Floats, z: Floats, centres: Floats, homes: NDArray[np.int64],
                  occupied: NDArray[np.bool_], strides: NDArray[np.int64], to_map: Floats,
                  depth: NDArray[np.float32], P: Floats, inverse: Floats, shift: Floats,
                  resolution: float, pad: int, samples: int, near: float, far: float,
                  across: float, fill: float, pixels: NDArray[np.int64]) -> NDArray[np.int64]:
    """For each cell (its projection ``u, v, z``, its centre in the rectified camera frame
    ``centres`` (K, 3), its flat index ``homes`` in the lattice ``occupied`` (flat bool,
    ``strides`` per map axis, ``pad`` free cells around every occupied one)): the flat
    indices of the pixels of its ``samples`` x ``samples`` footprint whose measured point
    lies in its window, written to ``pixels[k, :count]`` (a filled sample: the pixel that
    gave it its depth, whose colour goes with that point); returns the counts (K,).

    The window, from the centre: ``near <= along <= far`` along the line of sight and at
    most ``across`` from it. A point that lies in another occupied cell (``to_map``: the
    camera -> map rotation, row vectors: ``o_map = o_camera @ to_map``) does not count. A
    pixel without depth takes the depth of the nearest pixel with one within ``fill`` px
    (stereo leaves thin gaps at edges and on weak texture)."""
    height, width = depth.shape
    counts = np.zeros(len(u), dtype=np.int64)
    across2 = across * across
    cols = np.empty(samples, dtype=np.int64)
    rows = np.empty(samples, dtype=np.int64)
    for k in range(len(u)):
        cx, cy, cz = centres[k, 0], centres[k, 1], centres[k, 2]
        norm = math.sqrt(cx * cx + cy * cy + cz * cz)
        sx, sy, sz = cx / norm, cy / norm, cz / norm
        _footprint(u[k], v[k], z[k], P, resolution, cols, rows)
        count = 0
        for a in range(samples):
            row = rows[a]
            if row < 0 or row >= height:
                continue
            for b in range(samples):
                col = cols[b]
                if col < 0 or col >= width:
                    continue
                d, pixel = _depth_at(depth, row, col, fill)
                if d <= 0.0:
                    continue
                # the measured point of the pixel that holds the depth (this one or, filled,
                # its neighbour)
                ox, oy, oz = _point_offset(pixel, d, width, inverse, shift, cx, cy, cz)
                along = ox * sx + oy * sy + oz * sz
                if along < near or along > far:
                    continue
                if ox * ox + oy * oy + oz * oz - along * along > across2:
                    continue
                if _in_another_cell(ox, oy, oz, homes[k], occupied, strides, to_map,
                                    resolution, pad):
                    continue
                pixels[k, count] = pixel
                count += 1
        counts[k] = count
    return counts
