"""The picture of where to touch next: the map, the predicted surface coloured by its standard
deviation (dark: known, bright: a guess), and the ranked next touches as arrows onto it.

Drawn with the shape figure's panels and shaded meshes (shape_figure.py), from the same view.
"""

from __future__ import annotations

import cv2
import numpy as np

from inhand_shape.touch_guidance import Guidance, std_colours
from inhand_tools import drawing
from inhand_tools.drawing import OBLIQUE, Camera, View
from inhand_tools.map_cells import MapCells
from inhand_tools.shape_figure import PANEL, cells_panel, map_up, shaded_mesh

__all__ = ['guidance_figure']

SURFACE_GREY = (175, 175, 175)
TOUCH_COLOUR = (40, 40, 230)        # BGR red
ARROW_LENGTH = 0.03                 # m


def guidance_figure(cells: MapCells, guidance: Guidance, title: str, threshold: float = 0.8,
                    view: View = OBLIQUE, up: str | None = None) -> np.ndarray:
    """The three panels (module doc) side by side under ``title``, BGR; ``up``: the map's
    axis that points up (default: as the shape figure)."""
    occupied = cells.probabilities >= threshold
    surface = guidance.surface
    points = surface.vertices if not surface.empty else cells.centres[occupied]
    box = drawing.robust_box(points, 1.0, 99.0, reach=0.015, keep=0.5)
    camera = Camera.for_box(view, box, PANEL, up or map_up(cells)) if box is not None \
        else Camera(view, np.zeros(3), 0.1, PANEL, up or map_up(cells))
    colours = drawing.probability_colours(cells.probabilities[occupied])
    map_panel = drawing.annotate(
        drawing.render_cells(camera, cells.centres[occupied], cells.lattice.resolution, colours),
        camera, 'probabilistic map', f'{int(occupied.sum())} cells >= {threshold:g}')
    top = surface.settings.signal_std
    face_std = surface.vertex_std[surface.faces].mean(axis=1) if not surface.empty else np.zeros(0)
    std_panel = cells_panel(camera, cells, np.zeros(len(cells.centres), dtype=bool),
                            lambda image, f: shaded_mesh(image, camera, surface.vertices, surface.faces,
                                                         255.0 * std_colours(face_std, top)[:, ::-1], f),
                            'predicted surface',
                            f'std 0 (dark) to {top * 1000:.0f} mm (yellow)' if not surface.empty
                            else 'too few cells to predict')

    def draw_touches(image: np.ndarray, factor: int) -> None:
        shaded_mesh(image, camera, surface.vertices, surface.faces, SURFACE_GREY, factor)
        for rank, touch in reversed(list(enumerate(guidance.suggestions))):
            ends, _ = camera.project(np.stack([touch.position - ARROW_LENGTH * touch.approach,
                                               touch.position]), factor)
            a, b = (tuple(int(v) for v in np.round(p)) for p in ends)
            cv2.arrowedLine(image, a, b, TOUCH_COLOUR, (3 if rank == 0 else 2) * factor, cv2.LINE_AA,
                            tipLength=0.3)
            cv2.putText(image, str(rank + 1), (a[0] + 4 * factor, a[1]), cv2.FONT_HERSHEY_SIMPLEX,
                        0.5 * factor, TOUCH_COLOUR, factor, cv2.LINE_AA)

    best = guidance.suggestions[0] if guidance.suggestions else None
    subtitle = (f'{len(guidance.suggestions)} ranked; 1 removes {100 * best.gain:.1f} % of the '
                'uncertainty' if best is not None else 'nothing reachable to suggest')
    touch_panel = cells_panel(camera, cells, occupied, draw_touches, 'where to touch next', subtitle)
    return drawing.titled(drawing.hstack([map_panel, std_panel, touch_panel]), title)
