"""What a live view needs between whole maps: the cells whose shown state changed.

A whole map is published a few times a second (``publish_rate``): at 70^3 cells a touched
cloud is megabytes, too heavy at the rate a viewer should follow a finger. The
``occupancy/updates`` stream carries only the cells whose probability changed since the
previous update, and the cells the fingertips are in *now*: the path model applies a
sample's evidence only once the finger's speed around it is known (``speed_context``
later, see touch_paths.py), so without them a viewer would see a touch a third of a
second late. Such cells come flagged ``provisional`` with the probability one touch
would give; when their evidence is applied (or the finger passed through the air) the
next update carries their real value.

Layout (UPDATE_CELL_DTYPE): ``x y z`` (cell centre, map frame), ``intensity``
(probability), ``hits`` (uint32), ``provisional`` (uint8), padded to 20 bytes.
Plain numpy, no rclpy; every step is vectorised over the grid.
"""

from __future__ import annotations

import numpy as np

from inhand_common.array_types import Points
from inhand_mapping.occupancy import GridSpec, SensorModel, logit, probability

__all__ = ['UPDATE_CELL_DTYPE', 'MapUpdates']

UPDATE_CELL_DTYPE = np.dtype({'names': ['x', 'y', 'z', 'intensity', 'hits', 'provisional'],
                              'formats': ['<f4', '<f4', '<f4', '<f4', '<u4', 'u1'],
                              'offsets': [0, 4, 8, 12, 16, 20], 'itemsize': 24})


class MapUpdates:
    """The changes of the shown state of a grid of ``spec`` and ``model`` between calls
    of :meth:`changes`; a viewer starts from the prior (nothing sent yet)."""

    def __init__(self, spec: GridSpec, model: SensorModel):
        self.spec = spec
        size = spec.cells_per_axis ** 3
        # a provisional cell is shown with one touch more (eq. 4 inside the cell), clamped
        self.touch_log_odds = -float(np.log(model.p_z_given_not_occupied))
        self.clamp_log_odds = float(logit(model.clamp_max))
        self._sent = np.full(size, float(logit(model.prior)))   # log-odds as last sent
        self._sent_provisional = np.zeros(size, dtype=bool)

    def provisional_mask(self, held_points: Points) -> np.ndarray:
        """Flat mask of the cells holding ``held_points`` (those outside ignored)."""
        mask = np.zeros(self._sent.shape, dtype=bool)
        ijk = self.spec.cell_indices(held_points)
        ijk = ijk[self.spec.holds(ijk)]
        if len(ijk):
            mask[np.ravel_multi_index(ijk.T, self.spec.shape)] = True
        return mask

    def changes(self, log_odds: np.ndarray, hits: np.ndarray, held_points: Points) -> np.ndarray:
        """The cells (UPDATE_CELL_DTYPE) whose shown state differs from the last call's."""
        flat = log_odds.reshape(-1)
        provisional = self.provisional_mask(held_points)
        changed = np.flatnonzero((flat != self._sent) | (provisional != self._sent_provisional))
        self._sent[changed] = flat[changed]
        self._sent_provisional[changed] = provisional[changed]
        return self._cells(changed, flat, hits.reshape(-1), provisional)

    def _cells(self, flat_indices: np.ndarray, log_odds: np.ndarray, hits: np.ndarray,
               provisional: np.ndarray) -> np.ndarray:
        cells = np.empty(len(flat_indices), dtype=UPDATE_CELL_DTYPE)
        centres = self.spec.cell_centres(np.stack(np.unravel_index(flat_indices,
                                                                   self.spec.shape), axis=1))
        cells['x'], cells['y'], cells['z'] = centres[:, 0], centres[:, 1], centres[:, 2]
        shown = log_odds[flat_indices]
        is_provisional = provisional[flat_indices]
        shown = np.where(is_provisional,
                         np.minimum(shown + self.touch_log_odds, self.clamp_log_odds), shown)
        cells['intensity'] = probability(shown)
        cells['hits'] = hits[flat_indices]
        cells['provisional'] = is_provisional
        return cells
