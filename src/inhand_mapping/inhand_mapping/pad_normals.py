"""Which way a round finger pad touches: the surface normal from the pad centres before it.

A pad of radius ``r`` touches the surface one radius from its centre, along the surface's
normal there (tip_offsets.py). The normal is not measured, and the finger's own frame is
only a guess of it: a finger rolled about its axis by ``a`` faces ``a`` off the normal. But
the pad centres of a session lie on the object's surface grown by ``r`` (every contact
keeps the centre one radius out), so the centres the fingers have already passed through
around a point are a sheet whose normal is the surface's. This module keeps the moments of
those centres on a coarse hash grid and, for each new centre, fits a plane to the centres
before it within about one cell (principal components of the neighbouring cells' moments).

The plane's normal is used, turned to the side the pad faces, when the fit is trustworthy:
at least ``MIN_POINTS`` centres, spread over a patch (not one stroke's line: the second
axis at least ``MIN_SPREAD``), flat (the smallest axis under ``FLATNESS`` of the second),
and within ``MAX_TILT_DEG`` of where the finger's frame says the pad faces. Elsewhere (the
first pass over a region, an edge, a lone stroke) the finger's frame decides, as before.

Only centres with a stamp strictly before a point's own count for it, whatever the batches
were (the registrar releases whole stamps, never part of one), and every moment is an exact
integer, so the live graph and ``build_map`` (which batch the same points differently) put
every contact at the same place, to the bit. All of it is vectorised: a sorted table of occupied cells
and ``searchsorted``, no Python loop per point or per cell.
"""

from __future__ import annotations

import math

import numpy as np

from inhand_common.array_types import Points, Times

__all__ = ['PadNormals']

CELL_UM = 6000        # um: the hash cell; a fit uses the 27 cells around a centre (6-12 mm each way)
MIN_POINTS = 10       # centres in a fit
MIN_SPREAD = 0.002    # m: the patch's second axis (RMS): below it the centres are one stroke's line
FLATNESS = 0.25       # the smallest axis's variance at most this share of the second's
MAX_TILT_DEG = 60.0   # the fitted normal at most this far from the finger's facing

_BIAS = 1 << 20       # cell indices are packed as (i + B) S^2 + (j + B) S + (k + B)
_SPAN = 1 << 21
_OFFSETS = np.array([(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)],
                    dtype=np.int64)
_NEIGHBOURS = (_OFFSETS[:, 0] * _SPAN + _OFFSETS[:, 1]) * _SPAN + _OFFSETS[:, 2]
_MOMENTS = 10         # n, sum y (3), sum y y^T (upper triangle: 6)
_UPPER = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def _moments(local: np.ndarray) -> np.ndarray:
    """Per-point moments (N, 10) of integer coordinates (N, 3): 1, y, y y^T's upper triangle."""
    out = np.empty((local.shape[0], _MOMENTS), dtype=np.int64)
    out[:, 0] = 1
    out[:, 1:4] = local
    out[:, 4:] = local[:, _UPPER[0]] * local[:, _UPPER[1]]
    return out


