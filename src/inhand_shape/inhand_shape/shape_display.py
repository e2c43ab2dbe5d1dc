"""What a viewer draws of a shape result, as plain arrays: the node turns each into a
visualization_msgs/Marker, a picture or a web page could use the same.

Each item: a name (the marker namespace), a kind (``triangles``: every three points one
triangle; ``lines``: every two points one segment; ``points``), the points (N, 3) m in the
map's frame, and a colour (r, g, b, a in 0-1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from inhand_common.array_types import Points
from inhand_shape.shape_extraction import ShapeResult

__all__ = ['GRASPABLE_RGBA', 'PART_RGBA', 'DisplayItem', 'part_items', 'surface_item']

GRASPABLE_RGBA = (0.96, 0.51, 0.16, 0.85)     # orange, as in the pictures
PART_RGBA = ((0.24, 0.59, 0.78, 0.6), (0.35, 0.71, 0.47, 0.6), (0.67, 0.47, 0.71, 0.6),
             (0.59, 0.59, 0.59, 0.6), (0.78, 0.67, 0.35, 0.6))
GRASP_RGBA = (0.16, 0.63, 0.16, 1.0)
SURFACE_RGBA = (0.55, 0.67, 0.75, 0.9)
PART_SUBDIVISIONS = 3                          # icosphere level of a part's mesh (1,280 triangles)


@dataclass(frozen=True, eq=False)
class DisplayItem:
    name: str
    kind: str
    points: Points
    rgba: tuple[float, float, float, float]


def surface_item(result: ShapeResult) -> DisplayItem:
    """The surface mesh as a triangle list."""
    mesh = result.mesh
    return DisplayItem('surface', 'triangles', mesh.vertices[mesh.faces].reshape(-1, 3), SURFACE_RGBA)


def part_items(result: ShapeResult) -> list[DisplayItem]:
    """Each part as a triangle list (the graspable one orange), and the grasps as segments
    between their contacts."""
    items = []
    for k, part in enumerate(result.decomposition.parts):
        vertices, faces = part.superquadric.mesh(PART_SUBDIVISIONS)
        rgba = GRASPABLE_RGBA if k == result.graspable else PART_RGBA[k % len(PART_RGBA)]
        items.append(DisplayItem(f'part {k}', 'triangles', vertices[faces].reshape(-1, 3), rgba))
    if result.grasps:
        segments = np.array([np.stack(g.contacts) for g in result.grasps]).reshape(-1, 3)
        items.append(DisplayItem('grasps', 'lines', segments, GRASP_RGBA))
    return items
