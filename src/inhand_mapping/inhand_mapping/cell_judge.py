"""The cell judge: a learned second opinion on each touched cell of the touch map.

The surface layer (surface_layer.py) decides by hand-made rules which touched cells are the
object's surface. The same evidence holds more than the rules use: how many neighbours were
touched and how many were never visited, how flat the evidence around a cell lies and where
on that sheet the cell is, how much evidence lies one to five cells along the sheet's
normal, where in the cell its touches were. The judge reads those 23 numbers for every cell
with at least ``POOL_TOUCHES`` of path-model evidence (the pool: every cell the rules could
make occupied) and gives the probability that the cell is surface, from a gradient-boosted
tree ensemble learned on simulated sessions of two different hands (the docs' sets A and S:
``test/benchmarks/bench_cell_judge.py --export`` writes :data:`MODEL_FILE`).

It is sure only at its ends, and only there it overrides the rules (``apply``):

- **veto**: a cell it gives under ``VETO`` (0.3) takes the judge's probability where the
  rules gave it more, and is not occupied (a hover, a lift, the layer the rules let through)
  -- but only where its neighbourhood was explored (at most ``VETO_UNVISITED`` of the 343
  cells of its 7^3 box never visited). A trace alone in unexplored space has no surface
  beside it to be told from; the judge learned on sessions explored for minutes, where such
  a trace is mostly a lift, and vetoed the true cells of a sparse session (a sphere slid
  over from spot to spot for 6 s: 59 occupied cells, none off the surface, 23 vetoed at p
  0.001-0.28). There the rules' judgement stands;
- **rescue**: a pool cell it gives over ``RESCUE`` (0.97) takes the judge's probability
  where the rules gave it less, and is occupied (a thinly touched stretch of surface the
  rules' sheet test held back, a wall's other side).

Every cell in between keeps the rules' probability. The features are ratios and counts of
cells, not lengths or speeds: they do not depend on the cell size, the sampling rate or the
stroke speed. What the judge does on hands it never saw is measured on the independent
generator's sessions (docs/quality.md, "The cell judge").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from inhand_common.contact_centroids import centroids
from inhand_common.log_odds import logit
from inhand_common.log_odds import probability as probability_of
from inhand_mapping.occupancy_kernels import _compiled

POOL_TOUCHES = 0.5     # cells with at least this evidence are judged (the bridge's least)
WEIGHT_CAP = 4.0       # the local plane's weights, capped as surface_layer.py caps them
AIR_TOUCHES = 0.3      # a visited cell under this is air the path crossed (surface_layer.py)
PLANE_RADIUS = 3       # cells: the local plane of the 7^3 box, as surface_layer.py fits it
REACH = 5              # cells: the furthest a feature reads (the evidence 5 along the normal)
BATCH = 2_000          # changed cells over which judging every pool cell is the cheaper
VETO = 0.3             # a cell the judge gives under this takes its probability (a veto) ...
VETO_UNVISITED = 300   # ... where at most this many of its 7^3 box were never visited
RESCUE = 0.97          # a pool cell the judge gives over this takes its probability too
MODEL_FILE = Path(__file__).resolve().parent / 'cell_judge_model.npz'

FEATURES = (
    'share_of_level', 'share_of_max5', 'along_1', 'along_2', 'along_3', 'along_4', 'along_max',
    'flatness', 'breadth', 'off_middle', 'centroid_distance', 'touches_along',
    'touches_off_centre', 'air_lean', 'air_1', 'air_2', 'unvisited_1', 'unvisited_2',
    'unvisited_3', 'touched_1', 'touched_2', 'touched_3', 'evidence_per_hit')

Indices = NDArray[np.intp]


# What _neighbourhood_sums gives per pool cell, by column.
_SUMS = ('weight', 'wx', 'wy', 'wz', 'wxx', 'wxy', 'wxz', 'wyy', 'wyz', 'wzz', 'squares', 'total',
         'air_1', 'air_2', 'unvisited_1', 'unvisited_2', 'unvisited_3', 'touched_1',
         'touched_2', 'touched_3', 'max5', 'lean_x', 'lean_y', 'lean_z')
_COLUMN = {name: column for column, name in enumerate(_SUMS)}


@_compiled
def _neighbourhood_sums(evidence: NDArray[np.float64], pool: NDArray[np.int64],
                        sums: NDArray[np.float64]) -> None:
    """``sums[m]`` (columns: ``_SUMS``) of pool cell ``pool[m]`` over the cells around it
    inside the grid (nothing beyond its faces): the capped evidence's weight and moments
    over the 7^3 box (offsets in cells from the cell), the sums of e^2 and of e there, the
    air, unvisited and touched cells within 1-3 cells (Chebyshev), the strongest evidence
    within 2, and the air's summed unit directions within 2."""
    n0, n1, n2 = evidence.shape
    for m in range(pool.shape[0]):
        i, j, k = pool[m, 0], pool[m, 1], pool[m, 2]
        # locals, not the row: numba keeps them in registers
        w0 = wx = wy = wz = wxx = wxy = wxz = wyy = wyz = wzz = squares = total = 0.0
        strongest = lean_x = lean_y = lean_z = 0.0
        # counts by the Chebyshev distance they lie at (0-3), summed into "within r" below
        unvisited = np.zeros(4)
        touched = np.zeros(4)
        air = np.zeros(4)
        for dx in range(-PLANE_RADIUS, PLANE_RADIUS + 1):
            x = i + dx
            if x < 0 or x >= n0:
                continue
            for dy in range(-PLANE_RADIUS, PLANE_RADIUS + 1):
                y = j + dy
                if y < 0 or y >= n1:
                    continue
                for dz in range(-PLANE_RADIUS, PLANE_RADIUS + 1):
                    z = k + dz
                    if z < 0 or z >= n2:
                        continue
                    v = evidence[x, y, z]
                    w = min(v, WEIGHT_CAP)
                    w0 += w
                    wx += w * dx
                    wy += w * dy
                    wz += w * dz
                    wxx += w * dx * dx
                    wxy += w * dx * dy
                    wxz += w * dx * dz
                    wyy += w * dy * dy
                    wyz += w * dy * dz
                    wzz += w * dz * dz
                    squares += v * v
                    total += v
                    reach = max(abs(dx), abs(dy), abs(dz))
                    if v == 0.0:
                        unvisited[reach] += 1.0
                    elif v >= 1.0:
                        touched[reach] += 1.0
                    elif v < AIR_TOUCHES:
                        air[reach] += 1.0
                        if 0 < reach <= 2:
                            norm = math.sqrt(dx * dx + dy * dy + dz * dz)
                            lean_x += dx / norm
                            lean_y += dy / norm
                            lean_z += dz / norm
                    if reach <= 2 and v > strongest:
                        strongest = v
        row = sums[m]
        row[0], row[1], row[2], row[3] = w0, wx, wy, wz
        row[4], row[5], row[6], row[7], row[8], row[9] = wxx, wxy, wxz, wyy, wyz, wzz
        row[10], row[11] = squares, total
        row[12] = air[0] + air[1]
        row[13] = row[12] + air[2]
        row[14] = unvisited[0] + unvisited[1]
        row[15] = row[14] + unvisited[2]
        row[16] = row[15] + unvisited[3]
        row[17] = touched[0] + touched[1]
        row[18] = row[17] + touched[2]
        row[19] = row[18] + touched[3]
        row[20], row[21], row[22], row[23] = strongest, lean_x, lean_y, lean_z


