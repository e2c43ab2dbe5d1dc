"""The picture of a map's shape, like the paper's Fig. 1: the map, its surface mesh, and the
superquadric parts over the map with the graspable part highlighted and its grasps drawn.

Meshes are drawn as shaded triangles back to front (painter's algorithm; the fills loop over
triangles, everything else is computed for all of them at once).
"""

from __future__ import annotations

import cv2
import numpy as np

from inhand_shape.shape_extraction import ShapeResult
from inhand_tools import drawing
from inhand_tools.drawing import OBLIQUE, Camera, View
from inhand_tools.map_cells import MapCells
from inhand_tools.map_figures import default_up

__all__ = ['PART_COLOURS', 'cells_panel', 'map_up', 'shaded_mesh', 'shape_figure']

# BGR: the graspable part is drawn orange, the others in cool colours
GRASPABLE_COLOUR = (40, 130, 245)
PART_COLOURS = [(200, 150, 60), (120, 180, 90), (180, 120, 170), (150, 150, 150), (90, 170, 200)]
GRASP_COLOUR = (40, 160, 40)
CELL_GREY = (215, 215, 215)
PANEL = 520


def shaded_mesh(image: np.ndarray, camera: Camera, vertices: np.ndarray, faces: np.ndarray,
                colour, factor: int) -> None:
    """Triangles drawn into ``image`` (``factor`` times the camera's size), back to front,
    lit by the pictures' light (both sides lit alike: open meshes show their backs);
    ``colour``: one BGR for all, or one per triangle (F, 3)."""
    if len(faces) == 0:
        return
    pixels, depth = camera.project(vertices, factor)
    triangles = vertices[faces]
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    light = np.abs(normals @ camera.light_in_data())
    shade = (0.35 + 0.65 * light)[:, None] * np.asarray(colour, dtype=float).reshape(-1, 3)
    order = np.argsort(depth[faces].mean(axis=1))
    corners = np.round(pixels[faces] * 4).astype(np.int32)   # 2 fractional bits
    for k in order:
        cv2.fillPoly(image, [corners[k]], tuple(int(c) for c in shade[k]), cv2.LINE_AA, shift=2)


def cells_panel(camera: Camera, cells: MapCells, occupied: np.ndarray, draw, title: str,
                subtitle: str) -> np.ndarray:
    """The occupied cells in grey, then ``draw(image, factor)`` on top, annotated."""
    base = drawing.render_cells(camera, cells.centres[occupied], cells.lattice.resolution,
                                np.array(CELL_GREY), edges=False)
    big = cv2.resize(base, (camera.size * 2, camera.size * 2), interpolation=cv2.INTER_NEAREST)
    draw(big, 2)
    image = cv2.resize(big, (camera.size, camera.size), interpolation=cv2.INTER_AREA)
    return drawing.annotate(image, camera, title, subtitle)


def map_up(cells: MapCells) -> str:
    """The map's up axis in pictures: -z for a map registered in static mode (build_map
    records it: the frame is the tracker's, whose z points down), else by its frame."""
    return '-z' if cells.registration_mode == 'static' else default_up(cells.frame_id)


def shape_figure(cells: MapCells, result: ShapeResult, title: str, threshold: float = 0.8,
                 view: View = OBLIQUE, up: str | None = None) -> np.ndarray:
    """The three panels (module doc) side by side under ``title``, BGR; ``up``: the map's
    axis that points up (default :func:`map_up`)."""
    occupied = cells.probabilities >= threshold
    box = drawing.robust_box(cells.centres[occupied], 5.0, 95.0, reach=0.015, keep=0.5)
    up = up or map_up(cells)
    camera = Camera.for_box(view, box, PANEL, up) if box is not None \
        else Camera(view, np.zeros(3), 0.1, PANEL, up)
    colours = drawing.probability_colours(cells.probabilities[occupied])
    map_panel = drawing.annotate(
        drawing.render_cells(camera, cells.centres[occupied], cells.lattice.resolution, colours),
        camera, 'probabilistic map', f'{int(occupied.sum())} cells >= {threshold:g}')
    mesh = result.mesh
    mesh_panel = cells_panel(camera, cells, occupied, lambda image, f: shaded_mesh(
        image, camera, mesh.vertices, mesh.faces, (190, 170, 140), f), 'surface mesh',
        f'{len(mesh.faces):,} triangles, {mesh.holes} hole(s) left open')

    def draw_parts(image: np.ndarray, factor: int) -> None:
        for k, part in enumerate(result.decomposition.parts):
            colour = GRASPABLE_COLOUR if k == result.graspable else PART_COLOURS[k % len(PART_COLOURS)]
            vertices, faces = part.superquadric.mesh(3)
            shaded_mesh(image, camera, vertices, faces, colour, factor)
        for grasp in result.grasps:
            ends, _ = camera.project(np.stack(grasp.contacts), factor)
            a, b = (tuple(int(v) for v in np.round(p)) for p in ends)
            cv2.line(image, a, b, GRASP_COLOUR, 2 * factor, cv2.LINE_AA)
            for point in (a, b):
                cv2.circle(image, point, 4 * factor, GRASP_COLOUR, -1, cv2.LINE_AA)

    parts = result.decomposition.parts
    subtitle = (f'{len(parts)} part(s); graspable (orange): part {result.graspable}; '
                f'{len(result.grasps)} grasp(s) (green)' if parts else
                'no part: ' + (result.decomposition.reason or '')[:60])
    parts_panel = cells_panel(camera, cells, occupied, draw_parts, 'superquadric parts', subtitle)
    return drawing.titled(drawing.hstack([map_panel, mesh_panel, parts_panel]), title)
