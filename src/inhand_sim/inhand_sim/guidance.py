"""Where a simulated explorer strokes next, beyond the person's own choice.

Three explorers (``ExplorationSettings.explorer``, ``simulate_session --explorer``):

* ``random``: the simulated person (exploration.py): near where the finger is, on its side,
  preferring strokes not explored yet. No map involved.
* ``guided``: follows the project's own suggestions. After every :data:`REPLAN_STROKES`
  strokes the surface touched so far (the stroke paths as map cells of
  :data:`GUIDE_RESOLUTION`) goes through ``inhand_shape``'s predicted surface and next-touch
  ranking, exactly as ``predict_surface`` runs them on a map; each finger then starts at
  the best suggestion not taken yet nor touched since (on the reachable stroke start nearest
  to it, within :data:`START_REACH`), and the guide steers the stroke from there
  (:meth:`StrokeGuide.steering`): away from the touched cells within :data:`REPEL_REACH`
  and from the stroke's own trail, so that it keeps going into untouched surface instead of
  wandering back over what is known. A stroke is 2-6 s of sliding, 10-30 cm: where it goes
  matters more than where it starts. The fingertip slides on the true surface (that is all
  the simulator's object is used for); the guide only says which way.
* ``greedy``: the coverage baseline: the stroke start farthest from everything touched so far.

The guide sees what a perfect touch map would hold (the contact paths, no noise, no strays);
how the map's own errors change the guidance is measured by the explore benchmark, which maps
the sessions with the shipped touch model.
"""

from __future__ import annotations

from collections.abc import Callable

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
SUPPORT_CLEARANCE = 0.01     # m: nothing is sought this near the support (as next_touches)
REPEL_REACH = 0.015          # m: a guided stroke steers away from touched cells this near
REPEL_CELLS = 32             # touched cells that push a guided stroke at most (the nearest)
TRAIL_SKIP = 5               # steps of a guided stroke's own trail behind it that do not push it


class StrokeGuide:
    """The ``guided`` and ``greedy`` explorers' choice of the next stroke start, and the
    guided explorer's steering of the stroke (module doc).
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
        self.planned_from = 0       # contacts (entries) the latest prediction was made from

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
                                                             SUGGESTIONS, support=self.support,
                                                             support_clearance=SUPPORT_CLEARANCE)]
        self.planned_from = len(self.contacts)

    def steering(self) -> Callable[[np.ndarray], np.ndarray] | None:
        """For one guided stroke: the direction (N, 3) a fingertip at each of ``points``
        (N, 3), called step by step along the stroke, is sent in: away from the touched cells
        and the stroke's own trail (all but its last :data:`TRAIL_SKIP` steps) within
        :data:`REPEL_REACH`, each pushing by ``1 - d / REPEL_REACH``, the sum divided by the
        pushes' weight when that is above 1. Its length is how one-sided the touched surface
        around is: zero in untouched surface (the stroke keeps its heading), up to 1 along
        the edge of a touched patch. None for the greedy explorer or before any touch."""
        if self.kind != 'guided' or not self.contacts:
            return None
        cells = cKDTree(self._cells())
        trail: list[np.ndarray] = []

        def away(points: np.ndarray) -> np.ndarray:
            trail.append(points)
            distance, index = cells.query(points, k=REPEL_CELLS, distance_upper_bound=REPEL_REACH)
            found = np.isfinite(distance)
            near = cells.data[np.where(found, index, 0)]
            behind = np.concatenate(trail[:-TRAIL_SKIP]) if len(trail) > TRAIL_SKIP else np.empty((0, 3))
            near = np.concatenate([near, np.broadcast_to(behind, (len(points), *behind.shape))], axis=1)
            offset = points[:, None, :] - near
            d = np.linalg.norm(offset, axis=2)
            weight = np.clip(1.0 - d / REPEL_REACH, 0.0, None)
            weight[:, :REPEL_CELLS] *= found       # cells not found are padding
            push = np.sum(weight[:, :, None] * offset / np.maximum(d, 1e-9)[:, :, None], axis=1)
            return push / np.maximum(weight.sum(axis=1), 1.0)[:, None]
        return away

    def choose(self, starts: np.ndarray, available: np.ndarray) -> int | None:
        """The index into ``starts`` (S, 3) of the next stroke (only ``available`` ones), or
        None to let the person choose (nothing touched yet, no suggestion reachable)."""
        if not self.contacts or not available.any():
            return None
        free = np.flatnonzero(available)
        if self.kind == 'greedy':
            distance, _ = cKDTree(np.concatenate(self.contacts)).query(starts[free])
            return int(free[np.argmax(distance)])
        if self.since_plan >= REPLAN_STROKES or not self.suggestions:
            self._plan()
        tree = cKDTree(starts[free])
        since = cKDTree(np.concatenate(self.contacts[self.planned_from:])) \
            if len(self.contacts) > self.planned_from else None
        while self.suggestions:
            suggestion = self.suggestions.pop(0)
            if since is not None and since.query(suggestion)[0] <= PATH_REACH:
                continue        # touched since the prediction
            distance, nearest = tree.query(suggestion)
            if distance <= START_REACH:
                return int(free[nearest])
        return None