def pool_features(evidence: ArrayLike, hits: ArrayLike, contact_sum: ArrayLike,
                  origin: ArrayLike, resolution: float, cells: ArrayLike | None = None
                  ) -> tuple[Indices, NDArray[np.float64]]:
    """(the pool's cell indices (N, 3), their features (N, len(FEATURES))) of a touch map:
    its path-model ``evidence`` (n, n, n, touches, before the surface layer), ``hits``
    (n, n, n) and ``contact_sum`` (n, n, n, 3: the sum of the hits' positions, m) on the
    grid of cells of edge ``resolution`` from ``origin`` (3,). ``cells`` (N, 3): these pool
    cells only (default: all). A cell's features read the evidence within ``REACH`` cells
    of it and its own hits."""
    evidence = np.ascontiguousarray(evidence, dtype=np.float64)
    pool = (np.argwhere(evidence >= POOL_TOUCHES) if cells is None
            else np.asarray(cells, dtype=np.intp).reshape(-1, 3))
    if len(pool) == 0:
        return pool, np.empty((0, len(FEATURES)))
    sums = np.empty((len(pool), len(_SUMS)))
    _neighbourhood_sums(evidence, pool.astype(np.int64), sums)
    column = {name: sums[:, c] for name, c in _COLUMN.items()}
    i, j, k = pool.T
    e = evidence[i, j, k]
    shape = np.array(evidence.shape)

    # the local plane of the 7^3 box (capped evidence as weights), as surface_layer.py fits it
    weight = column['weight']
    towards = sums[:, 1:4] / weight[:, None]   # the evidence's centroid, from the cell (cells)
    cov = np.empty((len(pool), 3, 3))
    moments = iter(range(4, 10))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = (sums[:, next(moments)] / weight
                                           - towards[:, a] * towards[:, b])
    spread, vectors = np.linalg.eigh(cov)
    spread = np.maximum(spread, 1e-9)
    along = np.einsum('ij,ij->i', towards, vectors[:, :, 0])
    normal = vectors[:, :, 0] * np.where(along >= 0, 1.0, -1.0)[:, None]   # towards it

    def evidence_at(steps: float) -> NDArray[np.float64]:
        at = np.rint(pool + normal * steps).astype(np.int64)
        inside = ((at >= 0) & (at < shape)).all(axis=1)
        out = np.zeros(len(at))
        out[inside] = evidence[tuple(at[inside].T)]
        return out

    along_normal = {s: evidence_at(s) for s in (1, 1.5, 2, 2.5, 3, 4, 5)}

    level = column['squares'] / np.maximum(column['total'], 1e-9)
    # where in the cell its touches were, from its centre (cells; 0 for a cell a path
    # crossed between two samples, which holds no hit of its own)
    pool_hits = np.asarray(hits)[i, j, k]
    centres = np.asarray(origin, dtype=float) + (pool + 0.5) * resolution
    own = (centroids(centres, np.asarray(contact_sum)[i, j, k], pool_hits) - centres) / resolution
    cell_hits = np.maximum(pool_hits, 1).astype(float)
    # the air's summed direction within 2 cells, along the normal
    lean = sums[:, 21:24]
    lean_norm = np.linalg.norm(lean, axis=1)
    strongest = column['max5']
    lean_along = np.einsum('ij,ij->i', lean, normal) / np.maximum(lean_norm, 1e-9)
    columns = {
        'share_of_level': e / np.maximum(level, 1e-9),
        'share_of_max5': e / np.maximum(strongest, 1e-9),
        **{f'along_{s}': along_normal[s] / e for s in (1, 2, 3, 4)},
        'along_max': np.max(list(along_normal.values()), axis=0) / e,
        'flatness': spread[:, 0] / spread[:, 1],
        'breadth': spread[:, 1] / spread[:, 2],
        'off_middle': np.abs(along),
        'centroid_distance': np.linalg.norm(towards, axis=1),
        'touches_along': np.einsum('ij,ij->i', own, normal),
        'touches_off_centre': np.linalg.norm(own, axis=1),
        'air_lean': np.where(lean_norm > 0, lean_along, 0.0),
        **{f'{kind}_{r}': column[f'{kind}_{r}'] for kind in ('air', 'unvisited', 'touched')
           for r in (1, 2, 3) if kind != 'air' or r < 3},
        'evidence_per_hit': e / cell_hits,
    }
    assert tuple(columns) == FEATURES
    return pool, np.column_stack(list(columns.values()))


