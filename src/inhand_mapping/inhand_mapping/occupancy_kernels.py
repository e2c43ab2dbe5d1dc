"""Compiled inner loops of the occupancy update (numba), used only by occupancy.py.

Why compiled: the update is a scatter with per-visit state (each sample adds to its cell,
or to 27 cells, unless its visit has already given its measurement's worth), which in
numpy would be a sort and several passes per batch; one compiled pass over the samples
does tens of millions of cell updates per second. The maths is described in occupancy.py.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def integrate(points, times, has_times, fingers, weights, origin, inv_res, n, half_inv_var,
              log_c, reach, to_cell, visit_gap, visit_last, visit_weight, log_odds,
              probability, hits, first_touch, l_min, l_max, changed, changed_mark):
    """Apply eq. 4 sample by sample, in the order given.

    ``half_inv_var`` = res^2 / (2 sigma^2) (distances are in cells); ``to_cell`` 1: eq. 3's
    distance is to the nearest point of the cell, 0: to its centre; ``reach`` 0 or 1 (the
    27-neighbourhood). With times, ``visit_last`` / ``visit_weight`` (fingers x cells) hold
    each finger's current visit of each cell: when it was last there and how much evidence
    the visit has given (at most 1). ``probability`` is refreshed at the end around each
    containing cell (not per update: exp is most of the cost); ``changed`` is a buffer for
    those cells and ``changed_mark`` a per-cell flag array, all False on entry and return.
    Returns (integrated, outside, invalid, earliest time).
    """
    n_changed = 0
    axis_d2 = np.empty((3, 3))
    integrated = 0
    outside = 0
    invalid = 0
    earliest = np.inf
    cells = n * n * n
    ox, oy, oz = origin[0], origin[1], origin[2]
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
        ex, ey, ez = x - ix - 0.5, y - iy - 0.5, z - iz - 0.5   # offset from the centre
        c = (ix * n + iy) * n + iz
        hits[c] += 1
        if has_times:
            if not (first_touch[c] <= t):   # NaN: untouched
                first_touch[c] = t
            if t < earliest:
                earliest = t
        integrated += 1
        w = weights[i]
        base = fingers[i] * cells
        # Squared distance (in cells) along each axis to the cells at offsets -1, 0, +1:
        # the 27 neighbours' distances are sums of three of these.
        for d in range(3):
            for axis in range(3):
                e = ex if axis == 0 else (ey if axis == 1 else ez)
                u = abs(e - (d - 1))
                if to_cell:
                    u = max(u - 0.5, 0.0)
                axis_d2[axis, d] = u * u
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
                        k = base + j
                        if not (abs(t - visit_last[k]) <= visit_gap):   # a new visit
                            visit_weight[k] = 0.0
                        visit_last[k] = t
                        dw = min(w, 1.0 - visit_weight[k])
                        if dw <= 0.0:
                            continue
                        visit_weight[k] += dw
                    value = log_odds[j] - dw * ((dxy + axis_d2[2, dz + 1]) * half_inv_var
                                                + log_c)
                    log_odds[j] = min(max(value, l_min), l_max)
        # The cells changed are this cell's neighbourhood: listed once per containing cell.
        if not changed_mark[c]:
            changed_mark[c] = True
            changed[n_changed] = c
            n_changed += 1
    for k in range(n_changed):
        c = changed[k]
        changed_mark[c] = False
        ix, iy, iz = c // (n * n), (c // n) % n, c % n
        for jx in range(max(ix - reach, 0), min(ix + reach + 1, n)):
            for jy in range(max(iy - reach, 0), min(iy + reach + 1, n)):
                for jz in range(max(iz - reach, 0), min(iz + reach + 1, n)):
                    j = (jx * n + jy) * n + jz
                    probability[j] = 1.0 / (1.0 + math.exp(-log_odds[j]))
    return integrated, outside, invalid, earliest


@numba.njit(cache=True, nogil=True)
def gather_cells(log_odds, probabilities, hits, first_touch, time_origin, prior, origin, res,
                 n, threshold, touched, touched_u32, occupied, occupied_u32):
    """Touched cells into ``touched`` and those above ``threshold`` also into ``occupied``
    (rows of 6 float32: x y z intensity hits first_touch; the ``*_u32`` arguments are the
    same buffers viewed as uint32 so the hit count is stored as an integer). Returns the
    two row counts.

    One pass instead of the ~15 numpy passes of masks, index arrays and field copies: it
    is what keeps building the clouds of a full 70^3 map within a couple of milliseconds.
    The threshold is compared with the float64 probability, as OccupancyGrid.cells does.
    First-touch times are given relative to ``time_origin``.
    """
    m = 0
    k = 0
    c = 0
    for ix in range(n):
        x = origin[0] + (ix + 0.5) * res
        for iy in range(n):
            y = origin[1] + (iy + 0.5) * res
            for iz in range(n):
                if log_odds[c] != prior or hits[c] > 0:
                    z = origin[2] + (iz + 0.5) * res
                    touched[m, 0] = x
                    touched[m, 1] = y
                    touched[m, 2] = z
                    touched[m, 3] = probabilities[c]
                    touched_u32[m, 4] = hits[c]
                    touched[m, 5] = first_touch[c] - time_origin
                    if probabilities[c] > threshold:
                        for j in range(6):
                            occupied_u32[k, j] = touched_u32[m, j]
                        k += 1
                    m += 1
                c += 1
    return m, k
