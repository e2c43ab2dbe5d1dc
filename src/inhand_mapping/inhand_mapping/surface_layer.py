"""The touch map's surface is one layer of cells: of two cells stacked along the local
normal, the weaker is the layer above it.

A fingertip in contact moves on the surface; everything else it does happens just outside
it: a lift-off or a set-down crosses the cells above the surface along the normal, a hover
glides a few millimetres above a stroke, tracker noise puts samples of a stroke into the
cell above when the surface runs near that cell's face. The path model (touch_paths.py)
cannot tell these apart from a contact by the path alone (a set-down at 0.1 m/s is as slow
as a 10 cm/s stroke), but the map around them can: the object's inside is never visited,
so the evidence piles up in a sheet, and the cells of the layer above that sheet get less
of it than the sheet itself. Measured on sessions of our simulator with other hands (the
docs/quality.md, "Other hands"), 1,105 of 1,573 wrong cells lay 5-10 mm off the
surface, and all but 0.7% of those had a neighbour nearer the surface with more evidence
(three times as much, in the median).

The rule, per cell with evidence ``e`` (touches, touch_paths.py):

1. *The local plane.* The cells within ``LAYER_RADIUS`` (a 7^3 box: 3.5 cm at 5 mm cells)
   weighted by their evidence (capped at ``WEIGHT_CAP`` touches, so one much-rubbed spot
   does not tilt the plane) give a weighted covariance of positions; its eigenvector of the
   smallest eigenvalue is the normal ``n``.
2. *The layer.* The evidence one cell along ``+n`` and ``-n`` (trilinear between cells,
   0 outside the grid). A cell with less evidence than either is the layer above (or
   below) the surface: its evidence is scaled by ``layer_factor`` (0.4) and by its share
   of the stronger one (e / e_stronger), so one touch of it does not count, a full pass
   stays under 0.8, and the noise a much-rubbed spot spills into the cell above (6
   touches over 30) stays under it too: without the share, a cell of the layer with more
   than 4.4 touches was occupied, and on small objects explored for minutes (the docs'
   set S) that was most of the stray cells left.
   So is a cell under ``NOISE_SHARE`` (0.2) of the *local level* (scaled by
   ``layer_factor`` alone), the evidence-weighted mean evidence of the box (sum e^2 /
   sum e, uncapped): where the fingers went over the
   surface ten times, a cell passed twice is a hover, a lift or a corner the strokes
   clipped. Exploring fills a neighbourhood evenly (strokes are centimetres long and
   cross it), while what happens off the surface is a small part of the time; on small
   objects explored for minutes (the docs' set S: stray cells at 2.4 touches in the
   median, true ones at 10.8) the plane can be too coarse for the test along ``n``, and
   this one still holds. Where a region was passed once or twice the level is that pass,
   and nothing changes.
   *But a thin wall's other side is not a layer*: on a wall one or two cells thick (a
   cup's, a mug's) the weaker of the two stacked cells is the wall's other face, touched
   from the other side. The air the path crossed says which: cells it passed with under
   ``AIR_TOUCHES`` (lifts, set-downs, carries) lie on a surface cell's open side. Above a
   surface the air of both cells lies on the same side; on a wall it lies on opposite
   sides. A weaker cell that is itself on a flat sheet (rule 3's test) and whose air, within
   ``AIR_RADIUS``, leans away from the stronger cell while the stronger cell's leans away
   from it (both by more than ``AIR_COS``) is not scaled as the layer. The same air finds
   the layer where it is *as strong* as the surface (``AS_STRONG`` of it or more: a hover as
   slow as the stroke under it earns as much): a cell whose air leans away from that
   neighbour while the neighbour's leans towards it lies outside the neighbour's surface
   and keeps ``layer_factor`` of its evidence. On the docs' set A the two take the sessions
   meeting their targets from 9 to 10 of 24 and the stray cells from 140 to 125, the cups
   and mugs keeping more of their walls; set S is unchanged (docs/quality.md).
3. *The sheet.* A cell that is no weaker than its neighbours along ``n``, lies in a flat
   sheet of evidence (the plane's smallest spread under ``SHEET_FLATNESS`` of the middle
   one, the middle over ``SHEET_BREADTH`` of the largest: a surface, not a line of one
   stroke nor a blob of jitter), on its middle (the evidence's centroid within
   ``SHEET_OFFSET`` of a cell of it along ``n``: curvature, a wall's two sides and the noise
   a stroke spreads across its cell thicken a sheet, and the flatness has to allow for
   that, but the layer beside a sheet lies a cell off its middle) and holds at least
   ``SHEET_MIN_TOUCHES`` (a pass at stroke speed through it: 1 touch, 1.75 with the gain,
   p 0.80) counts its evidence ``sheet_gain`` (1.75) times: a contact the surface around
   it confirms is enough once, as the one-touch oracle assumes; without the sheet a touch
   stays under the paper's 0.7. (A corner a pass clips is worth less than a touch.)
4. *Support.* A surface is not one cell, and it continues along itself: a cell's evidence
   after rules 2-3 counts at most as much as its strongest neighbour's among those within
   30 degrees of its plane (of the 26, those whose offset makes at least 60 degrees with
   ``n``: ``SUPPORT_COS``), or as one touch of the layer (``layer_factor`` touches) where
   that is more. Under any threshold above that, a cell is occupied only when a neighbour
   beside it on the surface is too, and a cell alone stays under 0.8 however often it is
   touched (the paper's concern: repeated involuntary movements at one place). Within a
   sheet nothing changes. A cell the rest of the map does not continue (a lift-off's last
   sample, a corner clipped once) counts as the layer, and so does one whose only strong
   neighbour lies below it along the normal (the peak of a hover over a stroke). On the
   docs' sets A and S the stray cells fall from 220 to 137 and from 94 to 74; with the
   sheet's gain from one touch (``SHEET_MIN_TOUCHES`` 1, was 1.2: what the support lets
   through less of) to 142 and 74, with the recall back (docs/quality.md).
5. *Bridge.* A surface continues through a cell between two of its cells: a cell that is
   not the layer (neither of rule 2's tests), lies on a surface (its plane's smallest
   spread under ``BRIDGE_FLATNESS`` of the middle one: not a ridge, a corner or a blob,
   where a cell between two occupied ones may lie off the surface) and holds at least
   ``BRIDGE_MIN_TOUCHES`` counts at least as much as the weaker of two opposite
   neighbours within 30 degrees of its plane (after rule 4), neighbours that share a face
   or an edge with it (across a corner the two span 8.7 mm of a curved surface). A
   stroke's trace has gaps where the path ran near a cell's corner, tracker noise moved a
   sample into the next cell or a fast pass clipped the cell (0.5-1.7 touches, and no
   sheet gain off a sheet's middle), and a digitised surface oblique to the grid is two
   cells thick where the layer test keeps one. Only a cell between two that are occupied
   becomes occupied, so the rule closes gaps in a surface and never extends one; the
   layer above a surface is left alone. On the docs' set A 9 sessions of 24 meet their
   targets instead of 7, for 3 more stray cells; set S is unchanged (docs/quality.md).

Which cells the rule has to look at again: a cell's layered evidence depends only on the
evidence within ``LAYER_RADIUS`` of it, so when evidence changes, the cells within that
distance are recomputed, the support of their neighbours with them, and the bridge one
cell further again. The path model
marks the cells whose evidence changed (``dirty``); the grid applies the rule to their
neighbourhoods when the map is read (occupancy.py), so a live node pays for it at its
publish rate rather than at every sample, and the map read is always the rule applied to
the evidence so far, however the stream was cut into calls.

Why compiled: each cell's plane is a weighted sum over its 343 neighbours and a 3 x 3
eigenproblem; numba keeps that to a few milliseconds for a whole map.
"""