@dataclass(frozen=True, eq=False)
class TreeEnsemble:
    """A binary classifier of gradient-boosted decision trees, as flat arrays: node ``m``
    of any tree sends a row to ``left[m]`` when its feature ``feature[m]`` is at most
    ``threshold[m]``, else to ``right[m]``; a leaf points to itself and adds ``value[m]``.
    ``roots`` (T,) are the trees' first nodes; the probability is the logistic of
    ``baseline`` plus the leaves' values. Links go to later nodes only, so a walk ends."""

    feature: NDArray[np.int64]
    threshold: NDArray[np.float64]
    left: NDArray[np.int64]
    right: NDArray[np.int64]
    value: NDArray[np.float64]
    roots: NDArray[np.int64]
    baseline: float
    features: tuple[str, ...]

    def __post_init__(self) -> None:
        nodes = len(self.feature)
        if not (len(self.threshold) == len(self.left) == len(self.right) == len(self.value)
                == nodes) or nodes == 0:
            raise ValueError('tree ensemble: the node arrays differ in length or are empty')
        for name in ('left', 'right', 'roots'):
            links = getattr(self, name)
            if links.size and (links.min() < 0 or links.max() >= nodes):
                raise ValueError(f'tree ensemble: {name} points outside the {nodes} nodes')
        # a walk ends: every link goes to a later node, but a leaf's, to itself (both)
        own = np.arange(nodes)
        leaf = self.left == own
        if ((self.right == own) != leaf).any() or (self.left[~leaf] <= own[~leaf]).any() \
                or (self.right[~leaf] <= own[~leaf]).any():
            raise ValueError('tree ensemble: a link goes back to an earlier node (a cycle)')
        if self.feature.min() < 0 or self.feature.max() >= len(self.features):
            raise ValueError(f'tree ensemble: a feature index outside the {len(self.features)} '
                             'features')

    def probability(self, rows: ArrayLike) -> NDArray[np.float64]:
        """The probability (N,) of the positive class for ``rows`` (N, features)."""
        x = np.ascontiguousarray(rows, dtype=np.float64).reshape(-1, len(self.features))
        raw = np.empty(len(x))
        _leaf_sums(x, self.feature, self.threshold, self.left, self.right, self.value,
                   self.roots, raw)
        return probability_of(self.baseline + raw)

    def save(self, path: str | Path) -> None:
        np.savez_compressed(path, feature=self.feature, threshold=self.threshold,
                            left=self.left, right=self.right, value=self.value,
                            roots=self.roots, baseline=self.baseline,
                            features=np.array(self.features))

    @classmethod
    def load(cls, path: str | Path) -> TreeEnsemble:
        with np.load(path, allow_pickle=False) as data:
            return cls(feature=data['feature'].astype(np.int64),
                       threshold=data['threshold'].astype(float),
                       left=data['left'].astype(np.int64), right=data['right'].astype(np.int64),
                       value=data['value'].astype(float), roots=data['roots'].astype(np.int64),
                       baseline=float(data['baseline']),
                       features=tuple(str(f) for f in data['features']))