def _row_sums(rows: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sums of ``values`` (K, 10) by ``rows`` (K,, ascending) into (n, 10): one reduceat, not
    a scatter (np.add.at is ten times slower)."""
    out = np.zeros((n, _MOMENTS), dtype=np.int64)
    if rows.size:
        starts = np.flatnonzero(np.concatenate(([True], rows[1:] != rows[:-1])))
        out[rows[starts]] = np.add.reduceat(values, starts, axis=0)
    return out


def _shifted(moments: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Moments of y about a corner ``delta`` (K, 3) lower, i.e. of y + delta: exact integers."""
    n = moments[:, :1]
    s = moments[:, 1:4]
    out = np.empty_like(moments)
    out[:, :1] = n
    out[:, 1:4] = s + n * delta
    a, b = _UPPER
    out[:, 4:] = (moments[:, 4:] + delta[:, a] * s[:, b] + s[:, a] * delta[:, b]
                  + n * delta[:, a] * delta[:, b])
    return out


class PadNormals:
    """The surface normal at each new pad centre, from the centres before it (see above).

    Positions are taken to the micrometre and every moment is an exact integer about its
    cell's corner, so the fit does not depend on how the points were batched, to the bit."""

    def __init__(self) -> None:
        self._origin: np.ndarray | None = None    # micrometre coordinates are about it
        self._keys = np.empty(0, dtype=np.int64)  # sorted, one per occupied cell
        self._sums = np.empty((0, _MOMENTS), dtype=np.int64)  # about each cell's corner
        self.fitted = 0       # contacts placed by the fitted normal
        self.from_finger = 0  # by the finger's own facing

    def contacts(self, centres: Points, facing: Points, times: Times, radius: float) -> Points:
        """Contacts one ``radius`` from each pad centre (N, 3), towards the fitted normal or
        the unit ``facing`` (N, 3) where no fit is trusted; ``times`` (N,) order the
        centres. The centres then join the history."""
        n = centres.shape[0]
        if n == 0:
            return centres.copy()
        if self._origin is None:
            self._origin = centres[0].copy()
        micrometres = np.rint((centres - self._origin) * 1e6).astype(np.int64)
        cells = np.floor_divide(micrometres, CELL_UM)
        keys = ((cells[:, 0] + _BIAS) * _SPAN + cells[:, 1] + _BIAS) * _SPAN + cells[:, 2] + _BIAS
        moments = _moments(micrometres - cells * CELL_UM)
        earlier, batch_cells, batch_sums = self._earlier_in_batch(keys, moments, times)
        direction = self._directions(self._history_sums(keys) + earlier, facing)
        self._add(batch_cells, batch_sums)
        return centres + radius * direction

    def summary(self) -> str:
        """One line for the logs: how the contacts were placed."""
        total = self.fitted + self.from_finger
        share = 100.0 * self.fitted / total if total else 0.0
        return (f'pad contacts: {self.fitted} of {total} ({share:.0f}%) along the normal of the '
                "surface the pads traced, the rest the way the finger's frame faces")

    # ------------------------------------------------------------------ internals
    @staticmethod
    def _gather(keys: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For each key's 27 neighbours found in the sorted ``table``: the key's row, the
        table row, and the neighbour's corner relative to the key's (micrometres)."""
        around = keys[:, None] + _NEIGHBOURS[None, :]
        at = np.minimum(np.searchsorted(table, around), table.size - 1)
        rows, which = np.nonzero(table[at] == around)
        return rows, at[rows, which], _OFFSETS[which] * CELL_UM

    def _history_sums(self, keys: np.ndarray) -> np.ndarray:
        """Moments of the earlier batches' centres in the 27 cells around each key, about
        the key's corner."""
        if self._keys.size == 0:
            return np.zeros((keys.size, _MOMENTS), dtype=np.int64)
        rows, at, delta = self._gather(keys, self._keys)
        return _row_sums(rows, _shifted(self._sums[at], delta), keys.size)

    def _earlier_in_batch(self, keys: np.ndarray, moments: np.ndarray, times: Times
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Moments of this batch's centres stamped strictly before each one, in the 27
        cells around it: the batch sorted by (cell, time) with running sums, and each
        query's cut found by one searchsorted on the cell's rank and the time together.
        Also the batch's cells (sorted) and each one's total, from the same running sums,
        for the table (:meth:`_add`)."""
        order = np.lexsort((times, keys))
        unique, start = np.unique(keys[order], return_index=True)
        rank = np.repeat(np.arange(unique.size), np.diff(np.append(start, keys.size)))
        t0 = float(times.min())
        stride = float(times.max()) - t0 + 1.0
        composite = rank * stride + (times[order] - t0)
        running = np.zeros((keys.size + 1, _MOMENTS), dtype=np.int64)
        np.cumsum(moments[order], axis=0, out=running[1:])
        rows, cell, delta = self._gather(keys, unique)
        cut = np.searchsorted(composite, cell * stride + (times[rows] - t0), side='left')
        earlier = _row_sums(rows, _shifted(running[cut] - running[start[cell]], delta), keys.size)
        totals = running[np.append(start[1:], keys.size)] - running[start]
        return earlier, unique, totals

    def _directions(self, sums: np.ndarray, facing: Points) -> Points:
        """The fitted normal (turned to the facing side) where the fit is trusted, else the
        facing."""
        direction = facing.copy()
        usable = np.flatnonzero(sums[:, 0] >= MIN_POINTS)
        if usable.size:
            s = sums[usable].astype(float)
            mean = s[:, 1:4] / s[:, :1]
            second = np.empty((usable.size, 3, 3))
            second[:, _UPPER[0], _UPPER[1]] = s[:, 4:]
            second[:, _UPPER[1], _UPPER[0]] = s[:, 4:]
            covariance = (second / s[:, :1, None] - mean[:, :, None] * mean[:, None, :]) * 1e-12
            values, vectors = np.linalg.eigh(covariance)   # ascending, m^2
            normal = vectors[:, :, 0]
            along = np.sum(normal * facing[usable], axis=1)
            trusted = ((values[:, 1] >= MIN_SPREAD ** 2)
                       & (values[:, 0] <= FLATNESS * values[:, 1])
                       & (np.abs(along) >= math.cos(math.radians(MAX_TILT_DEG))))
            usable = usable[trusted]
            direction[usable] = normal[trusted] * np.sign(along[trusted])[:, None]
        self.fitted += usable.size
        self.from_finger += facing.shape[0] - usable.size
        return direction

    def _add(self, cells: np.ndarray, sums: np.ndarray) -> None:
        """Fold a batch's cells (sorted keys) and their moments into the table (kept sorted)."""
        merged = np.union1d(self._keys, cells)
        table = np.zeros((merged.size, _MOMENTS), dtype=np.int64)
        table[np.searchsorted(merged, self._keys)] = self._sums
        table[np.searchsorted(merged, cells)] += sums
        self._keys, self._sums = merged, table