from __future__ import annotations

import math

import numpy as np

from inhand_common.array_types import CellFloats, Indices
from inhand_mapping.occupancy_kernels import _compiled, _inlined
from inhand_mapping.path_kernels import PathModel, _clamp

__all__ = ['BRIDGE_FLATNESS', 'BRIDGE_MIN_TOUCHES', 'LAYER_RADIUS', 'NOISE_SHARE', 'SHEET_BREADTH',
           'SHEET_FLATNESS', 'SHEET_MIN_TOUCHES', 'SHEET_OFFSET', 'SUPPORT_COS', 'WEIGHT_CAP',
           'apply_layer', 'bridged_evidence', 'layered_evidence', 'supported_evidence']

LAYER_RADIUS = 3     # cells: the neighbourhood whose evidence gives the local plane
WEIGHT_CAP = 4.0     # touches: a cell weighs at most this much in its neighbours' planes
SHEET_FLATNESS = 0.3   # a sheet's smallest spread is under this share of its middle one
SHEET_OFFSET = 0.75    # cells: how far off the sheet's middle (along n) a cell of it lies
SHEET_BREADTH = 0.5    # and its middle spread over this share of its largest
SHEET_MIN_TOUCHES = 1.0  # touches a cell needs for the sheet's gain (a pass is 1 to 2)
NOISE_SHARE = 0.2    # a cell under this share of the local level counts as the layer
SUPPORT_COS = 0.5    # a neighbour supports a cell within 30 degrees of its plane (cos 60)
BRIDGE_MIN_TOUCHES = 0.5  # touches a cell needs to be bridged (a pass that clipped it)
BRIDGE_FLATNESS = 0.5  # and its plane's smallest spread under this share of its middle one
AIR_TOUCHES = 0.3    # a visited cell with less evidence than this is air the path crossed
AIR_RADIUS = 2       # cells: the air around a cell that says which side of it is open
AIR_COS = 0.3        # a side is open where the air's summed direction leans this far to it
AS_STRONG = 0.95     # a neighbour with this share of a cell's evidence is as strong as it


