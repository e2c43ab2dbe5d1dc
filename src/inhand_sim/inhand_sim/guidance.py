"""Where a simulated explorer starts its next stroke, beyond the person's own choice.

Three explorers (``ExplorationSettings.explorer``, ``simulate_session --explorer``):

* ``random``: the simulated person (exploration.py): near where the finger is, on its side,
  preferring strokes not explored yet. No map involved.
* ``guided``: follows the project's own suggestions. After every :data:`REPLAN_STROKES`
  strokes the surface touched so far (the stroke paths as map cells of
  :data:`GUIDE_RESOLUTION`) goes through ``inhand_shape``'s predicted surface and next-touch
  ranking, exactly as ``predict_surface`` runs them on a map; each finger then takes the best
  suggestion not taken yet and, of the reachable strokes starting within
  :data:`START_REACH` of it, the one whose path passes over the most predicted variance
  (summed over the surface within :data:`PATH_REACH` of it, by area).
* ``greedy``: the coverage baseline: the stroke start farthest from everything touched so far.

The guide sees what a perfect touch map would hold (the contact paths, no noise, no strays);
how the map's own errors change the guidance is measured by the explore benchmark, which maps
the sessions with the shipped touch model.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from inhand_shape.implicit_surface import PredictedSurface, predict_surface
from inhand_shape.next_touch import next_touches

__all__ = ['EXPLORERS', 'GUIDE_RESOLUTION', 'REPLAN_STROKES', 'StrokeGuide']

EXPLORERS = ('random', 'guided', 'greedy')
REPLAN_STROKES = 3           # strokes between two predictions of the guided explorer
GUIDE_RESOLUTION = 0.005     # m: the cells the guide's map is made of
SUGGESTIONS = 8              # suggestions asked for per prediction
START_REACH = 0.015          # m: a suggestion farther than this from every reachable start is skipped
PATH_REACH = 0.01            # m: the surface a stroke's path informs


class StrokeGuide:
    """The ``guided`` and ``greedy`` explorers' choice of the next stroke start (module doc).
    ``support``: the table's height in the object frame (static sessions), below which the
    guided explorer is never sent."""

    def __init__(self, kind: str, support: float | None):
        if kind not in EXPLORERS or kind == 'random':
            raise ValueError(f'explorer {kind!r}: the guide serves {EXPLORERS[1:]}')
        self.kind = kind
        self.support = support
        self.contacts: list[np.ndarray] = []
        self.since_plan = REPLAN_STROKES       # plan before the first guided stroke
        self.suggestions: list[np.ndarray] = []
        self.plans = 0
        self.surface: PredictedSurface | None = None

    def touched(self, points: np.ndarray, stroke: bool) -> None:
        """The finger was in contact along ``points`` (N, 3) object frame; ``stroke``: it was a
        stroke (counted towards the next prediction), not a slide between strokes."""
        if len(points):
            self.contacts.append(np.asarray(points, dtype=float).reshape(-1, 3))
        self.since_plan += int(stroke)

    def _cells(self) -> np.ndarray:
        points = np.concatenate(self.contacts)
        keys = np.unique(np.floor(points / GUIDE_RESOLUTION).astype(np.int64), axis=0)
        return (keys + 0.5) * GUIDE_RESOLUTION

    def _plan(self) -> None:
        self.since_plan = 0
        self.plans += 1
        self.surface = predict_surface(self._cells(), GUIDE_RESOLUTION)
        self.suggestions = [s.position for s in next_touches(self.surface, GUIDE_RESOLUTION,
                                                             SUGGESTIONS, support=self.support)]

    def _most_informative(self, candidates: np.ndarray, paths: list[np.ndarray]) -> int:
        """Of the strokes ``candidates`` (indices into ``paths``), the one whose path passes
        over the most predicted variance."""
        surface = self.surface
        if surface is None or surface.empty or len(candidates) == 1:
            return int(candidates[0])
        weight = surface.vertex_areas() * surface.process_std ** 2
        tree = cKDTree(surface.vertices)
        scores = []
        for index in candidates:
            path = paths[index][:: max(1, len(paths[index]) // 30)]
            near = tree.query_ball_point(path, PATH_REACH)
            covered = np.unique(np.concatenate([np.asarray(n, dtype=np.intp) for n in near]))
            scores.append(weight[covered].sum())
        return int(candidates[int(np.argmax(scores))])

    def choose(self, starts: np.ndarray, available: np.ndarray, paths: list[np.ndarray]) -> int | None:
        """The index into ``starts`` (S, 3) of the next stroke (only ``available`` ones; their
        ``paths``, each an (K, 3) array), or None to let the person choose (nothing touched
        yet, no suggestion reachable)."""
        if not self.contacts or not available.any():
            return None
        free = np.flatnonzero(available)
        if self.kind == 'greedy':
            distance, _ = cKDTree(np.concatenate(self.contacts)).query(starts[free])
            return int(free[np.argmax(distance)])
        if self.since_plan >= REPLAN_STROKES or not self.suggestions:
            self._plan()
        tree = cKDTree(starts[free])
        while self.suggestions:
            near = tree.query_ball_point(self.suggestions.pop(0), START_REACH)
            if near:
                return self._most_informative(free[np.asarray(near, dtype=np.intp)], paths)
        return None
