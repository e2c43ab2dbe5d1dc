"""The graspable part and antipodal grasps on it.

**The graspable part** (the paper's conclusion: "the most explored region" and the first
touched contacts are "a strong candidate to be the handle"). Each part scores

    score = EXPLORED_WEIGHT * (its share of all hits) / (its share of the cells)
            + FIRST_WEIGHT * (its share of the first FIRST_SHARE of first touches)

the first term is how much more it was explored than its size alone would give (a large
body is not the handle because it is large), the second where the exploration started.

**Grasps**: pairs of points on the part's superquadric (sampled over its surface) whose
connecting line lies inside both friction cones (half-angle ``atan(mu)``): for two contacts
with Coulomb friction that is exactly force closure (Nguyen 1988), and the smaller the
angle to the normals, the larger the margin. Each grasp gives the two contacts, the
closing width, an approach direction (perpendicular to the grasp axis, from the side away
from the object's other parts) and its margin (degrees inside the cones).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from inhand_common.array_types import Floats, Points, Vector3
from inhand_shape.shape_parts import Part
from inhand_shape.superquadric import Superquadric

__all__ = ['EXPLORED_WEIGHT', 'FIRST_SHARE', 'FIRST_WEIGHT', 'Grasp', 'antipodal_grasps',
           'graspable_scores']

EXPLORED_WEIGHT = 0.5
FIRST_WEIGHT = 0.5
FIRST_SHARE = 0.1          # the earliest tenth of the cells' first touches
MAX_WIDTH = 0.10           # m: a hand's opening
SAMPLES = 400              # surface points tried on a part


@dataclass(frozen=True)
class Grasp:
    """Two contacts (m, map frame), the closing width, the approach (unit, towards the
    object) and the margin inside the friction cones (degrees)."""
    contacts: tuple[Vector3, Vector3]
    width: float
    approach: Vector3
    margin_deg: float

    def as_dict(self) -> dict[str, object]:
        return {'contacts': [[round(float(v), 5) for v in c] for c in self.contacts],
                'width': round(self.width, 5),
                'approach': [round(float(v), 4) for v in self.approach],
                'margin_deg': round(self.margin_deg, 1)}


def graspable_scores(parts: list[Part], hits: ArrayLike, first_touch: ArrayLike) -> Floats:
    """Score of each part (module doc) from the hits (N,) and first-touch times (N,) of the
    occupied cells the parts index (NaN or inf: never touched)."""
    h = np.asarray(hits, dtype=float)
    first = np.asarray(first_touch, dtype=float)
    owned = np.concatenate([p.cells for p in parts]) if parts else np.zeros(0, dtype=np.intp)
    total_cells = max(len(owned), 1)
    total_hits = max(float(h[owned].sum()), 1.0)
    touched = owned[np.isfinite(first[owned])]
    early = np.zeros(0, dtype=np.intp)
    if len(touched):
        cut = np.quantile(first[touched], FIRST_SHARE)
        early = touched[first[touched] <= cut]
    scores = []
    for part in parts:
        explored = (float(h[part.cells].sum()) / total_hits) / (len(part.cells) / total_cells)
        started = float(np.isin(early, part.cells).mean()) if len(early) else 0.0
        scores.append(EXPLORED_WEIGHT * explored + FIRST_WEIGHT * started)
    return np.asarray(scores)


def antipodal_grasps(part: Superquadric, friction: float, *, away_from: ArrayLike | None = None,
                     count: int = 5, max_width: float = MAX_WIDTH,
                     rng: np.random.Generator | None = None) -> list[Grasp]:
    """Up to ``count`` force-closure grasps on ``part`` (module doc), best margin first,
    spread apart (no two with contacts within 1 cm of each other's). ``away_from``: a
    point (the rest of the object's centre) the approach should come from the other
    side of. ValueError for a negative friction coefficient."""
    if not friction >= 0:
        raise ValueError(f'friction coefficient {friction}: must be >= 0')
    generator = rng if rng is not None else np.random.default_rng(0)
    points = part.surface_samples(SAMPLES, generator)
    normals = part.normals(points)
    cone = math.atan(friction)
    axis = points[None, :, :] - points[:, None, :]              # i -> j
    width = np.linalg.norm(axis, axis=2)
    unit = axis / np.maximum(width, 1e-12)[:, :, None]
    # the force at i pushes along -n_i, so i -> j must be within the cone about -n_i, and
    # j -> i within the cone about -n_j
    at_i = np.arccos(np.clip(-np.einsum('ijk,ik->ij', unit, normals), -1, 1))
    at_j = np.arccos(np.clip(np.einsum('ijk,jk->ij', unit, normals), -1, 1))
    worst = np.maximum(at_i, at_j)
    ok = (worst < cone) & (width > 1e-3) & (width <= max_width)
    ok &= np.triu(np.ones_like(ok), 1)
    i, j = np.nonzero(ok)
    order = np.argsort(worst[i, j])
    grasps: list[Grasp] = []
    chosen: list[Points] = []
    centre = part.centre if away_from is None else np.asarray(away_from, dtype=float)
    for k in order:
        a, b = points[i[k]], points[j[k]]
        if any(min(np.linalg.norm(a - c[0]), np.linalg.norm(a - c[1])) < 0.01 for c in chosen):
            continue
        chosen.append(np.stack([a, b]))
        grasps.append(Grasp((a, b), float(width[i[k], j[k]]),
                            _approach(a, b, part, centre), math.degrees(cone - worst[i[k], j[k]])))
        if len(grasps) == count:
            break
    return grasps


def _approach(a: Vector3, b: Vector3, part: Superquadric, away: Vector3) -> Vector3:
    """Unit approach direction (towards the object) perpendicular to a -> b: from the
    grasp's middle outwards, away from ``away``, reversed."""
    middle = (a + b) / 2
    axis = (b - a) / max(float(np.linalg.norm(b - a)), 1e-12)
    outward = middle - away if np.linalg.norm(middle - away) > 1e-6 else part.rotation[:, 2]
    outward = outward - (outward @ axis) * axis
    if np.linalg.norm(outward) < 1e-9:
        outward = np.cross(axis, part.rotation[:, 0])
        if np.linalg.norm(outward) < 1e-9:
            outward = np.cross(axis, part.rotation[:, 1])
    return np.asarray(-outward / np.linalg.norm(outward))
