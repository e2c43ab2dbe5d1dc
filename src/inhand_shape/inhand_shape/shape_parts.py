"""The occupied cells as one or several superquadric parts, or a clear reason for none.

Each part is searched for in the cells no part has taken yet (the *pool*, at first all of
them) with the robust fit (:func:`inhand_shape.superquadric.fit_superquadric`): the fit of
the whole pool when it explains :data:`WHOLE_SHARE` of it, else the best of fits grown from
:data:`SEEDS` compact seeds (k-means; fit, take the pool's cells on it, fit again). The cells
on a found part or inside it leave the pool (a cup's inner wall, the far side of a thin
shell), and what is left must hang together (26-connected) to be searched again, up to
:data:`MAX_PARTS`; a new part whose cells all lie within :data:`RIM_REACH` cells of a found
one is that part's rim. Then every cell goes to the part nearest to it and each part is
fitted again on its own cells (a first fit that had to compromise, a cup's body pulled
towards its handle, is redone without the other part), and two parts one superquadric
explains are merged (a shaft cut in two by the holding hand). Every fit but a seed's growth
is held to its cells (the fit's ``reach``: a shape may not reach far past its last cells,
so a strip of a shaft touched on one side is a cylinder, not the face of a deep slab the
support check then refuses); a growing seed is free to reach past them, since that is where
the rest of its part is. Last, each part is fitted once more to its nearest cells with their
slack (``CELL_SLACK``, superquadric.py: "cells, not points"), or, given where in each cell
the touches were (``surface_points``, the map's contact centroids), to those, as points on
the surface; the search and the part checks run on the cells without either. Polished so,
each part holds the cells nearest to it, and two pieces of one shape that the first merge
could not join (a dumbbell's bar in two, one piece a flat part beside a block) may now be
explained by one superquadric: the merge runs again on them, and a part it makes is
polished in turn (docs/shape.md, "A second merge").

A part is reported only when it explains its cells: :data:`EXPLAINED_SHARE` of them within
one cell width of its surface, :data:`SUPPORTED_SHARE` of its surface within
:data:`SUPPORT_REACH` of them, at least :data:`MIN_PART_CELLS` cells. A map of scattered strays
gives no part, with the reason; so do an empty map, too few cells, and cells that lie in one
plane (a flat plate touched on one side has no thickness to fit).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage  # type: ignore[import-untyped]

from inhand_common.array_types import Points, Vector3, Weights
from inhand_common.cell_lattice import Lattice, cell_indices
from inhand_shape.superquadric import CELL_SLACK, REACH_WEIGHT, FitResult, Superquadric, fit_superquadric

__all__ = ['EXPLAINED_SHARE', 'MAX_PARTS', 'MIN_PART_CELLS', 'Decomposition', 'Part',
           'decompose']

MAX_PARTS = 5
MIN_PART_CELLS = 25        # fewer cells than this cannot be told from strays
MIN_PART_SHARE = 0.03      # ... nor can a group of less than this share of the cells
EXPLAINED_SHARE = 0.6      # a part must have this share of its cells on or in it
FLAT_SPREAD = 0.35         # cells: below this spread across their thinnest axis, a sheet
REFITS = 2                 # rounds of assign-to-nearest and fit again
WHOLE_SHARE = 0.85         # a fit of all the cells that explains this share is the part
SEEDS = 4                  # compact seeds tried otherwise
GROW_ROUNDS = 2            # fit, take the cells on it, fit again
SUPPORTED_SHARE = 0.7      # of a part's surface must lie near its cells ...
SUPPORT_REACH = 0.02       # m: ... within this (an untouched side of a small part is near)
SUPPORT_SAMPLES = 500
RIM_REACH = 2.0            # cells: a new part this close to a found one, all of it, ...
RIM_SHARE = 0.8            # ... (this share of its cells) is that part's rim
MERGE_SHARE = 0.85         # of each of two parts' cells one superquadric must explain to merge them


@dataclass(frozen=True, eq=False)
class Part:
    """One superquadric part: its fit, the cells it explains (indices into the map's
    occupied cells) and how well."""

    superquadric: Superquadric
    cells: NDArray[np.intp]
    residual: float        # m, probability-weighted RMS distance of its inlier cells
    explained: float       # share of its cells within tolerance or inside
    sigma: float           # m, the surface's fitted spread


@dataclass(frozen=True, eq=False)
class Decomposition:
    """The parts (largest first), the cells no part explains, and why there is no part
    when there is none (``reason``; None when there are parts)."""

    parts: list[Part]
    unexplained: NDArray[np.intp]
    reason: str | None = None
    total_cells: int = 0


def on_surface(fit: FitResult, points: Points, resolution: float) -> NDArray[np.bool_]:
    """Cells on the fitted surface: within one cell width."""
    return np.asarray(fit.superquadric.surface_distance(points) <= resolution)


def supported(sq: Superquadric, points: Points) -> float:
    """Share of the superquadric's surface within :data:`SUPPORT_REACH` of a cell: a shape
    that lays one face on the cells and spreads far past them is not what they show."""
    from scipy.spatial import cKDTree  # type: ignore[import-untyped]
    samples = sq.surface_samples(SUPPORT_SAMPLES, np.random.default_rng(0))
    distance, _ = cKDTree(points).query(samples, distance_upper_bound=SUPPORT_REACH)
    return float(np.mean(np.isfinite(distance)))


def _groups(points: Points, members: NDArray[np.intp], resolution: float) -> list[NDArray[np.intp]]:
    """``members`` split into 26-connected groups of cells, largest first."""
    if len(members) == 0:
        return []
    index = cell_indices(points[members], Lattice(resolution))
    low = index.min(axis=0)
    grid = np.zeros(tuple(index.max(axis=0) - low + 1), dtype=bool)
    grid[tuple((index - low).T)] = True
    labels, count = ndimage.label(grid, structure=np.ones((3, 3, 3), dtype=bool))
    label_of = labels[tuple((index - low).T)]
    groups = [members[label_of == k] for k in range(1, count + 1)]
    return sorted(groups, key=len, reverse=True)


def _sheet_reason(points: Points, resolution: float) -> str | None:
    """Why cells lying in one plane cannot be a solid part, or None."""
    centred = points - points.mean(axis=0)
    spreads = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(centred.T)), 0.0))
    if spreads[0] < FLAT_SPREAD * resolution:
        return (f'the {len(points)} occupied cells lie in one plane (spread '
                f'{spreads[0] * 1000:.1f} mm across it, {spreads[2] * 1000:.0f} mm along it): a sheet '
                'has no thickness to fit a solid part to; explore the other side or the edges')
    return None


def _fit_part(points: Points, weights: Weights, members: NDArray[np.intp], resolution: float,
              start: Superquadric | None = None, reach: float = REACH_WEIGHT, slack: float = 0.0,
              alternatives: bool = False, up: Vector3 | None = None) -> tuple[Part | None, FitResult]:
    """The part fitted to ``members`` (None when it does not explain them), and the fit;
    ``start``, ``reach``, ``slack``, ``alternatives`` and ``up`` as for
    :func:`fit_superquadric`."""
    fit = fit_superquadric(points[members], weights[members], resolution=resolution, start=start,
                           reach=reach, slack=slack, alternatives=alternatives, up=up)
    # only the cells on the surface vouch for it: a shape large enough to hold every cell
    # explains nothing
    surface = fit.distances <= resolution     # on_surface of the cells it was fitted to
    share = float(np.average(surface, weights=weights[members]))
    if share < EXPLAINED_SHARE or supported(fit.superquadric, points[members]) < SUPPORTED_SHARE:
        return None, fit
    return Part(fit.superquadric, members[surface], fit.residual, share, fit.sigma), fit


def _seeds(points: Points, members: NDArray[np.intp], count: int) -> list[NDArray[np.intp]]:
    """``members`` cut into ``count`` compact groups (k-means on position, fixed seed)."""
    from scipy.cluster.vq import kmeans2  # type: ignore[import-untyped]
    if count < 2:
        return [members]
    _, label = kmeans2(points[members], count, seed=0, minit='++')
    return [members[label == k] for k in range(count) if np.count_nonzero(label == k) >= 10]


def _grown(points: Points, weights: Weights, pool: NDArray[np.intp], seed: NDArray[np.intp],
           resolution: float, smallest: int) -> Part | None:
    """A part started on ``seed`` and grown over the cells of ``pool`` on its surface."""
    members = seed
    part: Part | None = None
    for _ in range(GROW_ROUNDS):
        # free to reach past the seed: growing is finding the rest of its part there
        candidate, fit = _fit_part(points, weights, members, resolution,
                                   None if part is None else part.superquadric, reach=0.0)
        if candidate is None:
            return part
        part = candidate
        grown = pool[on_surface(fit, points[pool], resolution)]
        if len(grown) < smallest or np.array_equal(grown, members):
            break
        members = grown
    return part


def _is_rim(part: Part, found: list[Part], points: Points, resolution: float) -> bool:
    """Whether nearly all of ``part``'s cells lie within :data:`RIM_REACH` cells of a part
    already found."""
    return bool(found) and float(_near_found(points[part.cells], found, resolution).mean()) >= RIM_SHARE


def _near_found(points: Points, found: list[Part], resolution: float) -> NDArray[np.bool_]:
    """Which points lie within :data:`RIM_REACH` cells of a found part's surface."""
    near = np.zeros(len(points), dtype=bool)
    for other in found:
        near |= other.superquadric.surface_distance(points) <= RIM_REACH * resolution
    return near