@_compiled
def _leaf_sums(x: NDArray[np.float64], feature: NDArray[np.int64],
               threshold: NDArray[np.float64], left: NDArray[np.int64],
               right: NDArray[np.int64], value: NDArray[np.float64],
               roots: NDArray[np.int64], out: NDArray[np.float64]) -> None:
    """``out[r]``: the sum over the trees of the leaf value row ``r`` of ``x`` reaches
    (a tree walk per row and tree: a level per pass over all rows in numpy took 14-43 ms for
    1,300-2,800 cells, this 4-11 ms, while the test suite ran beside it)."""
    for r in range(x.shape[0]):
        total = 0.0
        for t in range(roots.shape[0]):
            node = roots[t]
            while left[node] != node:
                node = left[node] if x[r, feature[node]] <= threshold[node] else right[node]
            total += value[node]
        out[r] = total


_shipped: TreeEnsemble | None = None


def shipped_judge() -> TreeEnsemble:
    """The judge learned for the defaults (:data:`MODEL_FILE`), loaded once."""
    global _shipped
    if _shipped is None:
        model = TreeEnsemble.load(MODEL_FILE)
        if model.features != FEATURES:
            raise ValueError(f'{MODEL_FILE}: its features are not this module\'s FEATURES')
        _shipped = model
    return _shipped


