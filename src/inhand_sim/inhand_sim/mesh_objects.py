"""Objects made from triangle meshes (OBJ, STL, PLY files), explored like the built-in ones.

Why: the map model must hold on real objects, and real objects come as scanned meshes, not
as unions of the simulator's primitives. A :class:`MeshObject` offers what
:class:`~inhand_sim.objects.SolidObject` promises, so the exploration, the session writer,
the ground truth and the stereo rig use it unchanged:

* **Loading** (:func:`load_mesh_object`) by trimesh, vertices merged. Refused, with one
  line saying why (:class:`MeshError`): a file trimesh cannot read or that holds no
  triangles, a mesh that is not watertight or not consistently oriented (the fingers and
  the map need an inside), one whose size (after ``scale``) is outside 3-30 cm (the
  workspaces are 35 cm cubes), one with parts too thin for the distance grid.
* **Frame**: metres (``scale`` multiplies the file's units), ``up`` (the file's axis that
  points up, default +z) turned to +z, and the OBJECT frame's origin at the centre of the
  mesh's bounding box (the object sensor; the static sessions put it at the workspace's
  centre). The table is the plane through the lowest vertex.
* **Distances**: a signed distance grid (:class:`~inhand_sim.distance_grid.DistanceGrid`,
  1 mm, 15 mm beyond the mesh, trilinear with its gradient) for the millions of queries of
  the exploration and the renderer; within a few hundredths of a millimetre of the
  triangles at most places, a few tenths at tight bumps. **Contacts** are then put on the
  triangles themselves: :meth:`MeshObject.project_to_surface` is the exact closest point
  (:class:`~inhand_sim.triangles.TriangleBins`).
* **Surface samples** uniform by area: a triangle drawn in proportion to its area, a
  uniform point in it, its face normal (the ground truth's samples and normals).
* **Grips** (where the other hand holds it) are balls around chosen places of the surface,
  each sized to hold a given share of the surface area, so that they hold a comparable
  part of any object: :class:`GripSpec`, a place given as fractions of the bounding box.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from inhand_sim.distance_grid import DistanceGrid
from inhand_sim.objects import HeldRegion, SolidObject
from inhand_sim.triangles import TriangleBins

__all__ = [
    'DEFAULT_MOVING_GRIPS',
    'DEFAULT_STATIC_GRIP',
    'MESH_SUFFIXES',
    'SIZE_RANGE',
    'UP_AXES',
    'GripSpec',
    'MeshError',
    'MeshObject',
    'load_mesh_object',
    'mesh_object',
]

MESH_SUFFIXES = ('.obj', '.stl', '.ply')
SIZE_RANGE = (0.03, 0.30)        # m: the largest extent of an explorable object
GRID_SPACING = 0.001             # m
GRID_MARGIN = 0.015              # m beyond the mesh's box
UP_AXES = ('x', 'y', 'z', '-x', '-y', '-z')
_SECOND_SENSOR_TURN = (0.7071067811865476, 0.0, 0.0, 0.7071067811865476)


class MeshError(ValueError):
    """A mesh that cannot be an object, with the reason in one line."""


@dataclass(frozen=True)
class GripSpec:
    """Where the other hand holds the object: around the surface point nearest to ``where``
    (fractions of the bounding box, 0 at its low corner, 1 at its high one), covering
    ``fraction`` of the surface area."""
    name: str
    where: tuple[float, float, float]
    fraction: float


DEFAULT_STATIC_GRIP = GripSpec('top', (0.5, 0.5, 1.0), 0.08)
DEFAULT_MOVING_GRIPS = (GripSpec('one end', (0.0, 0.5, 0.5), 0.10),
                        GripSpec('bottom', (0.5, 0.5, 0.0), 0.12),
                        GripSpec('other end', (1.0, 0.5, 0.5), 0.10))


class MeshObject(SolidObject):
    """A closed, outward-oriented triangle mesh in its OBJECT frame (see the module
    docstring); ``vertices`` (V, 3) m, ``faces`` (F, 3)."""

    def __init__(self, name: str, vertices: np.ndarray, faces: np.ndarray, *,
                 texture: str = 'scan', description: str = '',
                 static_grip: GripSpec = DEFAULT_STATIC_GRIP,
                 moving_grips: tuple[GripSpec, ...] = DEFAULT_MOVING_GRIPS,
                 spacing: float = GRID_SPACING, margin: float = GRID_MARGIN):
        self.name = name
        self.description = description
        self._texture = texture
        self.vertices = np.asarray(vertices, dtype=float)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.triangles = self.vertices[self.faces]
        cross = np.cross(self.triangles[:, 1] - self.triangles[:, 0],
                         self.triangles[:, 2] - self.triangles[:, 0])
        doubled = np.linalg.norm(cross, axis=1)
        self.face_areas = 0.5 * doubled
        self.face_normals = cross / np.maximum(doubled, 1e-300)[:, None]
        self._bounds = np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])
        self.grid = DistanceGrid.build(self.vertices, self.faces, spacing, margin)
        self.bins = TriangleBins(self.vertices, self.faces, bin_size=0.002, reach=0.0005)
        self.table_z = float(self._bounds[0, 2])
        self.nominal_size = tuple(float(v) for v in self.size)
        places, _ = self.sample_surface(20_000, np.random.default_rng(0))
        self.static_grip = self._held(places, static_grip)
        self.moving_grips = [self._held(places, spec) for spec in moving_grips]
        mount = self._nearest_place(places, (0.5, 0.0, 0.5))
        self.second_sensor = (tuple(float(v) for v in mount), _SECOND_SENSOR_TURN)

    @property
    def texture(self) -> str:
        return self._texture

    @property
    def bounds(self) -> np.ndarray:
        return self._bounds

    def sdf_grad(self, points) -> tuple[np.ndarray, np.ndarray]:
        """The grid's signed distance (negative inside) and gradient (see DistanceGrid)."""
        return self.grid.evaluate(np.asarray(points, dtype=float).reshape(-1, 3))

    def closest_points(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exact closest points on the triangles (N, 3), distances (N,), triangles (N,)."""
        return self.bins.nearest(points)

    def project_to_surface(self, points, iterations: int = 30) -> np.ndarray:
        """Points on the triangles: the exact closest point of each point within half a
        millimetre of the surface (contacts, which lie on the grid's surface), and of the
        grid's foot point (Newton steps along its gradient) of each point farther out."""
        p = np.array(points, dtype=float).reshape(-1, 3)
        far = np.abs(self.sdf(p)) > self.bins.reach
        if far.any():
            p[far] = self._newton(p[far], iterations, 1e-9)
        return self.bins.nearest(p)[0]

    def sample_surface(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``n`` points uniform by area and their normals (their triangles' normals)."""
        cumulative = np.cumsum(self.face_areas)
        face = np.minimum(np.searchsorted(cumulative, rng.random(n) * cumulative[-1], side='right'),
                          len(cumulative) - 1)
        r = rng.random((n, 2))
        root = np.sqrt(r[:, :1])
        t = self.triangles[face]
        points = (1.0 - root) * t[:, 0] + root * (1.0 - r[:, 1:]) * t[:, 1] + root * r[:, 1:] * t[:, 2]
        return points, self.face_normals[face]

    def surface_area(self) -> float:
        return float(self.face_areas.sum())

    def _nearest_place(self, places: np.ndarray, where) -> np.ndarray:
        target = self._bounds[0] + np.asarray(where, dtype=float) * self.size
        return places[int(np.argmin(np.sum((places - target) ** 2, axis=1)))]

    def _held(self, places: np.ndarray, spec: GripSpec) -> HeldRegion:
        """The ball around the place nearest to ``spec.where`` that holds ``spec.fraction``
        of the (uniform) surface samples."""
        centre = self._nearest_place(places, spec.where)
        radius = float(np.quantile(np.linalg.norm(places - centre, axis=1), spec.fraction))
        return HeldRegion(spec.name, (tuple(float(v) for v in centre),), (radius,))


def _turn_up(axis: str) -> np.ndarray:
    """Rotation matrix taking the file's ``axis`` (one of UP_AXES) to +z (a quarter or half
    turn about x or y)."""
    turns = {'z': np.eye(3),
             '-z': np.diag([1.0, -1.0, -1.0]),
             'y': np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
             '-y': np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
             'x': np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
             '-x': np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])}
    if axis not in turns:
        raise MeshError(f'up axis {axis!r}: choose one of {", ".join(UP_AXES)}')
    return turns[axis]


def load_mesh_object(path, *, name: str | None = None, scale: float = 1.0, up: str = 'z',
                     texture: str = 'scan', description: str | None = None,
                     static_grip: GripSpec = DEFAULT_STATIC_GRIP,
                     moving_grips: tuple[GripSpec, ...] = DEFAULT_MOVING_GRIPS) -> MeshObject:
    """The object of the mesh file at ``path`` (OBJ, STL or PLY), ``scale`` times its units
    in metres, its ``up`` axis turned to +z, centred (see the module docstring). ``name``
    (default: the path as given) is what the ground truth records. MeshError if it cannot
    be an object."""
    import trimesh
    path = Path(path)
    label = name if name is not None else str(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise MeshError(f'{path}: not a mesh file (OBJ, STL or PLY: {", ".join(MESH_SUFFIXES)})')
    try:
        mesh = trimesh.load(path, force='mesh')
    except Exception as error:   # trimesh raises whatever its parsers raise
        raise MeshError(f'cannot read {path}: {type(error).__name__}: {error}'.splitlines()[0]) from None
    faces = np.asarray(getattr(mesh, 'faces', np.empty((0, 3))))
    if faces.ndim != 2 or len(faces) == 0:
        raise MeshError(f'{path}: no triangles in it')
    return mesh_object(mesh, label, str(path), scale=scale, up=up, texture=texture,
                       description=description if description is not None else
                       f'mesh {path.name}: {len(faces):,} triangles',
                       static_grip=static_grip, moving_grips=moving_grips)


def mesh_object(mesh, label: str, source: str, *, scale: float = 1.0, up: str = 'z',
                texture: str = 'scan', description: str = '',
                static_grip: GripSpec = DEFAULT_STATIC_GRIP,
                moving_grips: tuple[GripSpec, ...] = DEFAULT_MOVING_GRIPS) -> MeshObject:
    """The object of a trimesh ``mesh`` (read from a file, or made by trimesh.creation),
    named ``label``; ``source`` names it in refusals. MeshError if it cannot be an object."""
    if not (scale > 0 and np.isfinite(scale)):
        raise MeshError(f'mesh scale {scale} must be a positive number')
    turn = _turn_up(up)
    if not mesh.is_watertight:
        open_edges = int(np.count_nonzero(np.bincount(mesh.edges_unique_inverse) != 2))
        raise MeshError(f'{source} is not watertight ({open_edges} edges not shared by exactly two '
                        'triangles): an object needs an inside')
    if not mesh.is_winding_consistent:
        raise MeshError(f'{source}: its triangles are not consistently oriented (no inside)')
    if mesh.volume < 0:
        mesh.invert()
    vertices = (np.asarray(mesh.vertices, dtype=float) * float(scale)) @ turn.T
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    extent = float((hi - lo).max())
    if not SIZE_RANGE[0] <= extent <= SIZE_RANGE[1]:
        raise MeshError(f'{source} is {extent * 100:.3g} cm across (scale {scale:g}): objects must be '
                        f'{SIZE_RANGE[0] * 100:g}-{SIZE_RANGE[1] * 100:g} cm across to fit the '
                        'workspace (set the scale: file units to metres)')
    vertices = vertices - (lo + hi) / 2
    obj = MeshObject(label, vertices, np.asarray(mesh.faces, dtype=np.int64), texture=texture,
                     description=description, static_grip=static_grip, moving_grips=moving_grips)
    _check_resolved(obj, source)
    return obj


def _check_resolved(obj: MeshObject, source: str, tolerance: float = 0.0005,
                    allowed: float = 0.01) -> None:
    """Refuse a mesh whose distance grid misses its surface (parts thinner than about two
    grid steps): more than ``allowed`` of its surface farther than ``tolerance`` from the
    grid's zero."""
    samples, _ = obj.sample_surface(20_000, np.random.default_rng(1))
    missed = float(np.mean(np.abs(obj.sdf(samples)) > tolerance))
    if missed > allowed:
        raise MeshError(f'{source}: {missed:.0%} of its surface is in parts thinner than the '
                        f'{GRID_SPACING * 1000:g} mm distance grid resolves')
