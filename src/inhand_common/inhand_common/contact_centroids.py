"""Where in each cell the surface was measured: the mean of the positions counted in it.

A cell is occupied when the surface passes anywhere through it, so its centre is up to
half a cell (sqrt(3)/2 at a corner) off the surface: 1.4-2.5 mm median on 5 mm cells of
the shape benchmark's touch maps. The mean of the fingertip positions that fell in the
cell lies on the surface to the tracker's noise: 0.4-1.0 mm there (docs/shape.md, "Where
the touches were"). The occupancy grid keeps the sums beside the hit counts
(``OccupancyGrid.contact_sum``); a consumer that has only a map cloud (the shape node)
sums the registered positions itself with :func:`position_sums`. Plain numpy, no ROS.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from inhand_common.array_types import Points
from inhand_common.cell_lattice import Lattice, cells_holding

__all__ = ['RecentPositions', 'centroids', 'position_sums']


def centroids(centres: ArrayLike, sums: ArrayLike, counts: ArrayLike) -> Points:
    """Per cell (M,): the mean position ``sums / counts`` (M, 3) where it counted any
    position, its centre (M, 3) where it counted none (a cell occupied by its neighbours'
    evidence, or by a sensor that keeps no positions)."""
    at = np.asarray(centres, dtype=float).reshape(-1, 3)
    total = np.asarray(sums, dtype=float).reshape(-1, 3)
    count = np.asarray(counts).reshape(-1)
    if not (len(total) == len(count) == len(at)):
        raise ValueError(f'{len(at)} cells, {len(total)} sums and {len(count)} counts')
    counted = count > 0
    means = at.copy()
    means[counted] = total[counted] / count[counted, None]
    return means


def position_sums(points: ArrayLike, centres: ArrayLike, lattice: Lattice,
                  newest: ArrayLike | None = None) -> tuple[Points, np.ndarray]:
    """The sum (M, 3) and count (M,) of the ``points`` (K, 3, oldest first) that fall in
    each of the cells whose ``centres`` (M, 3) are given on ``lattice``; points in no such
    cell and non-finite points are left out. ``newest`` (M,): at most this many of each
    cell's newest points count (the map's hit counts: points from before a reset of the
    map are then not its own)."""
    cell_centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    positions = np.asarray(points, dtype=float).reshape(-1, 3)
    sums = np.zeros((len(cell_centres), 3))
    counts = np.zeros(len(cell_centres), dtype=np.int64)
    owner = cells_holding(positions, cell_centres, lattice)
    inside = owner >= 0
    if not inside.any():
        return sums, counts
    owner, positions = owner[inside], positions[inside]
    if newest is not None:
        # each point's place from the newest in its cell (0: the newest)
        by_cell = np.argsort(owner, kind='stable')
        total = np.bincount(owner, minlength=len(cell_centres))
        start = np.cumsum(total) - total
        place = np.empty(len(owner), dtype=np.int64)
        place[by_cell] = np.arange(len(owner)) - start[owner[by_cell]]
        keep = total[owner] - 1 - place < np.asarray(newest).reshape(-1)[owner]
        owner, positions = owner[keep], positions[keep]
    counts = np.bincount(owner, minlength=len(cell_centres)).astype(np.int64)
    for axis in range(3):
        sums[:, axis] = np.bincount(owner, weights=positions[:, axis],
                                    minlength=len(cell_centres))
    return sums, counts


class RecentPositions:
    """The newest ``capacity`` positions given to :meth:`add` (float32, as the registered
    points arrive), for a consumer that sums them per cell only when asked
    (:func:`position_sums`). Past the capacity the oldest go (:attr:`dropped` counts them),
    a quarter of the capacity at a time, so that a full store does not copy itself on
    every message."""

    def __init__(self, capacity: int):
        if capacity < 1:
            raise ValueError(f'capacity {capacity}: must be at least 1')
        self.capacity = capacity
        self.dropped = 0
        self._chunks: list[np.ndarray] = []
        self._held = 0

    def __len__(self) -> int:
        return min(self._held, self.capacity)

    def add(self, points: ArrayLike) -> None:
        chunk = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        if not len(chunk):
            return
        self._chunks.append(chunk)
        self._held += len(chunk)
        if self._held > self.capacity + self.capacity // 4:
            kept = np.concatenate(self._chunks)[-self.capacity:]
            self.dropped += self._held - len(kept)
            self._chunks, self._held = [kept], len(kept)

    def points(self) -> Points:
        """(K, 3) float64, oldest first: the newest ``capacity``."""
        if not self._chunks:
            return np.empty((0, 3))
        return np.concatenate(self._chunks)[-self.capacity:].astype(np.float64)
