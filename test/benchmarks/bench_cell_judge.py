#!/usr/bin/env python3
"""How much a judge of each touched cell could add to the touch map's rules: a measurement,
not part of the map (docs/quality.md, "A learned judge of each cell").

    .venv/bin/python test/benchmarks/hand_sessions.py --set A --output /tmp/hands_a   # and S,
    .venv/bin/python test/benchmarks/hand_sessions.py --set A --seconds 60 --output /tmp/hands_a60
    .venv/bin/python test/benchmarks/bench_cell_judge.py --train /tmp/hands_a,/tmp/hands_s \
        [--check ../shared/data/validation_sessions,/tmp/hands_a60] [--keep DIR] [--jobs 2]

The touch map decides which touched cells are surface by hand-made rules on the path model's
evidence around each cell (inhand_mapping/surface_layer.py). This asks whether the same
evidence holds more than the rules use. Every session of the folders is mapped by
``build_map`` as ``bench_validation.py`` maps it; for each cell with at least half a touch
(the pool: every occupied cell is in it) the script computes scale-free features of its
neighbourhood in the saved ``touch_evidence`` (touched neighbours, unvisited and air cells
around it, the local plane's flatness and the cell's place on it, the evidence one to five
cells along the plane's normal relative to the cell's own, where in the cell its touches were)
and labels it by the truth (surface: its centre within 5 mm of the true surface).

A gradient-boosted classifier (scikit-learn) judges each session, trained on the ``--train``
folders' sessions of other draws (each training session held out in turn, and for a
``--check`` session, every training session of its draw: a 60 s session of set A begins as
its 120 s twin does). The sessions are then scored as ``bench_validation.py`` scores them
(precision >= 0.97, F >= its floor, stray cells <= 1 %) for the shipped map, for the
judge alone at several thresholds, and for the shipped map with the judge's veto (an occupied
cell the judge gives under ``v`` is left out) and rescue (a pool cell it gives over ``r`` is
taken). The classifier is scikit-learn's, installed on first use into ``.sklearn-lib`` (pip
``--target``, without touching .venv; numpy and scipy are .venv's). Sets A and S come from
``hand_sessions.py``.
"""

from __future__ import annotations

import argparse
import importlib
import re
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from scipy import ndimage

from inhand_common.ground_truth import load_truth
from inhand_mapping.map_io import load_npz
from inhand_mapping.occupancy import OccupancyGrid
from inhand_tools.map_quality import map_metrics, one_touch_oracle, surface_truth

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_validation import EXPLORED_RADIUS, FOLDER, meets_targets, score, session_floor

POOL_TOUCHES = 0.5     # cells with at least this evidence are judged (bridge's least)
WEIGHT_CAP = 4.0       # the local plane's weights, as surface_layer.py caps them
AIR_TOUCHES = 0.3      # a visited cell under this is air the path crossed (surface_layer.py)
SKLEARN_LIB = Path(__file__).resolve().parents[2] / '.sklearn-lib'
SKLEARN = ('scikit-learn==1.9.1', 'joblib==1.6.0', 'threadpoolctl==3.8.0', 'narwhals==2.29.0',
           'cloudpickle==3.1.3')
OCCUPIED = 0.8         # the maps' occupied cells: probability over this
SURFACE = 0.005        # m: a cell centre this near the true surface is surface
THRESHOLDS = (0.9, 0.93, 0.95, 0.97)
VETO_RESCUE = ((0.3, None), (None, 0.97), (0.2, 0.97), (0.3, 0.97), (0.3, 0.98))


def _box_sum(grid: np.ndarray, radius: int) -> np.ndarray:
    """Sum over the (2 radius + 1)^3 box around each cell, zero outside the grid."""
    size = 2 * radius + 1
    return np.asarray(ndimage.uniform_filter(grid, size=size, mode='constant') * size ** 3)