@_inlined
def _value(evidence: CellFloats, n: int, x: int, y: int, z: int) -> float:
    if x < 0 or y < 0 or z < 0 or x >= n or y >= n or z >= n:
        return 0.0
    return float(evidence[(x * n + y) * n + z])


@_inlined
def _trilinear(evidence: CellFloats, n: int, px: float, py: float, pz: float) -> float:
    """Evidence at a point in cell coordinates (cell centres at whole numbers), linear
    between the 8 cells around it, 0 outside the grid."""
    x0, y0, z0 = math.floor(px), math.floor(py), math.floor(pz)
    fx, fy, fz = px - x0, py - y0, pz - z0
    ix, iy, iz = int(x0), int(y0), int(z0)
    total = 0.0
    for dx in range(2):
        wx = fx if dx else 1.0 - fx
        for dy in range(2):
            wy = fy if dy else 1.0 - fy
            for dz in range(2):
                wz = fz if dz else 1.0 - fz
                w = wx * wy * wz
                if w > 0.0:
                    total += w * _value(evidence, n, ix + dx, iy + dy, iz + dz)
    return total


@_inlined
def _air_lean(evidence: CellFloats, n: int, ix: int, iy: int, iz: int,
              nx: float, ny: float, nz: float) -> float:
    """How far the air around cell (ix, iy, iz) (cells within ``AIR_RADIUS`` the path
    crossed with under ``AIR_TOUCHES``) lies along (nx, ny, nz): the cosine between the sum
    of the unit directions to them and that direction; 0 where there is none."""
    ax = ay = az = 0.0
    r = AIR_RADIUS
    for jx in range(max(ix - r, 0), min(ix + r + 1, n)):
        for jy in range(max(iy - r, 0), min(iy + r + 1, n)):
            for jz in range(max(iz - r, 0), min(iz + r + 1, n)):
                ej = evidence[(jx * n + jy) * n + jz]
                if 0.0 < ej < AIR_TOUCHES and not (jx == ix and jy == iy and jz == iz):
                    dx, dy, dz = float(jx - ix), float(jy - iy), float(jz - iz)
                    length = math.sqrt(dx * dx + dy * dy + dz * dz)
                    ax += dx / length
                    ay += dy / length
                    az += dz / length
    norm = math.sqrt(ax * ax + ay * ay + az * az)
    return (ax * nx + ay * ny + az * nz) / norm if norm > 0.0 else 0.0


