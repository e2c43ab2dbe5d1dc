"""From a map's occupied cells to what a grasp planner uses, in one call, and its files.

:func:`extract_shape` runs the surface mesh (surface_mesh.py), the superquadric parts
(shape_parts.py), the graspable part and its grasps (grasps.py) on the cells above the
occupancy threshold; :func:`write_shape_files` writes ``NAME_surface.ply|.obj|.stl`` and
``NAME_parts.yaml`` atomically (all or none). The picture is drawn by inhand_tools.
"""

from __future__ import annotations

import io
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike

from inhand_common.array_types import Bools, Floats
from inhand_common.atomic_file import write_file_set
from inhand_common.parameters import ParamSpec
from inhand_shape.grasps import Grasp, antipodal_grasps, graspable_scores
from inhand_shape.shape_parts import MAX_PARTS, Decomposition, decompose
from inhand_shape.surface_mesh import SurfaceMesh, surface_mesh

__all__ = ['DEFAULT_FRICTION', 'MESH_FORMATS', 'MODE_ORIENTATION', 'SHAPE_PARAMETERS', 'ShapeResult',
           'extract_shape', 'mode_orientation', 'part_cells', 'shape_file_names', 'support_normal',
           'write_shape_files']

DEFAULT_FRICTION = 0.5     # a fingertip on wood or plastic
MESH_FORMATS = ('ply', 'obj', 'stl')
# The shape extraction's parameters (the shape_node section of a parameter file; extract_shape
# reads the same section).
SHAPE_PARAMETERS = (
    ParamSpec('friction', DEFAULT_FRICTION, 'Coulomb friction coefficient of the grasp contacts '
              '(force closure: the grasp axis inside both friction cones)', minimum=0.0, maximum=5.0),
    ParamSpec('max_parts', MAX_PARTS, 'Most superquadric parts in a decomposition (1: one '
              'superquadric)', minimum=1, maximum=10),
    ParamSpec('occupied_threshold', 0.8, 'Cells at or above this occupancy probability are the '
              'shape', minimum=0.5, maximum=0.999),
)


@dataclass(frozen=True, eq=False)
class ShapeResult:
    """Everything extracted from one map (module doc); ``graspable`` indexes ``parts``
    (None without parts); ``seconds`` the time of each step."""

    mesh: SurfaceMesh
    decomposition: Decomposition
    scores: Floats
    graspable: int | None
    grasps: list[Grasp]
    friction: float
    frame_id: str
    seconds: dict[str, float] = field(default_factory=dict)

    def summary(self) -> str:
        """One line for people."""
        d = self.decomposition
        mesh = (f'surface {len(self.mesh.faces):,} triangles, {self.mesh.holes} hole(s)'
                if len(self.mesh.faces) else 'no surface')
        if d.reason is not None:
            return f'{mesh}; no parts: {d.reason}'
        which = f'part {self.graspable}' if self.graspable is not None else 'none'
        return (f'{mesh}; {len(d.parts)} part(s) explaining {d.total_cells - len(d.unexplained)} of '
                f'{d.total_cells} cells; graspable: {which}, {len(self.grasps)} grasp(s)')

    def as_dict(self) -> dict[str, Any]:
        """The content of NAME_parts.yaml."""
        d = self.decomposition
        parts = []
        for k, part in enumerate(d.parts):
            parts.append({'index': k, **part.superquadric.as_dict(), 'cells': int(len(part.cells)),
                          'residual': round(part.residual, 5), 'explained': round(part.explained, 3),
                          'graspable_score': round(float(self.scores[k]), 3)})
        return {'frame_id': self.frame_id, 'cells': d.total_cells,
                'unexplained_cells': int(len(d.unexplained)), 'reason': d.reason,
                'parts': parts, 'graspable_part': self.graspable, 'friction': self.friction,
                'grasps': [g.as_dict() for g in self.grasps],
                'surface': {'triangles': int(len(self.mesh.faces)), 'holes': self.mesh.holes,
                            'area': round(self.mesh.area, 6),
                            'boundary_length': round(self.mesh.boundary_length, 4)},
                'seconds': {k: round(v, 3) for k, v in self.seconds.items()}}


# (up, on_support) of a map by the graph's registration mode: a static object stands on a
# support below it, in the tracker frame (z down); a tracked one is held, its own +z up.
MODE_ORIENTATION = {'static': ((0.0, 0.0, -1.0), True), 'tracked': ((0.0, 0.0, 1.0), False)}


def mode_orientation(mode: str | None) -> tuple[tuple[float, float, float], bool]:
    """(up, on_support) of a map by the graph's registration ``mode``
    (``MODE_ORIENTATION``); an unknown mode (None: not known yet) as a held object's."""
    return MODE_ORIENTATION.get(mode or '', MODE_ORIENTATION['tracked'])


def support_normal(mode: str | None) -> tuple[float, float, float] | None:
    """The normal of the support a map's object stands on, by the graph's registration
    ``mode`` (:func:`mode_orientation`): the tracker's -z for a static map; None for a held
    one or an unknown mode."""
    up, on_support = mode_orientation(mode)
    return up if on_support else None


