"""Compiled inner loops of the occupancy update (numba), used only by occupancy.py and cloud_layouts.py.

Why compiled: the update is a scatter with per-visit state (each sample adds to its cell,
or to 27 cells, unless its visit has already given its measurement's worth), which in
numpy would be a sort and several passes per batch; one compiled pass over the samples
does tens of millions of cell updates per second. The maths is described in occupancy.py.

The kernels take their inputs grouped in the NamedTuples below (numba passes them in
nopython mode as structs of arrays and scalars, at no cost in the loops). The grid builds
the ones that do not change (geometry, update model, cell arrays) once, when it is made.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple, TypeVar, cast

import numba
import numpy as np
from numpy.typing import NDArray

from inhand_common.array_types import (
    Bools,
    CellFloats,
    CellHits,
    FingerIds,
    Floats,
    Indices,
    Points,
    Times,
    Vector3,
    Weights,
)

__all__ = ['CellArrays', 'CloudBuffers', 'GridGeometry', 'SampleBatch', 'UpdateModel', 'Visits',
           'gather_cells', 'integrate']

_Function = TypeVar('_Function', bound=Callable[..., object])


def _compiled(function: _Function) -> _Function:
    """``numba.njit(cache=True, nogil=True)`` that keeps the Python signature for mypy (numba
    ships no type information, so the dispatcher it returns would be untyped)."""
    return cast(_Function, numba.njit(cache=True, nogil=True)(function))


def _uncounted(function: _Function) -> _Function:
    """``_compiled`` without numba's reference counting (its ``_nrt=False`` option, which
    numba's own string helpers use for the same reason): for kernels that index the arrays
    they are given and allocate none (an allocation does not compile). Counted, every
    array bound to a name (a field of a state tuple handed to an inlined step, a row view)
    is an atomic increment and decrement: in the path model, about a hundred per sample,
    four fifths of its time (perf: NRT_incref and NRT_decref)."""
    # _nrt is a flag of numba's compiler, not in its type stubs' signature of njit
    return cast(_Function, numba.njit(cache=True, nogil=True, _nrt=False)(  # type: ignore[call-overload]
        function))


def _inlined(function: _Function) -> _Function:
    """A per-sample step of a kernel, compiled into it (numba inlines it in its own IR): as
    separately compiled functions they stay calls, and neighbourhood 1 runs at a third of
    the speed. Only for the per-sample steps: inlining costs compile time (cold cache)."""
    return cast(_Function, numba.njit(cache=True, nogil=True, inline='always')(function))


class GridGeometry(NamedTuple):
    """Where the cells are: fixed when the grid is made."""

    origin: Vector3     # (3,) map-frame position of the outer corner of cell (0, 0, 0), m
    resolution: float   # cell edge, m
    inv_res: float      # 1 / resolution: metres to cells
    n: int              # cells per axis; cell (ix, iy, iz) is flat index (ix * n + iy) * n + iz


class UpdateModel(NamedTuple):
    """The sensor model and update in the kernel's units (distances in cells)."""

    half_inv_var: float  # res^2 / (2 sigma^2): eq. 3's exponent per squared distance in cells
    log_c: float         # log P(Z | not O)
    reach: int           # 0: the containing cell only; 1: its 27-neighbourhood
    to_cell: bool        # eq. 3's distance to the nearest point of a cell (else to its centre)
    visit_gap: float     # s: one finger's samples in one cell this close are one visit
    l_min: float         # log-odds clamp, applied after every update
    l_max: float


class CellArrays(NamedTuple):
    """The grid's per-cell state: flat (n^3,) views of OccupancyGrid's (n, n, n) arrays."""

    log_odds: CellFloats
    probability: CellFloats  # logistic of log_odds, refreshed by integrate where it changed
    hits: CellHits           # measurements whose containing cell it is
    first_touch: CellFloats  # time of the first of them (s); NaN: none yet
    contact_sum: Floats      # (3 n^3,) the sum of their positions (m, map frame): x y z per cell
    changed_mark: Bools      # integrate's scratch flags: all False on entry and on return


class Visits(NamedTuple):
    """Each finger's current visit of each cell, flat (fingers * n^3,), at finger * n^3 + cell."""

    last: Floats    # when the finger was last in the cell (s); -inf: never
    weight: Floats  # evidence the visit has given so far: at most one measurement's worth


class SampleBatch(NamedTuple):
    """Measurements to apply, in order."""

    points: Points      # (N, 3) map frame, m
    times: Times        # (N,) s; not read (may be empty) when has_times is False
    has_times: bool     # without times there is neither first-touch time nor visits
    fingers: FingerIds  # (N,) whose fingertip: indexes the visits
    weights: Weights    # (N,) how much of a measurement each sample is