@_compiled
def _pool_near(changed: NDArray[np.int64], evidence: NDArray[np.float64], n: int,
               mark: NDArray[np.bool_], out: NDArray[np.int64]) -> int:
    """Write into ``out`` the flat indices of the pool cells (``POOL_TOUCHES`` or more of
    ``evidence``, flat (n^3,)) within ``REACH`` cells (Chebyshev) of a cell of ``changed``,
    each once; returns how many. ``mark`` (n^3,) is scratch, all False on entry and on
    return."""
    count = 0
    for c in changed:
        ix, iy, iz = c // (n * n), (c // n) % n, c % n
        for x in range(max(ix - REACH, 0), min(ix + REACH + 1, n)):
            for y in range(max(iy - REACH, 0), min(iy + REACH + 1, n)):
                for z in range(max(iz - REACH, 0), min(iz + REACH + 1, n)):
                    j = (x * n + y) * n + z
                    if evidence[j] >= POOL_TOUCHES and not mark[j]:
                        mark[j] = True
                        out[count] = j
                        count += 1
    for k in range(count):
        mark[out[k]] = False
    return count


class CellJudge:
    """The judge's verdicts on one grid's cells, kept up to date as its evidence changes,
    and the map's probabilities they override (occupancy.py calls it around the surface
    layer). The map's arrays it is given, and its own, are flat (n^3,)."""

    def __init__(self, shape: tuple[int, int, int], origin: ArrayLike, resolution: float,
                 judge: TreeEnsemble | None = None):
        self.shape = shape
        self.origin = np.asarray(origin, dtype=float)
        self.resolution = float(resolution)
        self.judge = judge or shipped_judge()
        size = shape[0] * shape[1] * shape[2]
        self.sure = np.full(size, np.nan)       # the judge's probability; NaN: not judged
        self.explored = np.zeros(size, dtype=np.bool_)   # its veto counts (VETO_UNVISITED)
        self._mark = np.zeros(size, dtype=np.bool_)
        self._near = np.empty(size, dtype=np.int64)
        # the cells overridden, with the rules' log-odds and probability they replaced
        self.overridden: Indices = np.empty(0, dtype=np.intp)
        self.rules: NDArray[np.float64] = np.empty(0)
        self.rules_probability: NDArray[np.float64] = np.empty(0)
        self.stale = True                       # every verdict is to be made (again)

    def copy(self) -> CellJudge:
        twin = CellJudge(self.shape, self.origin, self.resolution, self.judge)
        twin.sure[...] = self.sure
        twin.explored[...] = self.explored
        twin.overridden, twin.rules = self.overridden.copy(), self.rules.copy()
        twin.rules_probability = self.rules_probability.copy()
        twin.stale = self.stale
        return twin

    def forget(self) -> None:
        """The map was set from outside (loaded, shown): nothing it holds is overridden,
        and every verdict is to be made again."""
        self.resume(np.empty(0, dtype=np.intp), np.empty(0))

    def resume(self, overridden: ArrayLike, rules: ArrayLike) -> None:
        """The map is one saved with its verdicts: ``overridden`` (flat indices) are the
        cells they set, ``rules`` the log-odds they replaced (``overridden`` and ``rules``
        of the judge that saved it). Every verdict is made again when the map next changes."""
        self.sure.fill(np.nan)
        self.overridden = np.asarray(overridden, dtype=np.intp).reshape(-1)
        self.rules = np.asarray(rules, dtype=np.float64).reshape(-1)
        if len(self.rules) != len(self.overridden):
            raise ValueError(f'{len(self.overridden)} cells overridden but {len(self.rules)} '
                             'log-odds they replaced')
        if len(self.overridden) and (self.overridden.min() < 0
                                     or self.overridden.max() >= len(self.sure)):
            raise ValueError(f'a cell overridden outside the {len(self.sure)} cells')
        if not np.isfinite(self.rules).all():
            raise ValueError('the log-odds the verdicts replaced hold NaN or infinity')
        self.rules_probability = probability_of(self.rules)
        self.stale = True

    def undo(self, log_odds: NDArray[np.float64], probability: NDArray[np.float64]) -> None:
        """Put the rules' log-odds and probability back where the judge overrode them."""
        log_odds[self.overridden] = self.rules
        probability[self.overridden] = self.rules_probability

    def update(self, evidence: NDArray[np.float64], hits: ArrayLike, contact_sum: ArrayLike,
               changed: NDArray[np.int64]) -> None:
        """Judge again the pool cells within ``REACH`` of the ``changed`` cells (flat) of
        ``evidence`` (flat, n^3), all of them when there are many; a cell that left the
        pool is no longer judged."""
        if self.stale or len(changed) > BATCH:
            cells = np.flatnonzero(evidence >= POOL_TOUCHES)
            self.sure.fill(np.nan)
            self.stale = False
        else:
            cells = self._near[:_pool_near(changed, evidence, self.shape[0], self._mark,
                                           self._near)].copy()
            gone = changed[~(evidence[changed] >= POOL_TOUCHES)]
            self.sure[gone] = np.nan
        if len(cells) == 0:
            return
        ijk = np.stack(np.unravel_index(cells, self.shape), axis=1)
        _, rows = pool_features(evidence.reshape(self.shape), hits, contact_sum, self.origin,
                                self.resolution, cells=ijk)
        self.sure[cells] = self.judge.probability(rows)
        self.explored[cells] = explored(rows)

    def apply(self, log_odds: NDArray[np.float64], probability: NDArray[np.float64],
              clamp: tuple[float, float]) -> None:
        """Override the rules' probability (``probability``, with ``log_odds``) where the
        judge is sure, with its own held to ``clamp`` (the map's lowest and highest): under
        ``VETO`` where the rules gave more and the cell's neighbourhood was explored, over
        ``RESCUE`` where they gave less."""
        judged = np.flatnonzero(~np.isnan(self.sure))
        overridden, verdict = verdicts(self.sure[judged], self.explored[judged],
                                       probability[judged], clamp)
        self.overridden = judged[overridden]
        self.rules = log_odds[self.overridden].copy()
        self.rules_probability = probability[self.overridden].copy()
        log_odds[self.overridden] = logit(verdict)
        probability[self.overridden] = probability_of(log_odds[self.overridden])


def explored(rows: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether the neighbourhood of each cell of ``rows`` (features) was explored enough
    for a veto: at most ``VETO_UNVISITED`` of its 7^3 box never visited."""
    return np.asarray(rows[:, FEATURES.index('unvisited_3')] <= VETO_UNVISITED)


def verdicts(sure: NDArray[np.float64], explored: NDArray[np.bool_], rules: NDArray[np.float64],
             clamp: tuple[float, float], veto: float = VETO, rescue: float = RESCUE
             ) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """(which cells the judge overrides, their probabilities (held to ``clamp``)) of cells
    it gives ``sure``, their neighbourhoods ``explored`` (``VETO_UNVISITED``) and the rules
    giving them ``rules``: under ``veto`` where explored and the rules gave more, over
    ``rescue`` where the rules gave less."""
    verdict = np.clip(sure, *clamp)
    # (a cell at the clamp already is left alone: 0.97 and 0.9699999999999999 are one)
    overridden = (((sure < veto) & explored & (rules > verdict + 1e-9))
                  | ((sure > rescue) & (rules < verdict - 1e-9)))
    return overridden, verdict[overridden]
