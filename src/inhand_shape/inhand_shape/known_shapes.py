"""Objects made of known superquadrics: what the shape extraction is measured against.

Each object is a union of superquadric parts in its own frame (z up, centred on its bounding
box as the simulator centres a mesh), with the part a hand would take it by named: the
handle of a cup, a bottle's neck, a hammer's shaft. :func:`union_mesh` makes the closed
triangle mesh the simulator explores (``simulate_session --object FILE``): marching cubes of
the smallest signed radial distance to the parts, on a 1 mm lattice.

Singles span the superquadric range (box-like e = 0.1, a cylinder, an ellipsoid, a diamond
e = 1.6, rounded shapes) at 3-15 cm; multi-part objects have two or three parts.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from inhand_common.array_types import Floats, Points
from inhand_shape.superquadric import Superquadric

__all__ = ['KNOWN_SHAPES', 'KnownShape', 'signed_distance', 'union_mesh']


def _part(size_cm: tuple[float, float, float], shape: tuple[float, float],
          centre_cm: tuple[float, float, float] = (0, 0, 0), turn: tuple[str, float] | None = None
          ) -> Superquadric:
    rotation = np.eye(3) if turn is None else Rotation.from_euler(turn[0], turn[1], degrees=True).as_matrix()
    return Superquadric(np.array(size_cm) / 100, shape, rotation, np.array(centre_cm, dtype=float) / 100)


@dataclass(frozen=True)
class KnownShape:
    """Parts (superquadrics) of an object, which one is its handle (None for one part)."""
    name: str
    description: str
    parts: tuple[Superquadric, ...]
    handle: int | None = None


KNOWN_SHAPES: dict[str, KnownShape] = {s.name: s for s in (
    KnownShape('box', 'box 8 x 5 x 3 cm, sharp edges (e = 0.1)',
               (_part((4, 2.5, 1.5), (0.1, 0.1)),)),
    KnownShape('cylinder', 'cylinder 6 cm across, 10 cm tall',
               (_part((3, 3, 5), (0.1, 1.0)),)),
    KnownShape('ellipsoid', 'ellipsoid 6 x 4 x 3 cm',
               (_part((3, 2, 1.5), (1.0, 1.0)),)),
    KnownShape('diamond', 'diamond-like 5 cm (e = 1.6)',
               (_part((2.5, 2.5, 2.5), (1.6, 1.6)),)),
    KnownShape('small', 'rounded cube 3.2 cm (e = 0.5)',
               (_part((1.6, 1.6, 1.6), (0.5, 0.5)),)),
    KnownShape('large', 'rounded slab 15 x 8 x 6 cm (e = 0.3, 0.6)',
               (_part((7.5, 4, 3), (0.3, 0.6)),)),
    KnownShape('cup', 'cup with handle: cylinder 8 cm across, 10 cm tall, a 3 cm handle',
               (_part((4, 4, 5), (0.1, 1.0)), _part((1.6, 0.8, 3), (0.3, 0.3), (5.0, 0, 0))),
               handle=1),
    KnownShape('bottle', 'bottle with neck: body 7 cm across, 12 cm tall, neck 2.4 cm across',
               (_part((3.5, 3.5, 6), (0.2, 1.0)), _part((1.2, 1.2, 2.5), (0.1, 1.0), (0, 0, 8.0))),
               handle=1),
    KnownShape('hammer', 'hammer-like: shaft 18 cm, head 9 cm across it',
               (_part((1.2, 1.2, 9), (0.1, 1.0), (-1.5, 0, 0), ('y', 90)),
                _part((1.6, 4.5, 1.6), (0.2, 0.2), (8.5, 0, 0))),
               handle=0),
    KnownShape('dumbbell', 'dumbbell: two rounded blocks 5 cm on a bar 2.4 cm across',
               (_part((1.2, 1.2, 6.5), (0.1, 1.0), (0, 0, 0), ('y', 90)),
                _part((2.5, 2.5, 2.5), (0.4, 0.4), (-7.5, 0, 0)),
                _part((2.5, 2.5, 2.5), (0.4, 0.4), (7.5, 0, 0))),
               handle=0),
)}


def signed_distance(parts: tuple[Superquadric, ...], points: Points) -> Floats:
    """The smallest signed radial distance of ``points`` to the parts (< 0 inside)."""
    return np.min([np.where(part.contains(points), -1.0, 1.0) * part.distance(points)
                   for part in parts], axis=0)


def union_mesh(shape: KnownShape, spacing: float = 0.001):  # type: ignore[no-untyped-def]
    """(the closed trimesh of the union, the parts moved the same way): the mesh centred on
    its bounding box, as the simulator centres a mesh, and the parts with it."""
    import trimesh
    from skimage.measure import marching_cubes
    reach = np.array([np.abs(p.rotation) @ p.size + np.abs(p.centre) for p in shape.parts]).max(axis=0)
    # off the parts' planes by a fraction of a step: a flat face exactly on the lattice
    # makes zero-area triangles and edges of three
    low = -reach - 3 * spacing + 0.37 * spacing
    counts = np.ceil(2 * (reach + 3 * spacing) / spacing).astype(int) + 1
    axes = [low[k] + spacing * np.arange(counts[k]) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing='ij'), axis=-1).reshape(-1, 3)
    field = signed_distance(shape.parts, grid).reshape(tuple(counts))
    verts, faces, _, _ = marching_cubes(field, 0.0, spacing=(spacing,) * 3, allow_degenerate=False)
    vertices = verts + low
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    if mesh.volume < 0:
        mesh.invert()
    shift = (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0)) / 2
    mesh.apply_translation(-shift)
    return mesh, tuple(replace(p, centre=p.centre - shift) for p in shape.parts)