def _next_part(points: Points, weights: Weights, pool: NDArray[np.intp], resolution: float,
               smallest: int) -> Part | None:
    """The part that explains most of ``pool``: the fit of all of it when that explains
    nearly all, else the best grown from a few compact seeds."""
    whole, _ = _fit_part(points, weights, pool, resolution)
    if whole is not None and len(whole.cells) >= WHOLE_SHARE * len(pool):
        return whole
    # a shape through all of them that leaves many out is a compromise between parts: the
    # seeds compete without it, and it is kept only when no seed gives a part
    best: Part | None = None
    for seed in _seeds(points, pool, min(SEEDS, len(pool) // smallest)):
        part = _grown(points, weights, pool, seed, resolution, smallest)
        if part is not None and (best is None or len(part.cells) > len(best.cells)):
            best = part
    return best if best is not None else whole


def decompose(points: ArrayLike, weights: ArrayLike | None = None, *, resolution: float = 0.005,
              max_parts: int = MAX_PARTS, slack: float | None = None,
              surface_points: ArrayLike | None = None, up: ArrayLike | None = None) -> Decomposition:
    """The parts of the cells at ``points`` (N, 3) m weighted by ``weights`` (occupancy
    probabilities), as the module doc describes; ``max_parts`` = 1 fits one superquadric;
    ``slack`` as for :func:`fit_superquadric` (0 for points on the surface), used by the
    final fit of each part. ``surface_points`` (N, 3) m: where in each cell the surface was
    measured (the map's contact centroids, the cell's centre where it has none); the final
    fit of each part then takes them, as points on the surface (no slack). ``up`` (3,): the
    object stands on a support whose normal this is (a static map): the final fit of each
    part may hold it upright (:func:`fit_superquadric`; the search stays free, so that a
    shape resting on a face keeps the pose its cells show)."""
    cells = np.asarray(points, dtype=float).reshape(-1, 3)
    held = None if up is None else np.asarray(up, dtype=float).reshape(3)
    measured = None
    if surface_points is not None:
        measured = np.asarray(surface_points, dtype=float).reshape(-1, 3)
        if measured.shape != cells.shape:
            raise ValueError(f'{len(measured)} surface points for {len(cells)} cells')
    w = np.ones(len(cells)) if weights is None else np.asarray(weights, dtype=float)
    everything = np.arange(len(cells))
    if len(cells) == 0:
        return Decomposition([], everything, 'the map has no occupied cells: nothing to fit', 0)
    if len(cells) < MIN_PART_CELLS:
        return Decomposition([], everything, f'only {len(cells)} occupied cells: a part needs at '
                             f'least {MIN_PART_CELLS}', len(cells))
    sheet = _sheet_reason(cells, resolution)
    if sheet is not None:
        return Decomposition([], everything, sheet, len(cells))
    smallest = max(MIN_PART_CELLS, int(MIN_PART_SHARE * len(cells)))
    parts: list[Part] = []
    pool = everything
    while len(parts) < max_parts and len(pool) >= smallest and not _sheet_reason(cells[pool], resolution):
        if _near_found(cells[pool], parts, resolution).mean() >= RIM_SHARE:
            break           # what is left is the found parts' rims, not another part
        part = _next_part(cells, w, pool, resolution, smallest)
        if part is None:
            break
        if _is_rim(part, parts, cells, resolution):
            # cells just off a part already found (its rounded rim, a cap's edge): its own
            pool = np.setdiff1d(pool, part.cells)
            continue
        parts.append(part)
        inside = part.superquadric.contains(cells[pool])
        pool = np.setdiff1d(pool[~inside], part.cells)
        # what is left must hang together to be a part: strays between parts are not one
        pool = np.concatenate([g for g in _groups(cells, pool, resolution) if len(g) >= smallest]
                              or [np.zeros(0, dtype=np.intp)])
    parts = _merged(cells, w, _refit(cells, w, parts, resolution, smallest), resolution)
    polish_slack = 0.0 if measured is not None else CELL_SLACK if slack is None else slack
    if measured is not None or polish_slack > 0.0:
        parts = _polished(cells, w, parts, resolution, polish_slack, measured, held)
        # Polished, each part holds the cells nearest to it: two pieces of one shape cut
        # where the other hand held it (a dumbbell's bar) may show only now that one
        # superquadric explains both.
        merged = _merged(cells, w, parts, resolution)
        if len(merged) < len(parts):
            parts = _polished(cells, w, merged, resolution, polish_slack, measured, held)
    if not parts:
        return Decomposition([], everything, f'no superquadric explains the {len(cells)} occupied '
                             f'cells (at least {EXPLAINED_SHARE:.0%} on it): they look like '
                             'scattered strays, not a surface', len(cells))
    explained = np.zeros(len(cells), dtype=bool)
    for part in parts:
        explained[part.cells] = True
    return Decomposition(parts, everything[~explained], None, len(cells))


def _refit(points: Points, weights: Weights, parts: list[Part], resolution: float,
           smallest: int) -> list[Part]:
    """Each cell to its nearest part (inside counts as distance 0), each part fitted again
    on its own cells; parts left with too few cells or not explaining them are dropped."""
    for _ in range(REFITS if len(parts) > 1 else 0):
        owner = _owners(points, parts)
        refitted = []
        for k in range(len(parts)):
            members = np.flatnonzero(owner == k)
            if len(members) < smallest:
                continue
            part, _ = _fit_part(points, weights, members, resolution, parts[k].superquadric)
            if part is not None:
                refitted.append(part)
        parts = refitted
    return sorted(parts, key=lambda p: len(p.cells), reverse=True)


def _owners(points: Points, parts: list[Part]) -> NDArray[np.intp]:
    """Each cell's nearest part (inside counts as distance 0)."""
    distance = np.stack([np.where(p.superquadric.contains(points), 0.0,
                                  p.superquadric.surface_distance(points)) for p in parts])
    return np.asarray(np.argmin(distance, axis=0))


def _polished(points: Points, weights: Weights, parts: list[Part], resolution: float,
              slack: float, measured: Points | None = None, up: Vector3 | None = None) -> list[Part]:
    """Each part fitted once more to the cells nearest to it, from where it is, with the
    cells' ``slack`` (:func:`fit_superquadric`), or to where in them the surface was
    ``measured`` (then points on the surface); the part as it was where that fit does not
    explain its cells (``up`` as for :func:`fit_superquadric`)."""
    if (slack <= 0.0 and measured is None) or not parts:
        return parts
    owner = _owners(points, parts)
    polished = []
    for k, part in enumerate(parts):
        members = np.flatnonzero(owner == k)
        better = None
        if len(members) >= MIN_PART_CELLS:
            better, _ = _fit_part(points if measured is None else measured, weights, members,
                                  resolution, part.superquadric, slack=slack,
                                  alternatives=measured is not None, up=up)
        polished.append(part if better is None else better)
    return sorted(polished, key=lambda p: len(p.cells), reverse=True)


def _merged(points: Points, weights: Weights, parts: list[Part], resolution: float) -> list[Part]:
    """Two parts that one superquadric explains as well (:data:`MERGE_SHARE` of each one's
    cells on it, and its surface supported by them) become one: a shape cut in pieces by an
    untouched band (where the other hand held it) is one part. Only parts whose cells come
    within :data:`SUPPORT_REACH` of each other are tried (a shape across a wider gap would
    not be supported), and each pair once."""
    from scipy.spatial import cKDTree
    tried: set[frozenset[int]] = set()
    merged = True
    while merged and len(parts) > 1:
        merged = False
        trees = [cKDTree(points[p.cells]) for p in parts]
        for a in range(len(parts)):
            for b in range(a + 1, len(parts)):
                pair = frozenset((id(parts[a]), id(parts[b])))
                if pair in tried:
                    continue
                tried.add(pair)
                gap, _ = trees[b].query(points[parts[a].cells], distance_upper_bound=SUPPORT_REACH)
                if not np.isfinite(gap).any():
                    continue
                members = np.union1d(parts[a].cells, parts[b].cells)
                part, _ = _fit_part(points, weights, members, resolution)
                if part is not None and all(
                        np.isin(parts[k].cells, part.cells).mean() >= MERGE_SHARE for k in (a, b)):
                    parts = [p for k, p in enumerate(parts) if k not in (a, b)] + [part]
                    merged = True
                    break
            if merged:
                break
    return sorted(parts, key=lambda p: len(p.cells), reverse=True)
