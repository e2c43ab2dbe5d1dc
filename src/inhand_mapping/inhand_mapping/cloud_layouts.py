"""Point layouts of the clouds the mapping nodes publish (plain numpy, no ROS).

* ``registration/points``: registered fingertip positions, ``x y z`` (float32, map frame,
  m), ``finger`` (uint8, index into the registration node's ``finger_names``) and ``t``
  (float64, the measurement stamp in seconds). ``build_map`` passes its points through
  the same packing, so it integrates exactly the float32 positions the node would.
* ``occupancy/cloud`` and ``occupancy/occupied``: one point per cell, ``x y z`` (cell
  centre), ``intensity`` (occupancy probability: RViz and Foxglove colour by it), ``hits``
  (uint32: measurements whose containing cell it is) and ``first_touch`` (float32 seconds
  since the map's first measurement, NaN if never hit directly).
* ``occupancy/textured``: one point per occupied cell, ``x y z intensity`` as above, ``rgb``
  (float32 holding packed 0x00RRGGBB, the PCL/RViz convention, 0 where not textured) and
  ``textured`` (uint8: 1 where the camera saw the cell's surface), padded to 24 bytes.
* ``vision/cloud`` (and ``occupancy/touch/cloud``, the touch local map, in the
  ``occupancy/cloud`` layout): the vision local map, one point per cell a stereo exposure
  updated, ``x y z intensity`` (its probability) and ``log_odds`` (float32). The occupancy
  node rebuilds the vision grid from ``log_odds`` (:func:`vision_log_odds`), and
  ``build_map`` passes its vision map through the same layout, so both fuse the same
  float32 values.
* ``stereo/object``: the object's measured points of a stereo pair (the table and the
  backdrop left out), ``x y z`` and the camera's position ``vp_x vp_y vp_z`` (float32, map
  frame, m): PCL's PointWithViewpoint layout. The exploration node makes the cells they fall
  in surface, and the space in front of them along the rays free.
"""

from __future__ import annotations

import math

import numpy as np

from inhand_common.log_odds import probability
from inhand_common.packed_rgb import rgb_of_colours
from inhand_mapping import occupancy_kernels as kernels
from inhand_mapping.occupancy import GridSpec, OccupancyGrid

__all__ = [
    'MAP_CELL_DTYPE',
    'REGISTERED_DTYPE',
    'SEEN_POINT_DTYPE',
    'TEXTURED_CELL_DTYPE',
    'VISION_CELL_DTYPE',
    'MapClouds',
    'map_cells',
    'pack_registered',
    'seen_cloud',
    'seen_points',
    'textured_cells',
    'unpack_registered',
    'vision_cells',
    'vision_log_odds',
]

REGISTERED_DTYPE = np.dtype({'names': ['x', 'y', 'z', 'finger', 't'],
                             'formats': ['<f4', '<f4', '<f4', 'u1', '<f8'],
                             'offsets': [0, 4, 8, 12, 16], 'itemsize': 24})

# layer: the surface layer's probability, the same as intensity but where the cell judge
# overrode it (OccupancyGrid.layer_probabilities); the shape's parts leave out the cells it
# rescued (shape_extraction.part_cells)
MAP_CELL_DTYPE = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4'),
                           ('hits', '<u4'), ('first_touch', '<f4'), ('layer', '<f4')])

TEXTURED_CELL_DTYPE = np.dtype({'names': ['x', 'y', 'z', 'intensity', 'rgb', 'textured'],
                                'formats': ['<f4', '<f4', '<f4', '<f4', '<f4', 'u1'],
                                'offsets': [0, 4, 8, 12, 16, 20], 'itemsize': 24})

VISION_CELL_DTYPE = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4'),
                              ('log_odds', '<f4')])


SEEN_POINT_DTYPE = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                             ('vp_x', '<f4'), ('vp_y', '<f4'), ('vp_z', '<f4')])


def seen_cloud(points, viewpoint) -> np.ndarray:
    """``stereo/object``'s points: ``points`` (K, 3) seen from ``viewpoint`` (3,)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    camera = np.asarray(viewpoint, dtype=np.float64).reshape(3)
    cloud = np.empty(len(points), dtype=SEEN_POINT_DTYPE)
    for axis, name in enumerate('xyz'):
        cloud[name] = points[:, axis]
        cloud[f'vp_{name}'] = camera[axis]
    return cloud


def seen_points(cloud: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(points (K, 3), viewpoints (K, 3)) of a ``stereo/object`` cloud, float64."""
    return (np.stack([cloud[a] for a in 'xyz'], axis=1).astype(np.float64),
            np.stack([cloud[f'vp_{a}'] for a in 'xyz'], axis=1).astype(np.float64))


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