class CloudBuffers(NamedTuple):
    """Rows of 7 (x y z intensity hits first_touch layer) that gather_cells fills, (n^3, 7)
    each; the ``*_u32`` arrays are the same memory viewed as uint32, for the hit count."""

    touched: NDArray[np.float32]
    touched_u32: NDArray[np.uint32]
    occupied: NDArray[np.float32]
    occupied_u32: NDArray[np.uint32]


@_inlined
def _add_position(contact_sum: Floats, c: int, px: float, py: float, pz: float) -> None:
    """Count a measurement's position in its cell ``c`` (CellArrays.contact_sum)."""
    contact_sum[3 * c] += px
    contact_sum[3 * c + 1] += py
    contact_sum[3 * c + 2] += pz


@_compiled
def integrate(samples: SampleBatch, geometry: GridGeometry, model: UpdateModel,
              cells: CellArrays, visits: Visits, changed: Indices) -> tuple[int, int, int, float]:
    """Apply eq. 4 sample by sample, in the order given.

    ``changed`` is a buffer of at least min(samples, cells) entries for the cells whose
    neighbourhood changed: ``probability`` is refreshed there once at the end, not per
    update (exp is most of the cost). Returns (integrated, outside, invalid, earliest time).
    """
    points, times, has_times = samples.points, samples.times, samples.has_times
    ox, oy, oz = geometry.origin[0], geometry.origin[1], geometry.origin[2]
    inv_res, n = geometry.inv_res, geometry.n
    hits, first_touch, changed_mark = cells.hits, cells.first_touch, cells.changed_mark
    n_changed = 0
    axis_d2 = np.empty((3, 3))
    integrated = 0
    outside = 0
    invalid = 0
    earliest = np.inf
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        t = times[i] if has_times else 0.0
        if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)
                and math.isfinite(t)):
            invalid += 1
            continue
        # A finite point far away may scale to inf: it is outside, not invalid.
        x = (px - ox) * inv_res
        y = (py - oy) * inv_res
        z = (pz - oz) * inv_res
        if x < 0.0 or y < 0.0 or z < 0.0 or x >= n or y >= n or z >= n:
            outside += 1
            continue
        ix, iy, iz = int(x), int(y), int(z)
        c = (ix * n + iy) * n + iz
        hits[c] += 1
        _add_position(cells.contact_sum, c, px, py, pz)
        if has_times:
            if not (first_touch[c] <= t):   # NaN: untouched
                first_touch[c] = t
            if t < earliest:
                earliest = t
        integrated += 1
        # Offsets from the cell's centre, in cells.
        _axis_distances(x - ix - 0.5, y - iy - 0.5, z - iz - 0.5, model.to_cell, axis_d2)
        _add_evidence(ix, iy, iz, t, samples.weights[i], samples.fingers[i] * (n * n * n),
                      has_times, axis_d2, n, model, cells.log_odds, visits)
        # The cells changed are this cell's neighbourhood: listed once per containing cell.
        if not changed_mark[c]:
            changed_mark[c] = True
            changed[n_changed] = c
            n_changed += 1
    _refresh_probability(cells, n, model.reach, changed, n_changed)
    return integrated, outside, invalid, earliest


@_inlined
def _axis_distances(ex: float, ey: float, ez: float, to_cell: bool, axis_d2: Floats) -> None:
    """Squared distance (in cells) along each axis from a point ``e`` off its cell's centre to
    the cells at offsets -1, 0, +1: ``axis_d2[axis, offset + 1]`` (3, 3). The 27 neighbours'
    squared distances are sums of three of these, so no neighbour needs its own."""
    for d in range(3):
        for axis in range(3):
            e = ex if axis == 0 else (ey if axis == 1 else ez)
            u = abs(e - (d - 1))
            if to_cell:
                u = max(u - 0.5, 0.0)
            axis_d2[axis, d] = u * u