def part_cells(probabilities: ArrayLike, threshold: float, layer: ArrayLike | None = None
               ) -> tuple[Bools, Floats]:
    """(which cells the parts are fitted on, the weights of those): the cells at or above
    ``threshold`` with their probabilities -- given the surface ``layer``'s probabilities,
    the map without the cell judge's rescue: not the cells the layer holds under
    ``threshold``, the lower of the two probabilities for the others (all of them where
    nothing else would be left). Most rescued cells are a second cell across the surface, a
    few millimetres off it: the parts are searched on cell centres, and a surface two cells
    thick moves them (docs/shape.md, "With the touch map's cell judge")."""
    p = np.asarray(probabilities, dtype=float)
    keep: Bools = p >= threshold
    if layer is not None:
        below = np.asarray(layer, dtype=float)
        sheet: Bools = keep & (below >= threshold)
        if sheet.any():
            return sheet, np.minimum(p, below)[sheet]
    return keep, p[keep]


def extract_shape(centres: ArrayLike, probabilities: ArrayLike, hits: ArrayLike,
                  first_touch: ArrayLike, *, resolution: float, origin: ArrayLike = (0, 0, 0),
                  threshold: float = 0.8, friction: float = DEFAULT_FRICTION,
                  max_parts: int = MAX_PARTS, frame_id: str = 'object',
                  surface_points: ArrayLike | None = None,
                  up: ArrayLike | None = None, layer: ArrayLike | None = None) -> ShapeResult:
    """The shape of the map whose cells are given (centres (N, 3) m, probabilities, hits,
    first-touch times; any cells, those at or above ``threshold`` are used).
    ``surface_points`` (N, 3) m: where in each cell the surface was measured (the map's
    contact centroids); the surface mesh's tangent planes pass there (surface_mesh) and the
    parts' last fit takes them (shape_parts.decompose). ``up`` (3,): the object stands on a
    support whose normal this is (a static map): the parts may be held upright
    (superquadric.fit_superquadric). ``layer`` (N,): the surface layer's probabilities
    (OccupancyGrid.layer_probabilities): the parts and the graspable scores leave out the
    cells the map's cell judge raised to ``threshold`` from under it (:func:`part_cells`);
    the mesh takes them."""
    if not 0 < threshold < 1:
        raise ValueError(f'threshold {threshold}: must be in (0, 1)')
    if not friction >= 0:
        raise ValueError(f'friction {friction}: must be >= 0')
    p = np.asarray(probabilities, dtype=float)
    keep = p >= threshold
    cells = np.asarray(centres, dtype=float).reshape(-1, 3)[keep]
    seconds = {}
    start = time.perf_counter()
    measured = None if surface_points is None else \
        np.asarray(surface_points, dtype=float).reshape(-1, 3)[keep]
    mesh = surface_mesh(cells, resolution, origin, surface_points=measured)
    seconds['mesh'] = time.perf_counter() - start
    start = time.perf_counter()
    sheet, weights = part_cells(p, threshold, layer)
    chosen = sheet[keep]
    parts = decompose(cells[chosen], weights, resolution=resolution, max_parts=max_parts,
                      surface_points=None if measured is None else measured[chosen], up=up)
    seconds['parts'] = time.perf_counter() - start
    scores = graspable_scores(parts.parts, np.asarray(hits)[sheet], np.asarray(first_touch)[sheet])
    graspable = int(np.argmax(scores)) if len(parts.parts) else None
    grasps: list[Grasp] = []
    if graspable is not None:
        start = time.perf_counter()
        others = [q.superquadric.centre for k, q in enumerate(parts.parts) if k != graspable]
        away = np.mean(others, axis=0) if others else None
        grasps = antipodal_grasps(parts.parts[graspable].superquadric, friction, away_from=away)
        seconds['grasps'] = time.perf_counter() - start
    return ShapeResult(mesh, parts, scores, graspable, grasps, friction, frame_id, seconds)


def shape_file_names(output_dir: str | Path, name: str) -> dict[str, Path]:
    """What :func:`write_shape_files` writes (and the picture's name), by kind."""
    folder = Path(output_dir)
    files = {fmt: folder / f'{name}_surface.{fmt}' for fmt in MESH_FORMATS}
    files.update(parts=folder / f'{name}_parts.yaml', picture=folder / f'{name}_shape.png')
    return files


def yaml_document(comment: str, content: dict[str, Any]) -> bytes:
    """A YAML file: a ``# comment`` line, then ``content`` in its order."""
    text = io.StringIO()
    text.write(f'# {comment}\n')
    yaml.safe_dump(content, text, sort_keys=False, default_flow_style=None)
    return text.getvalue().encode()


def mesh_bytes(mesh: Any, file_type: str) -> bytes:
    """A trimesh.Trimesh as a file of ``file_type`` (ply, obj, stl)."""
    data = mesh.export(file_type=file_type)
    return data if isinstance(data, bytes) else str(data).encode()


def write_shape_files(result: ShapeResult, output_dir: str | Path, name: str,
                      picture: bytes | None = None) -> list[Path]:
    """Write the surface (PLY, OBJ, STL; none when there is no surface), the parts YAML and
    the ``picture`` (PNG bytes) if given, all or none; the paths written."""
    files = shape_file_names(output_dir, name)
    mesh = result.mesh.trimesh() if len(result.mesh.faces) else None
    contents: dict[Path, bytes | None] = {
        files[fmt]: None if mesh is None else mesh_bytes(mesh, fmt) for fmt in MESH_FORMATS}
    contents[files['parts']] = yaml_document(f'Shape of the map (inhand_shape): {result.summary()}',
                                             result.as_dict())
    if picture is not None:
        contents[files['picture']] = picture
    return write_file_set(contents)