@_inlined
def _open_sides(evidence: CellFloats, n: int, ix: int, iy: int, iz: int,
                nx: float, ny: float, nz: float) -> tuple[float, float]:
    """The air's leans (``_air_lean``) around the cell (ix, iy, iz) and around its
    neighbour one step along (nx, ny, nz): the cell's along -n (away from the neighbour) and
    the neighbour's along +n (away from the cell); (0, 0) when the neighbour is outside the
    grid or unvisited."""
    sx, sy, sz = int(round(ix + nx)), int(round(iy + ny)), int(round(iz + nz))
    if sx < 0 or sy < 0 or sz < 0 or sx >= n or sy >= n or sz >= n \
            or not evidence[(sx * n + sy) * n + sz] > 0.0:
        return 0.0, 0.0
    return (_air_lean(evidence, n, ix, iy, iz, -nx, -ny, -nz),
            _air_lean(evidence, n, sx, sy, sz, nx, ny, nz))


@_compiled
def layered_evidence(evidence: CellFloats, n: int, c: int, factor: float, gain: float) -> float:
    """Cell ``c``'s evidence after the layer rule (module docstring): scaled by ``factor``
    when a cell one step along the local normal has more or the cell is under
    ``NOISE_SHARE`` of the local level, by ``gain`` when it is a cell of a flat sheet with
    at least ``SHEET_MIN_TOUCHES``."""
    return _layered(evidence, n, c, factor, gain, np.zeros(3))[0]