def cell_features(grid: OccupancyGrid) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """(feature names, features (N, F), the pool's cell indices (N, 3), the shipped map's
    occupied flags (N,)) of the pool cells of a map (``grid``, as loaded), from its path
    model evidence before the rules (``touch_evidence``)."""
    evidence = np.asarray(grid.touch_evidence, dtype=float)
    n = evidence.shape[0]
    judged = evidence >= POOL_TOUCHES
    pool = np.argwhere(judged)
    i, j, k = pool.T
    e = evidence[i, j, k]
    # the local plane of the 7^3 box (capped evidence as weights), as surface_layer.py fits it
    weight = np.minimum(evidence, WEIGHT_CAP)
    axes = np.indices(evidence.shape).astype(float)
    total = _box_sum(weight, 3)[i, j, k]
    mean = np.stack([_box_sum(weight * axes[a], 3)[i, j, k] for a in range(3)], axis=1) / total[:, None]
    cov = np.empty((len(pool), 3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = (_box_sum(weight * axes[a] * axes[b], 3)[i, j, k] / total
                                           - mean[:, a] * mean[:, b])
    spread, vectors = np.linalg.eigh(cov)
    spread = np.maximum(spread, 1e-9)
    towards = mean - pool                      # the evidence's centroid, from the cell (cells)
    along = np.einsum('ij,ij->i', towards, vectors[:, :, 0])
    normal = vectors[:, :, 0] * np.where(along >= 0, 1.0, -1.0)[:, None]   # towards it

    def evidence_at(steps: float) -> np.ndarray:
        at = np.rint(pool + normal * steps).astype(int)
        inside = ((at >= 0) & (at < n)).all(axis=1)
        out = np.zeros(len(pool))
        out[inside] = evidence[tuple(at[inside].T)]
        return out

    level = _box_sum(evidence ** 2, 3)[i, j, k] / np.maximum(_box_sum(evidence, 3)[i, j, k], 1e-9)
    air = ((evidence > 0) & (evidence < AIR_TOUCHES)).astype(float)
    touched = (evidence >= 1.0).astype(float)
    unvisited = (evidence == 0).astype(float)
    hits = np.maximum(grid.hits[i, j, k], 1).astype(float)
    # where in the cell its touches were, from its centre (cells; 0 for a cell a path crossed
    # between two samples, which holds no touch of its own)
    own = (grid.contact_centroids(judged) - grid.spec.cell_centres(pool)) / grid.spec.resolution
    # the air's summed direction within 2 cells, along the normal
    lean = np.zeros((len(pool), 3))
    for offset in np.argwhere(np.ones((5, 5, 5))) - 2:
        if not offset.any():
            continue
        at = pool + offset
        inside = ((at >= 0) & (at < n)).all(axis=1)
        hit = np.zeros(len(pool), bool)
        hit[inside] = air[tuple(at[inside].T)] > 0
        lean[hit] += offset / np.linalg.norm(offset)
    lean_norm = np.linalg.norm(lean, axis=1)
    strongest = ndimage.maximum_filter(evidence, size=5, mode='constant')[i, j, k]
    lean_along = np.einsum('ij,ij->i', lean, normal) / np.maximum(lean_norm, 1e-9)
    columns = {
        'share_of_level': e / np.maximum(level, 1e-9),
        'share_of_max5': e / np.maximum(strongest, 1e-9),
        **{f'along_{s}': evidence_at(s) / e for s in (1, 2, 3, 4)},
        'along_max': np.max([evidence_at(s) for s in (1, 1.5, 2, 2.5, 3, 4, 5)], axis=0) / e,
        'flatness': spread[:, 0] / spread[:, 1],
        'breadth': spread[:, 1] / spread[:, 2],
        'off_middle': np.abs(along),
        'centroid_distance': np.linalg.norm(towards, axis=1),
        'touches_along': np.einsum('ij,ij->i', own, normal),
        'touches_off_centre': np.linalg.norm(own, axis=1),
        'air_lean': np.where(lean_norm > 0, lean_along, 0.0),
        **{f'air_{r}': _box_sum(air, r)[i, j, k] for r in (1, 2)},
        **{f'unvisited_{r}': _box_sum(unvisited, r)[i, j, k] for r in (1, 2, 3)},
        **{f'touched_{r}': _box_sum(touched, r)[i, j, k] for r in (1, 2, 3)},
        'evidence_per_hit': e / hits,
    }
    occupied = grid.probabilities()[i, j, k] > OCCUPIED
    return list(columns), np.column_stack(list(columns.values())), pool, occupied


def sklearn_ready() -> bool:
    """scikit-learn importable, installed into :data:`SKLEARN_LIB` on first use."""
    sys.path.append(str(SKLEARN_LIB))        # after .venv's own numpy and scipy
    try:
        importlib.import_module('sklearn')
        return True
    except ImportError:
        pass
    print(f'  .. installing {SKLEARN[0]} into {SKLEARN_LIB.name} (this benchmark only)', flush=True)
    done = subprocess.run([sys.executable, '-m', 'pip', 'install', '-q', '--no-deps', '--target',
                           str(SKLEARN_LIB), *SKLEARN])
    if done.returncode != 0:
        print(f'bench_cell_judge: could not install {SKLEARN[0]} (pip exit {done.returncode})',
              file=sys.stderr)
        return False
    importlib.invalidate_caches()
    importlib.import_module('sklearn')
    return True


class Session:
    """One session's map judged: its pool's features, labels and what scores a selection."""

    def __init__(self, bag: Path, maps: Path):
        self.name = bag.name
        truth = load_truth(bag.parent / f'{bag.name}_truth.npz')
        self.surface = surface_truth(truth, EXPLORED_RADIUS)
        grid, _ = load_npz(maps / f'{bag.name}.npz')
        self.names, self.features, pool, self.shipped = cell_features(grid)
        self.centres = grid.spec.cell_centres(pool)
        self.lattice = grid.spec.lattice()
        self.labels = self.surface.distance(self.centres)[0] <= SURFACE
        self.floor = session_floor(bag.name, truth,
                                   one_touch_oracle(self.surface, self.lattice)['fscore_at_5mm'])

    def judged(self, occupied: np.ndarray) -> tuple[bool, float, int]:
        """(targets met, F minus the floor, stray cells) with ``occupied`` pool cells."""
        scores = map_metrics(self.centres, np.where(occupied, 1.0, 0.0), self.lattice, self.surface)
        strays = int(np.count_nonzero(occupied & ~self.labels))
        share = strays / max(int(np.count_nonzero(occupied)), 1)
        met = meets_targets(scores['precision_at_5mm'], scores['fscore_at_5mm'], self.floor, share)
        return met, scores['fscore_at_5mm'] - self.floor, strays


def classifier(sessions: list[Session]):
    """A gradient-boosted classifier of surface cells, each session weighted alike."""
    from sklearn.ensemble import HistGradientBoostingClassifier
    features = np.vstack([s.features for s in sessions])
    labels = np.concatenate([s.labels for s in sessions])
    weights = np.concatenate([np.full(len(s.labels), len(labels) / len(s.labels) / len(sessions))
                              for s in sessions])
    model = HistGradientBoostingClassifier(max_iter=150, learning_rate=0.08, max_leaf_nodes=15,
                                           l2_regularization=1.0, random_state=0)
    return model.fit(features, labels, sample_weight=weights)


def mapped(folder: Path, maps: Path, jobs: int) -> list[Session]:
    """The folder's sessions, each mapped by build_map into ``maps`` (a kept map is reused)."""
    bags = sorted(p for p in folder.iterdir() if p.is_dir() and (p.parent / f'{p.name}_truth.npz').exists())
    out = maps / folder.name
    out.mkdir(parents=True, exist_ok=True)
    todo = [b for b in bags if not (out / f'{b.name}.npz').exists()]
    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        list(pool.map(lambda bag: score(bag, out, []), todo))
    return [Session(b, out) for b in bags]


def report(label: str, groups: dict[str, tuple[list[Session], list[np.ndarray]]],
           choose: Callable[[Session, np.ndarray], np.ndarray]) -> None:
    cells = []
    for name, (sessions, probabilities) in groups.items():
        results = [s.judged(choose(s, p)) for s, p in zip(sessions, probabilities)]
        margins = [r[1] for r in results]
        cells.append(f'{name}: {sum(r[0] for r in results):2d} of {len(results):2d} met, F - floor '
                     f'{min(margins):+.3f} / {np.mean(margins):+.3f}, {sum(r[2] for r in results):4d} strays')
    print(f'{label:30s} ' + ' | '.join(cells), flush=True)


def draw(name: str) -> str:
    """A session's name without its length: the 60 s and 120 s sessions of one draw of
    ``hand_sessions.py`` share their start, so one must not judge the other."""
    return re.sub(r'_T[\d.]+_', '_', name)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--train', required=True,
                        help='comma-separated session folders (hand_sessions.py sets) to learn on')
    parser.add_argument('--check', default=str(FOLDER),
                        help='comma-separated folders judged by the classifier of the training '
                             'sessions (without those of the same draw)')
    parser.add_argument('--keep', type=Path, help='keep the maps in this folder (and reuse them)')
    parser.add_argument('--jobs', type=int, default=2)
    args = parser.parse_args()
    folders = [Path(f) for f in args.train.split(',')]
    checks = [Path(f) for f in args.check.split(',')]
    missing = [str(f) for f in folders + checks if not f.is_dir()]
    if missing:
        print(f'bench_cell_judge: no session folder at {", ".join(missing)} (hand_sessions.py '
              'writes sets A and S; the validation sessions come with the shared data)',
              file=sys.stderr)
        return 2
    if not sklearn_ready():
        return 2
    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix='bench_cell_judge_') as scratch:
        maps = args.keep or Path(scratch)
        train = {f.name: mapped(f, maps, args.jobs) for f in folders}
        check = {f.name: mapped(f, maps, args.jobs) for f in checks}
    everyone = [s for v in train.values() for s in v]
    print(f'# {len(everyone)} training sessions, {sum(len(v) for v in check.values())} to check; '
          f'{sum(len(s.labels) for s in everyone)} pool cells to learn on; mapped in '
          f'{time.monotonic() - started:.0f} s', flush=True)
    models = {}      # by the draws left out

    def judge(session: Session) -> np.ndarray:
        """The probabilities of ``session``'s pool cells by the classifier of the training
        sessions of other draws."""
        left_out = frozenset(s.name for s in everyone if draw(s.name) == draw(session.name))
        if left_out not in models:
            models[left_out] = classifier([s for s in everyone if s.name not in left_out])
            print(f'  [{len(models)}] a classifier without {", ".join(sorted(left_out)) or "none"}',
                  file=sys.stderr, flush=True)
        return np.asarray(models[left_out].predict_proba(session.features)[:, 1])

    groups = {name: (v, [judge(s) for s in v]) for name, v in {**train, **check}.items()}
    print('# each session judged by the classifier of the training sessions of other draws')
    report('shipped', groups, lambda s, p: s.shipped)
    for t in THRESHOLDS:
        report(f'the judge alone, p > {t}', groups, lambda s, p, t=t: p > t)
    for veto, rescue in VETO_RESCUE:
        label = ' and '.join(x for x in (f'veto p < {veto}' if veto else '',
                                         f'rescue p > {rescue}' if rescue else '') if x)

        def choose(s: Session, p: np.ndarray, veto=veto, rescue=rescue) -> np.ndarray:
            kept = s.shipped & (p >= veto) if veto else s.shipped.copy()
            return kept | (p > rescue) if rescue else kept
        report(f'shipped, {label}', groups, choose)
    print(f'\n{time.monotonic() - started:.0f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