@_inlined
def _add_evidence(ix: int, iy: int, iz: int, t: float, w: float, visit_base: int, has_times: bool,
                  axis_d2: Floats, n: int, model: UpdateModel, log_odds: CellFloats,
                  visits: Visits) -> None:
    """Eq. 4 for one sample of weight ``w`` in cell (ix, iy, iz): on that cell, and with
    reach 1 on its neighbours inside the grid, each at its own distance. ``visit_base`` is
    the sample's finger's row in ``visits``."""
    reach = model.reach
    for dx in range(-reach, reach + 1):
        jx = ix + dx
        if jx < 0 or jx >= n:
            continue
        for dy in range(-reach, reach + 1):
            jy = iy + dy
            if jy < 0 or jy >= n:
                continue
            dxy = axis_d2[0, dx + 1] + axis_d2[1, dy + 1]
            row = (jx * n + jy) * n
            for dz in range(-reach, reach + 1):
                jz = iz + dz
                if jz < 0 or jz >= n:
                    continue
                j = row + jz
                dw = w
                if has_times:
                    dw = _visit_share(visits, visit_base + j, t, w, model.visit_gap)
                    if dw <= 0.0:
                        continue
                value = log_odds[j] - dw * ((dxy + axis_d2[2, dz + 1]) * model.half_inv_var
                                            + model.log_c)
                log_odds[j] = min(max(value, model.l_min), model.l_max)


@_inlined
def _visit_share(visits: Visits, k: int, t: float, w: float, visit_gap: float) -> float:
    """How much of the weight ``w`` of a sample at ``t`` its finger's visit ``k`` (of one
    cell) still takes, the visit updated: a visit gives at most one measurement's worth, and
    a finger back in the cell more than ``visit_gap`` after it was last there starts a new one.
    Nothing (<= 0) once the visit has given its worth."""
    if not (abs(t - visits.last[k]) <= visit_gap):   # a new visit
        visits.weight[k] = 0.0
    visits.last[k] = t
    dw: float = min(w, 1.0 - visits.weight[k])
    if not dw <= 0.0:
        visits.weight[k] += dw
    return dw


@_compiled
def _refresh_probability(cells: CellArrays, n: int, reach: int, changed: Indices,
                         n_changed: int) -> None:
    """Recompute the probability around each of the first ``n_changed`` cells of ``changed``
    (their neighbourhood is what the update touched), and clear their ``changed_mark``."""
    log_odds, probability = cells.log_odds, cells.probability
    for k in range(n_changed):
        c = changed[k]
        cells.changed_mark[c] = False
        ix, iy, iz = c // (n * n), (c // n) % n, c % n
        for jx in range(max(ix - reach, 0), min(ix + reach + 1, n)):
            for jy in range(max(iy - reach, 0), min(iy + reach + 1, n)):
                for jz in range(max(iz - reach, 0), min(iz + reach + 1, n)):
                    j = (jx * n + jy) * n + jz
                    probability[j] = 1.0 / (1.0 + math.exp(-log_odds[j]))


@_compiled
def gather_cells(cells: CellArrays, geometry: GridGeometry, prior: float, threshold: float,
                 time_origin: float, overridden: NDArray[np.intp],
                 layer: NDArray[np.float64], out: CloudBuffers) -> tuple[int, int]:
    """Touched cells (log-odds not ``prior``, or hit) into ``out.touched``, and those with a
    probability above ``threshold`` also into ``out.occupied``. Returns the two row counts.
    The last column is the surface layer's probability: the cell's own but in the cells
    ``overridden`` (flat, ascending), where it is ``layer`` (OccupancyGrid.layer_overrides).

    One pass instead of the ~15 numpy passes of masks, index arrays and field copies: it
    is what keeps building the clouds of a full 70^3 map within a couple of milliseconds.
    The threshold is compared with the float64 probability, as OccupancyGrid.cells does.
    First-touch times are given relative to ``time_origin``.
    """
    log_odds, probabilities, hits = cells.log_odds, cells.probability, cells.hits
    first_touch = cells.first_touch
    origin, res, n = geometry.origin, geometry.resolution, geometry.n
    touched, touched_u32 = out.touched, out.touched_u32
    occupied_u32 = out.occupied_u32
    m = 0
    k = 0
    c = 0
    o = 0
    for ix in range(n):
        x = origin[0] + (ix + 0.5) * res
        for iy in range(n):
            y = origin[1] + (iy + 0.5) * res
            for iz in range(n):
                if hits[c] > 0 or log_odds[c] != prior:  # hits first: 4 bytes, not 8
                    z = origin[2] + (iz + 0.5) * res
                    touched[m, 0] = x
                    touched[m, 1] = y
                    touched[m, 2] = z
                    touched[m, 3] = probabilities[c]
                    touched_u32[m, 4] = hits[c]
                    touched[m, 5] = first_touch[c] - time_origin
                    while o < len(overridden) and overridden[o] < c:
                        o += 1
                    if o < len(overridden) and overridden[o] == c:
                        touched[m, 6] = layer[o]
                    else:
                        touched[m, 6] = probabilities[c]
                    if probabilities[c] > threshold:
                        for j in range(7):
                            occupied_u32[k, j] = touched_u32[m, j]
                        k += 1
                    m += 1
                c += 1
    return m, k
