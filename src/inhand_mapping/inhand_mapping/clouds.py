"""Point layouts of the clouds the mapping nodes publish (plain numpy, no ROS).

* ``registration/points``: registered fingertip positions, ``x y z`` (float32, map frame,
  m), ``finger`` (uint8, index into the registration node's ``finger_names``) and ``t``
  (float64, the measurement stamp in seconds). ``build_map`` passes its points through
  the same packing, so it integrates exactly the float32 positions the node would.
* ``occupancy/cloud`` and ``occupancy/occupied``: one point per cell, ``x y z`` (cell
  centre), ``intensity`` (occupancy probability: RViz and Foxglove colour by it), ``hits``
  (uint32: measurements whose containing cell it is) and ``first_touch`` (float32 seconds
  since the map's first measurement, NaN if never hit directly).
"""

from __future__ import annotations

import numpy as np

from inhand_mapping.occupancy import OccupancyGrid

__all__ = ['REGISTERED_DTYPE', 'MAP_CELL_DTYPE', 'pack_registered', 'unpack_registered',
           'map_cells']

REGISTERED_DTYPE = np.dtype({'names': ['x', 'y', 'z', 'finger', 't'],
                             'formats': ['<f4', '<f4', '<f4', 'u1', '<f8'],
                             'offsets': [0, 4, 8, 12, 16], 'itemsize': 24})

MAP_CELL_DTYPE = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4'),
                           ('hits', '<u4'), ('first_touch', '<f4')])


def pack_registered(points, times, fingers) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    packed = np.empty(points.shape[0], dtype=REGISTERED_DTYPE)
    packed['x'], packed['y'], packed['z'] = points[:, 0], points[:, 1], points[:, 2]
    packed['finger'] = fingers
    packed['t'] = times
    return packed


def unpack_registered(packed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (N, 3) float64, times (N,), fingers (N,)) from a registered-points array."""
    points = np.stack([packed['x'], packed['y'], packed['z']], axis=1).astype(np.float64)
    return points, np.asarray(packed['t'], dtype=np.float64), np.asarray(packed['finger'])


def map_cells(grid: OccupancyGrid, threshold: float | None = None,
              time_origin: float | None = None) -> np.ndarray:
    """Touched cells (above ``threshold`` if given) in the MAP_CELL_DTYPE layout.

    ``time_origin`` (s) is subtracted from first-touch times; by default the earliest
    first touch of the map, so the field reads "seconds into the exploration".
    """
    mask = grid.touched_mask()
    probabilities = grid.probabilities()
    if threshold is not None:
        mask &= probabilities > threshold
    ijk = np.nonzero(mask)
    cells = np.empty(ijk[0].shape[0], dtype=MAP_CELL_DTYPE)
    spec = grid.spec
    for axis, name in enumerate('xyz'):
        cells[name] = spec.origin[axis] + (ijk[axis] + 0.5) * spec.resolution
    cells['intensity'] = probabilities[ijk]
    cells['hits'] = grid.hits[ijk]
    first = grid.first_touch[ijk]
    if time_origin is None:
        touched = grid.first_touch[np.isfinite(grid.first_touch)]
        time_origin = float(touched.min()) if touched.size else 0.0
    cells['first_touch'] = first - time_origin
    return cells
