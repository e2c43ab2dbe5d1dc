"""Where to touch next: the places on the predicted surface where one touch is expected to
remove the most uncertainty.

A touch at ``c`` is one more observation of the implicit function there (``f(c) = 0`` with the
contact's noise). Under the Gaussian process (implicit_surface.py) it lowers the variance at
every surface point ``y`` by ``cov(c, y)^2 / (var(c) + noise^2)``, whatever it finds. The
expected gain of ``c`` is that reduction summed over the predicted surface, each point
weighted by its area, and reported as the share of the surface's summed variance it removes
(so 0.05: a touch there removes 5 % of what the map does not know yet).

Candidates are the predicted surface's vertices (thinned to one per :data:`CANDIDATE_SPACING`
cells), minus what a finger cannot reach: below the support plane (an object standing on a
table: within ``support_clearance`` of its lowest cell, along ``up``) and inside the holding
hand's regions when they are known. The ranked handful is greedy: the best candidate, then the
best at least :data:`SEPARATION` (or one length scale, if longer) away from those already
chosen, and so on, so that the list points to different places rather than five neighbours
of one. The approach direction is
into the surface, along the predicted surface's inward normal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree  # type: ignore[import-untyped]

from inhand_common.array_types import Points, Vector3
from inhand_shape.implicit_surface import PredictedSurface, thinned

__all__ = ['DEFAULT_SUGGESTIONS', 'Suggestion', 'next_touches']

DEFAULT_SUGGESTIONS = 5
CANDIDATE_SPACING = 2.0     # cells between candidate touches
MAX_CANDIDATES = 400        # candidate touches (thinned beyond)
MAX_TARGETS = 800           # surface points the gain is summed over (thinned beyond)
SEPARATION = 0.02           # m between two suggestions at least


@dataclass(frozen=True, eq=False)
class Suggestion:
    """One place to touch: ``position`` on the predicted surface (m), ``approach`` the unit
    direction the fingertip moves in (into the surface), ``gain`` the share of the surface's
    summed variance one touch there is expected to remove, ``std`` the predicted surface's
    standard deviation there (m)."""

    position: Vector3
    approach: Vector3
    gain: float
    std: float

    def as_dict(self) -> dict[str, Any]:
        return {'position': [round(float(v), 5) for v in self.position],
                'approach': [round(float(v), 4) for v in self.approach],
                'gain': round(self.gain, 5), 'std': round(self.std, 5)}


def _reachable(points: Points, up: Vector3, support: float | None, clearance: float,
               held: list[tuple[Vector3, float]]) -> np.ndarray:
    ok = np.ones(len(points), dtype=bool)
    if support is not None:
        ok &= points @ up > support + clearance
    for centre, radius in held:
        ok &= np.linalg.norm(points - centre, axis=1) > radius
    return ok


def next_touches(surface: PredictedSurface, resolution: float, count: int = DEFAULT_SUGGESTIONS,
                 *, up: ArrayLike = (0.0, 0.0, 1.0), support: float | None = None,
                 support_clearance: float = 0.01,
                 held: list[tuple[ArrayLike, float]] | None = None) -> list[Suggestion]:
    """The ``count`` best places to touch next (module doc), best first. ``support``: the
    height along ``up`` of the plane the object stands on (None: nothing below it is
    excluded); ``held``: (centre, radius) spheres of the holding hand. Empty when the surface
    is empty or nothing is reachable."""
    if count < 1:
        raise ValueError(f'count {count}: must be >= 1')
    process = surface.process
    if surface.empty or process is None:
        return []
    up_vector = np.asarray(up, dtype=float) / np.linalg.norm(up)
    regions = [(np.asarray(c, dtype=float), float(r)) for c, r in (held or [])]
    normals = surface.vertex_normals()
    candidates = thinned(surface.vertices, CANDIDATE_SPACING * resolution, MAX_CANDIDATES)
    candidates = candidates[_reachable(surface.vertices[candidates], up_vector, support,
                                       support_clearance, regions)]
    if len(candidates) == 0:
        return []
    areas = surface.vertex_areas()
    targets = thinned(surface.vertices, resolution, MAX_TARGETS)
    # the thinned points stand for the area around them
    target_area = np.bincount(cKDTree(surface.vertices[targets]).query(surface.vertices)[1], areas,
                              len(targets))
    # what a touch can reduce is the process's own variance (the extrapolation's part of
    # the surface's std is the prior shape's error, which the process does not model)
    variance = surface.process_std ** 2
    total = float((areas * variance).sum())
    noise = surface.settings.noise_std * resolution
    cov = process.covariance(surface.vertices[candidates], surface.vertices[targets])
    gain = (cov ** 2 @ target_area) / (variance[candidates] + noise ** 2) / max(total, 1e-30)
    chosen: list[Suggestion] = []
    taken: list[Vector3] = []
    apart = max(SEPARATION, surface.settings.length_scale)
    for k in np.argsort(-gain):
        p = surface.vertices[candidates[k]]
        if any(np.linalg.norm(p - q) < apart for q in taken):
            continue
        taken.append(p)
        chosen.append(Suggestion(p.copy(), -normals[candidates[k]], float(gain[k]),
                                 float(surface.vertex_std[candidates[k]])))
        if len(chosen) == count:
            break
    return chosen

