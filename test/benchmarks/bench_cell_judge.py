#!/usr/bin/env python3
"""The touch map's cell judge (inhand_mapping/cell_judge.py): learned here, and measured on
sessions it did not learn from (docs/quality.md, "The cell judge").

    .venv/bin/python test/benchmarks/hand_sessions.py --set A --output /tmp/hands_a   # and S,
    .venv/bin/python test/benchmarks/hand_sessions.py --set A --seconds 60 --output /tmp/hands_a60
    .venv/bin/python test/benchmarks/bench_cell_judge.py --train /tmp/hands_a,/tmp/hands_s \
        [--check ../shared/data/validation_sessions,/tmp/hands_a60] [--keep DIR] [--jobs 2] \
        [--export src/inhand_mapping/inhand_mapping/cell_judge_model.npz] [--set NAME=VALUE ...]

The surface layer (inhand_mapping/surface_layer.py) decides by hand-made rules which touched
cells are surface; the judge overrides it where it is sure. Every session of the folders is
mapped by ``build_map`` as ``bench_validation.py`` maps it, with the rules alone
(``cell_judge`` false). For each cell with at least half a touch (the pool: every occupied
cell is in it), the judge's features (``cell_judge.pool_features``: touched neighbours,
unvisited and air cells around it, the local plane's flatness and the cell's place on it,
the evidence one to five cells along the plane's normal relative to the cell's own, where in
the cell its touches were) are labelled by the truth (surface: its centre within 5 mm of the
true surface).

A gradient-boosted classifier (scikit-learn) judges each session, trained on the ``--train``
folders' sessions of other draws (each training session held out in turn, and for a
``--check`` session, every training session of its draw: a 60 s session of set A begins as
its 120 s twin does). The sessions are then scored as ``bench_validation.py`` scores them
(precision >= 0.97, F >= its floor, stray cells <= 1 %) for the rules' map, for the judge
alone at several thresholds, and for the rules' map with the judge's veto and rescue at
several thresholds (``cell_judge.verdicts``; the map's own marked). ``--export`` writes the
classifier of all the training sessions as the map reads it. The classifier is
scikit-learn's, installed on first use into ``.sklearn-lib`` (pip ``--target``, without
touching .venv; numpy and scipy are .venv's). Sets A and S come from ``hand_sessions.py``.
``--set`` maps every session with another touch model (``build_map --set``), to learn the
judge on its evidence: keep those maps in a ``--keep`` folder of their own.
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

from inhand_common.ground_truth import load_truth
from inhand_mapping.cell_judge import FEATURES, RESCUE, VETO, TreeEnsemble, explored, pool_features, verdicts
from inhand_mapping.map_io import load_npz
from inhand_mapping.occupancy import OccupancyGrid
from inhand_tools.map_quality import map_metrics, one_touch_oracle, surface_truth

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_validation import EXPLORED_RADIUS, FOLDER, meets_targets, score, session_floor

SKLEARN_LIB = Path(__file__).resolve().parents[2] / '.sklearn-lib'
SKLEARN = ('scikit-learn==1.9.1', 'joblib==1.6.0', 'threadpoolctl==3.8.0', 'narwhals==2.29.0',
           'cloudpickle==3.1.3')
OCCUPIED = 0.8         # the maps' occupied cells: probability over this
SURFACE = 0.005        # m: a cell centre this near the true surface is surface
THRESHOLDS = (0.9, 0.93, 0.95, 0.97)
# (veto under, rescue over): the map's rule (cell_judge.py: a veto where the neighbourhood was
# explored) with other thresholds; 0 / 1: none
VETO_RESCUE = ((0.3, 1.0), (0.0, 0.97), (0.3, 0.97), (0.1, 0.97), (0.3, 0.98))


def cell_features(grid: OccupancyGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(features (N, F), the pool's cell indices (N, 3), the rules' probabilities (N,)) of a
    map (``grid``, as loaded, built without the judge) by the judge's own features."""
    pool, features = pool_features(grid.touch_evidence, grid.hits, grid.contact_sum,
                                   grid.spec.origin, grid.spec.resolution)
    return features, pool, grid.probabilities()[tuple(pool.T)]


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
        self.features, pool, self.rules = cell_features(grid)
        self.shipped = self.rules > OCCUPIED
        self.explored = explored(self.features)
        self.clamp = (grid.model.clamp_min, grid.model.clamp_max)
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


