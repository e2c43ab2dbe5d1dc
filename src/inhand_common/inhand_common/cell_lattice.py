"""The lattice of a map's cells: cell size and the corner of cell (0, 0, 0).

A PLY or a published map cloud carries cell centres only; the lattice is inferred from them
(the smallest gap between distinct coordinates), the same way for the tools and the shape
node.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ['Lattice', 'cell_indices', 'cells_holding', 'infer_lattice']


@dataclass(frozen=True)
class Lattice:
    """Cubic cells of edge ``resolution``; ``origin`` is the corner of cell (0, 0, 0)."""

    resolution: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f'cell size must be positive, not {self.resolution!r}')


def infer_lattice(centres: ArrayLike, resolution: float | None = None) -> Lattice:
    """The lattice of a set of cell centres (a PLY or a recorded cloud carries none).

    The cell edge is the smallest gap between distinct centre coordinates on any axis
    (``resolution`` overrides it); the origin puts the centres at half-cell positions.
    """
    points = np.asarray(centres, dtype=float).reshape(-1, 3)
    if len(points) == 0:
        raise ValueError('no cells to infer the cell size from')
    if resolution is None:
        gaps = []
        for axis in range(3):
            values = np.unique(np.round(points[:, axis], 7))
            step = np.diff(values)
            step = step[step > 1e-6]
            if step.size:
                gaps.append(step.min())
        if not gaps:
            raise ValueError('cannot infer the cell size from a single cell: give it '
                             '(--resolution)')
        resolution = float(np.round(min(gaps), 6))
    x, y, z = (float(v) for v in points[0] - 0.5 * resolution)
    return Lattice(float(resolution), (x, y, z))


def cell_indices(points: ArrayLike, lattice: Lattice) -> NDArray[np.int64]:
    """Integer cell index (n, 3) of each point."""
    flat = np.asarray(points, dtype=float).reshape(-1, 3)
    return np.asarray(np.floor((flat - np.asarray(lattice.origin)) / lattice.resolution), dtype=np.int64)


def cells_holding(points: ArrayLike, centres: ArrayLike, lattice: Lattice) -> NDArray[np.intp]:
    """For each of ``points`` (K, 3), the index into ``centres`` (M, 3: cell centres on
    ``lattice``) of the cell it lies in; -1 where it lies in none of them or is not finite.
    One sort of the cells' keys and a binary search per point (keys taken within the cells'
    bounding box, so that they cannot overflow)."""
    positions = np.asarray(points, dtype=float).reshape(-1, 3)
    cell_centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    owner = np.full(len(positions), -1, dtype=np.intp)
    finite = np.flatnonzero(np.isfinite(positions).all(axis=1))
    if not len(finite) or not len(cell_centres):
        return owner
    cells = cell_indices(cell_centres, lattice)
    low, high = cells.min(axis=0), cells.max(axis=0)
    keys = cell_indices(positions[finite], lattice)
    near = np.all((keys >= low) & (keys <= high), axis=1)
    span = high - low + 1

    def flat(ijk: np.ndarray) -> np.ndarray:
        shifted = ijk - low
        return np.asarray((shifted[:, 0] * span[1] + shifted[:, 1]) * span[2] + shifted[:, 2])
    cell_keys, point_keys = flat(cells), flat(keys[near])
    order = np.argsort(cell_keys, kind='stable')
    where = np.clip(np.searchsorted(cell_keys[order], point_keys), 0, len(order) - 1)
    inside = cell_keys[order][where] == point_keys
    owner[finite[near][inside]] = order[where[inside]]
    return owner
