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

__all__ = ['Lattice', 'cell_indices', 'infer_lattice']


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