class MapClouds:
    """Builds the touched and the occupied cells of a grid in the MAP_CELL_DTYPE layout.

    One compiled pass over the grid (occupancy_kernels.gather_cells) into two buffers that
    are reused: the returned arrays are views, valid until the next call (copy them to
    keep them).
    """

    def __init__(self, grid: OccupancyGrid):
        self.grid = grid
        size = grid.spec.cells_per_axis ** 3
        self._touched = np.empty((size, 7), dtype=np.float32)
        self._occupied = np.empty((size, 7), dtype=np.float32)
        self._buffers = kernels.CloudBuffers(self._touched, self._touched.view(np.uint32),
                                             self._occupied, self._occupied.view(np.uint32))

    def __call__(self, threshold: float) -> tuple[np.ndarray, np.ndarray]:
        grid = self.grid
        grid.apply_layer()          # the kernel reads the cell arrays directly
        time_origin = grid.earliest_touch if math.isfinite(grid.earliest_touch) else 0.0
        overridden, layer = grid.layer_overrides()
        touched, occupied = kernels.gather_cells(
            grid.cell_arrays, grid.geometry, grid.prior_log_odds, float(threshold), time_origin,
            overridden, layer, self._buffers)
        return (self._touched[:touched].view(MAP_CELL_DTYPE).reshape(-1),
                self._occupied[:occupied].view(MAP_CELL_DTYPE).reshape(-1))


def map_cells(grid: OccupancyGrid, threshold: float | None = None) -> np.ndarray:
    """Touched cells (above ``threshold`` if given) in the MAP_CELL_DTYPE layout (a copy).

    ``first_touch`` reads "seconds into the exploration": relative to the map's earliest.
    """
    touched, occupied = MapClouds(grid)(-1.0 if threshold is None else threshold)
    return (touched if threshold is None else occupied).copy()


def textured_cells(cells: np.ndarray, colours, textured) -> np.ndarray:
    """The ``occupancy/textured`` points (TEXTURED_CELL_DTYPE, a new array) of the occupied
    ``cells`` (any structured array with ``x y z intensity``: MAP_CELL_DTYPE rows) with their
    ``colours`` (N, 3) RGB uint8 and ``textured`` (N,) mask; ``rgb`` is 0 where not
    textured, whatever ``colours`` holds there."""
    colours = np.asarray(colours)
    seen = np.asarray(textured).astype(bool)
    if colours.shape != (len(cells), 3) or seen.shape != (len(cells),):
        raise ValueError(f'colours must be ({len(cells)}, 3) and textured ({len(cells)},), '
                         f'got {colours.shape} and {seen.shape}')
    points = np.zeros(len(cells), dtype=TEXTURED_CELL_DTYPE)    # zeros: defined padding bytes
    for name in ('x', 'y', 'z', 'intensity'):
        points[name] = cells[name]
    points['rgb'] = rgb_of_colours(np.where(seen[:, None], colours, 0))
    points['textured'] = seen
    return points


def vision_cells(spec: GridSpec, log_odds: np.ndarray) -> np.ndarray:
    """The ``vision/cloud`` points (VISION_CELL_DTYPE) of a vision map's log-odds grid
    (prior 1/2 = 0): every cell an exposure updated."""
    observed = log_odds != 0.0
    ijk = np.argwhere(observed)
    centres = spec.cell_centres(ijk)
    values = log_odds[observed].astype(np.float32)
    points = np.empty(len(ijk), dtype=VISION_CELL_DTYPE)
    for axis, name in enumerate('xyz'):
        points[name] = centres[:, axis]
    points['log_odds'] = values
    points['intensity'] = probability(values)
    return points


def vision_log_odds(cells: np.ndarray, spec: GridSpec) -> tuple[np.ndarray, int]:
    """The vision map's log-odds grid (float64, 0 where unobserved) from ``vision/cloud``
    points, and how many of them fell outside ``spec`` (another grid: dropped)."""
    grid = np.zeros(spec.shape, dtype=np.float64)
    centres = np.stack([cells['x'], cells['y'], cells['z']], axis=1).astype(np.float64)
    inside = spec.contains(centres)
    ijk = spec.cell_indices(centres[inside])
    grid[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = cells['log_odds'][inside].astype(np.float64)
    return grid, int(np.count_nonzero(~inside))