def ensemble(model) -> TreeEnsemble:
    """A fitted HistGradientBoostingClassifier as the map's :class:`TreeEnsemble`."""
    trees = [predictors[0].nodes for predictors in model._predictors]
    starts = np.cumsum([0] + [len(t) for t in trees[:-1]])
    nodes = np.concatenate(trees)
    offset = np.repeat(starts, [len(t) for t in trees])
    leaf = nodes['is_leaf'].astype(bool)
    own = np.arange(len(nodes))
    if nodes['is_categorical'].any() or not np.isfinite(nodes['num_threshold'][~leaf]).all():
        raise ValueError('the classifier has categorical or missing-value splits')
    return TreeEnsemble(
        feature=np.where(leaf, 0, nodes['feature_idx']).astype(np.int64),
        threshold=np.where(leaf, 0.0, nodes['num_threshold']),
        left=np.where(leaf, own, nodes['left'] + offset).astype(np.int64),
        right=np.where(leaf, own, nodes['right'] + offset).astype(np.int64),
        value=np.where(leaf, nodes['value'], 0.0), roots=starts.astype(np.int64),
        baseline=float(np.asarray(model._baseline_prediction).ravel()[0]), features=FEATURES)


def mapped(folder: Path, maps: Path, jobs: int, overrides: list[str]) -> list[Session]:
    """The folder's sessions, each mapped by build_map into ``maps`` (a kept map is reused)
    with the ``overrides`` (``NAME=VALUE``) besides the judge's own."""
    bags = sorted(p for p in folder.iterdir() if p.is_dir() and (p.parent / f'{p.name}_truth.npz').exists())
    out = maps / folder.name
    out.mkdir(parents=True, exist_ok=True)
    todo = [b for b in bags if not (out / f'{b.name}.npz').exists()]
    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        # the rules alone: the judge's training and its baseline
        list(pool.map(lambda bag: score(bag, out, [*overrides, 'cell_judge=false']), todo))
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
    parser.add_argument('--set', action='append', default=[], metavar='NAME=VALUE',
                        help='build_map override (repeatable): learn on maps of another touch '
                             'model (keep them in a --keep folder of their own)')
    parser.add_argument('--export', type=Path,
                        help='write the classifier of all training sessions here, as the map '
                             'reads it (inhand_mapping/cell_judge_model.npz is the default\'s)')
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
        train = {f.name: mapped(f, maps, args.jobs, args.set) for f in folders}
        check = {f.name: mapped(f, maps, args.jobs, args.set) for f in checks}
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

    if args.export:
        model = classifier(everyone)
        exported = ensemble(model)
        rows = np.vstack([s.features for s in everyone])
        gap = np.abs(exported.probability(rows) - model.predict_proba(rows)[:, 1]).max()
        if gap > 1e-9:
            print(f'bench_cell_judge: the exported trees differ from the classifier by {gap}',
                  file=sys.stderr)
            return 1
        exported.save(args.export)
        print(f'# the classifier of all {len(everyone)} training sessions written to '
              f'{args.export} ({len(exported.feature)} nodes)', flush=True)
    groups = {name: (v, [judge(s) for s in v]) for name, v in {**train, **check}.items()}
    print('# each session judged by the classifier of the training sessions of other draws')
    report('the rules alone', groups, lambda s, p: s.shipped)
    for t in THRESHOLDS:
        report(f'the judge alone, p > {t}', groups, lambda s, p, t=t: p > t)
    for veto, rescue in VETO_RESCUE:
        label = ' and '.join(x for x in (f'veto p < {veto}' if veto else '',
                                         f'rescue p > {rescue}' if rescue < 1 else '') if x)

        def choose(s: Session, p: np.ndarray, veto=veto, rescue=rescue) -> np.ndarray:
            overridden, verdict = verdicts(p, s.explored, s.rules, s.clamp, veto, rescue)
            taken = s.shipped.copy()
            taken[overridden] = verdict > OCCUPIED
            return taken
        mark = ' (the map\'s)' if (veto, rescue) == (VETO, RESCUE) else ''
        report(f"the rules, {label}{mark}", groups, choose)
    print(f'\n{time.monotonic() - started:.0f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