@_inlined
def _layered(evidence: CellFloats, n: int, c: int, factor: float, gain: float,
             normal_out: np.ndarray) -> tuple[float, bool]:
    """``layered_evidence``, whether rule 5 may bridge the cell, and the local normal into
    ``normal_out`` (zeros where the rule does not look at the cell)."""
    normal_out[:] = 0.0
    e = evidence[c]
    if not e > 0.0 or (factor == 1.0 and gain == 1.0):
        return float(e), False
    ix, iy, iz = c // (n * n), (c // n) % n, c % n
    r = LAYER_RADIUS
    s0 = 0.0
    s1 = np.zeros(3)
    s2 = np.zeros((3, 3))
    level1 = 0.0   # sums of the evidence and of its square: the local level
    level2 = 0.0
    for jx in range(max(ix - r, 0), min(ix + r + 1, n)):
        for jy in range(max(iy - r, 0), min(iy + r + 1, n)):
            for jz in range(max(iz - r, 0), min(iz + r + 1, n)):
                ej = evidence[(jx * n + jy) * n + jz]
                w = min(ej, WEIGHT_CAP)
                if w > 0.0:
                    level1 += ej
                    level2 += ej * ej
                    d0, d1, d2 = float(jx - ix), float(jy - iy), float(jz - iz)
                    s0 += w
                    s1[0] += w * d0
                    s1[1] += w * d1
                    s1[2] += w * d2
                    s2[0, 0] += w * d0 * d0
                    s2[1, 1] += w * d1 * d1
                    s2[2, 2] += w * d2 * d2
                    s2[0, 1] += w * d0 * d1
                    s2[0, 2] += w * d0 * d2
                    s2[1, 2] += w * d1 * d2
    cov = np.empty((3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[a, b] = s2[a, b] / s0 - (s1[a] / s0) * (s1[b] / s0)
            cov[b, a] = cov[a, b]
    spread, axes = np.linalg.eigh(cov)
    normal = axes[:, 0]
    normal_out[:] = normal
    up = _trilinear(evidence, n, ix + normal[0], iy + normal[1], iz + normal[2])
    down = _trilinear(evidence, n, ix - normal[0], iy - normal[1], iz - normal[2])
    stronger = max(up, down)
    bridgeable = e >= BRIDGE_MIN_TOUCHES and spread[0] < BRIDGE_FLATNESS * spread[1]
    offset = abs(s1[0] * normal[0] + s1[1] * normal[1] + s1[2] * normal[2]) / s0
    on_sheet = e >= SHEET_MIN_TOUCHES and spread[0] < SHEET_FLATNESS * spread[1] \
        and spread[1] > SHEET_BREADTH * spread[2] and offset < SHEET_OFFSET
    # the air around the cell and around its strongest neighbour along n, leaning away from
    # each other: a thin wall's two faces; the cell's away and the neighbour's towards it:
    # the cell is outside the neighbour's surface (both open on its side)
    # (looked at only where one of the two rules can use it: a weaker cell of a sheet, or a
    # neighbour as strong as the cell but no stronger)
    as_strong = AS_STRONG * e <= stronger <= e
    own = other = 0.0
    if factor < 1.0 and ((e < stronger and on_sheet) or as_strong):
        side = 1.0 if up >= down else -1.0
        own, other = _open_sides(evidence, n, ix, iy, iz, side * normal[0], side * normal[1],
                                 side * normal[2])
    if as_strong and own > AIR_COS and -other > AIR_COS:
        # as strong as the surface beside it, and outside it: a hover as slow as the stroke
        # under it
        return float(e * factor), False
    if e < stronger and not (on_sheet and own > AIR_COS and other > AIR_COS):
        # the layer keeps less the weaker it is: what the surface under a hover or the
        # noise of a much-rubbed spot spills into the next cell is a small share of it
        # (factor 1: the layer is off, share and all)
        share = e / stronger if factor < 1.0 else 1.0
        return float(e * factor * share), False
    if e < NOISE_SHARE * level2 / level1:
        return float(e * factor), False
    if on_sheet:
        return float(e * gain), bridgeable
    return float(e), bridgeable


@_inlined
def _mark_around(cells: Indices, count: int, radius: int, evidence: CellFloats, n: int,
                 mark: np.ndarray, out: Indices, start: int) -> int:
    """Append to ``out`` from ``start`` every cell with evidence within ``radius`` of the
    first ``count`` of ``cells`` and not yet in ``mark`` (then marked). Returns the end."""
    end = start
    for k in range(count):
        c = cells[k]
        ix, iy, iz = c // (n * n), (c // n) % n, c % n
        for jx in range(max(ix - radius, 0), min(ix + radius + 1, n)):
            for jy in range(max(iy - radius, 0), min(iy + radius + 1, n)):
                for jz in range(max(iz - radius, 0), min(iz + radius + 1, n)):
                    j = (jx * n + jy) * n + jz
                    if not mark[j] and evidence[j] != 0.0:
                        mark[j] = True
                        out[end] = j
                        end += 1
    return end


@_inlined
def _in_plane(dx: int, dy: int, dz: int, nx: float, ny: float, nz: float) -> bool:
    """Whether the step to a neighbour (dx, dy, dz) lies within ``SUPPORT_COS`` of the plane
    whose normal is ``n`` (zeros: any step does)."""
    along = dx * nx + dy * ny + dz * nz
    return bool(along * along <= SUPPORT_COS ** 2 * (dx * dx + dy * dy + dz * dz))


@_compiled
def supported_evidence(layered: CellFloats, normals: np.ndarray, n: int, c: int,
                       factor: float) -> float:
    """Cell ``c``'s layered evidence held to its support (rule 4 of the module docstring):
    at most its strongest neighbour's within ``SUPPORT_COS`` of its plane (``normals[c]``;
    zeros: any neighbour), or ``factor`` touches if that is more (a cell alone counts as
    one touch of the layer, however often it was touched). ``factor`` 1: the layer is off,
    and so is this."""
    v = layered[c]
    if not v > 0.0 or factor == 1.0:
        return float(v)
    ix, iy, iz = c // (n * n), (c // n) % n, c % n
    nx, ny, nz = normals[c, 0], normals[c, 1], normals[c, 2]
    strongest = factor
    for jx in range(max(ix - 1, 0), min(ix + 2, n)):
        for jy in range(max(iy - 1, 0), min(iy + 2, n)):
            for jz in range(max(iz - 1, 0), min(iz + 2, n)):
                j = (jx * n + jy) * n + jz
                if j == c or not layered[j] > strongest:
                    continue
                if _in_plane(jx - ix, jy - iy, jz - iz, nx, ny, nz):
                    strongest = layered[j]
    return float(min(v, strongest))


@_compiled
def bridged_evidence(supported: CellFloats, bridgeable: np.ndarray, normals: np.ndarray,
                     n: int, c: int, factor: float) -> float:
    """Cell ``c``'s supported evidence bridged (rule 5 of the module docstring): where
    ``bridgeable[c]`` (not the layer, on a surface, ``BRIDGE_MIN_TOUCHES`` or more), at
    least the weaker of two opposite neighbours within ``SUPPORT_COS`` of its plane
    (``normals[c]``) that share a face or an edge with it. ``factor`` 1: the layer is off, and so is this."""
    v = supported[c]
    if factor == 1.0 or not bridgeable[c]:
        return float(v)
    ix, iy, iz = c // (n * n), (c // n) % n, c % n
    if ix == 0 or iy == 0 or iz == 0 or ix == n - 1 or iy == n - 1 or iz == n - 1:
        return float(v)        # no cell beyond the grid's edge to bridge to
    nx, ny, nz = normals[c, 0], normals[c, 1], normals[c, 2]
    # the 13 directions of the 26 neighbours, each with its opposite, but the 4 body
    # diagonals: two cells 8.7 mm apart span too much of a curved surface (the cell
    # between them can lie off it)
    for dx in range(0, 2):
        for dy in range(-1 if dx else 0, 2):
            for dz in range(-1 if dx or dy else 1, 2):
                if dx != 0 and dy != 0 and dz != 0:
                    continue
                if not _in_plane(dx, dy, dz, nx, ny, nz):
                    continue
                span = min(supported[((ix + dx) * n + iy + dy) * n + iz + dz],
                           supported[((ix - dx) * n + iy - dy) * n + iz - dz])
                v = max(v, span)
    return float(v)


@_compiled
def apply_layer(evidence: CellFloats, n: int, factor: float, gain: float, model: PathModel,
                dirty: Indices, n_dirty: int, dirty_mark: np.ndarray, region: Indices,
                layered: CellFloats, bridgeable: np.ndarray, normals: np.ndarray,
                supported: CellFloats, log_odds: CellFloats, probability: CellFloats) -> int:
    """Recompute the layered evidence (``layered``), whether rule 5 applies (``bridgeable``),
    and the local normal (``normals``, (n^3, 3)) of every cell with evidence within
    ``LAYER_RADIUS`` of the first ``n_dirty`` cells of ``dirty``, the support of those and
    of their neighbours (``supported``), then the log-odds and probability of those and
    of their neighbours (eq. 4 at distance 0 on the evidence held to its support and
    bridged, clamped: the path model's own update, path_kernels), and clear their
    ``dirty_mark``. ``region`` is scratch (n^3). Returns how many cells were recomputed."""
    # The union of the dirty cells' neighbourhoods, each cell once: dirty_mark, cleared
    # here, serves as the visited mark (the dirty cells themselves are in the union).
    for k in range(n_dirty):
        dirty_mark[dirty[k]] = False
    changed = _mark_around(dirty, n_dirty, LAYER_RADIUS, evidence, n, dirty_mark, region, 0)
    for k in range(changed):
        j = region[k]
        layered[j], bridgeable[j] = _layered(evidence, n, j, factor, gain, normals[j])
    # A cell's support is its neighbours' layered evidence: one cell further.
    held = _mark_around(region, changed, 1, evidence, n, dirty_mark, region, changed)
    for k in range(held):
        j = region[k]
        supported[j] = supported_evidence(layered, normals, n, j, factor)
    # Its bridge is its neighbours' supported evidence: one cell further again.
    count = _mark_around(region, held, 1, evidence, n, dirty_mark, region, held)
    for k in range(count):
        j = region[k]
        dirty_mark[j] = False
        value = _clamp(model.prior
                       + bridged_evidence(supported, bridgeable, normals, n, j, factor)
                       * model.log_odds_per_touch, model.l_min, model.l_max)
        log_odds[j] = value
        probability[j] = 1.0 / (1.0 + math.exp(-value))
    return count
