"""The picture of a pivot calibration: the geometry, and each finger's pivot as measured.

The first panel draws the geometry the registration uses (tip_offsets.py, pad_normals.py)
from its own formulas, for a finger rolled 30 degrees: the sensor on the nail, the tip
offset to the pad centre, the pad, the surface, and the two ways of going from the pad
centre to the contact (the way the finger's frame faces, and along the surface normal).
Then one panel per finger: the sensor positions of the poses the calibration used (grey,
on a sphere about the pivot) and the pad centres they give with the solved offset (red:
one tight blob at the pivot when the offset is right), the pivot point in black.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from inhand_common.atomic_file import atomic_write
from inhand_common.rotations import rotate_vectors
from inhand_mapping.pivot_calibration import PivotResult
from inhand_tools import drawing

__all__ = ['geometry_panel', 'pivot_figure', 'write_pivot_figure']

SIZE = 420
GREY = (150, 150, 150)
RED = (40, 40, 220)
BLUE = (200, 110, 30)
GREEN = (60, 160, 60)
BLACK = (20, 20, 20)


def geometry_panel(size: int = SIZE, offset=(0.003, -0.010), pad_radius: float = 0.007,
                   roll_deg: float = 30.0) -> np.ndarray:
    """The finger seen end on (its axis into the picture), rolled ``roll_deg``: sensor
    frame y right, z up before the roll; ``offset`` is the pad centre's (y, z) in it."""
    k = 2 * size / 0.05                       # pixels per metre at twice the size
    image = np.full((2 * size, 2 * size, 3), 255, dtype=np.uint8)
    ground = 1.45 * size                      # the surface's row, twice the size

    def px(y: float, z: float) -> tuple[int, int]:
        return int(round(size + k * y)), int(round(ground - k * z))

    roll = math.radians(roll_deg)
    turn = np.array([[math.cos(roll), -math.sin(roll)], [math.sin(roll), math.cos(roll)]])
    centre = np.array([0.0, pad_radius])                 # the pad touches the surface at 0
    sensor = centre - turn @ np.asarray(offset)
    facing = turn @ (np.asarray(offset) / np.linalg.norm(offset))
    by_frame = centre + pad_radius * facing
    contact = np.array([0.0, 0.0])
    thick = 4
    cv2.line(image, px(-0.03, 0.0), px(0.03, 0.0), BLACK, thick)
    cv2.circle(image, px(*centre), int(k * pad_radius), GREY, thick, cv2.LINE_AA)
    nail = turn @ np.array([[-0.006, 0.0], [0.006, 0.0]]).T + sensor[:, None]
    cv2.line(image, px(*nail[:, 0]), px(*nail[:, 1]), BLACK, 2 * thick)
    cv2.arrowedLine(image, px(*sensor), px(*centre), BLUE, thick, cv2.LINE_AA, tipLength=0.12)
    cv2.arrowedLine(image, px(*centre), px(*by_frame), RED, thick, cv2.LINE_AA, tipLength=0.25)
    cv2.arrowedLine(image, px(*centre), px(*contact), GREEN, thick, cv2.LINE_AA, tipLength=0.25)
    for point, colour in ((sensor, BLACK), (centre, BLUE), (by_frame, RED), (contact, GREEN)):
        cv2.circle(image, px(*point), 9, colour, -1, cv2.LINE_AA)
    image = cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)
    lines = [(BLACK, 'sensor on the nail: position p, rotation R'),
             (BLUE, 'tip offset o (sensor frame): pad centre p + R o'),
             (RED, "the finger's own facing: p + R o + r R o/|o|"),
             (GREEN, 'the contact: r along the surface normal')]
    for row, (colour, text) in enumerate(lines):
        y = int(0.8 * size) + 18 * row
        cv2.circle(image, (18, y - 4), 5, colour, -1, cv2.LINE_AA)
        drawing.label(image, text, (30, y), 0.42, colour)
    drawing.label(image, f'a finger end on, rolled {roll_deg:g} deg; pad radius r = '
                  f'{1000 * pad_radius:g} mm', (12, 24), 0.5)
    drawing.label(image, 'the normal: of the surface the pad centres have traced', (12, 44), 0.42)
    drawing.label(image, "(pad_normals.py); the finger's facing where none is yet", (12, 62), 0.42)
    return image


def _finger_panel(name: str, positions: np.ndarray, quaternions: np.ndarray,
                  result: PivotResult, size: int) -> np.ndarray:
    centres = positions + rotate_vectors(quaternions, np.broadcast_to(result.offset,
                                                                      positions.shape))
    box = drawing.box_of(np.vstack([positions, result.pivot[None]]))
    if box is None:
        return np.full((size, size, 3), 255, dtype=np.uint8)
    camera = drawing.Camera.for_box(drawing.OBLIQUE, box, size, up='-z')
    colours = np.vstack([np.tile(GREY, (len(positions), 1)), np.tile(RED, (len(centres), 1))])
    image = drawing.render_points(camera, np.vstack([positions, centres]),
                                  colours.astype(np.uint8), radius_px=1.5, depth_cue=0.2)
    pixel, _ = camera.project(result.pivot[None])
    cv2.circle(image, (int(pixel[0, 0]), int(pixel[0, 1])), 5, BLACK, -1, cv2.LINE_AA)
    verdict = 'accepted' if result.accepted else 'REFUSED'
    o = ', '.join(f'{1000 * v:+.1f}' for v in result.offset)
    subtitle = (f'offset [{o}] mm\nresidual {1000 * result.residual:.2f} mm RMS, turned '
                f'{result.rotation_deg:.0f} deg, {result.kept} of {result.poses} poses: {verdict}')
    return drawing.annotate(image, camera, f'{name}', subtitle, 'tracker frame')


def pivot_figure(fingers: dict[str, tuple[np.ndarray, np.ndarray, PivotResult]],
                 source: str, size: int = SIZE) -> np.ndarray:
    """The whole picture: the geometry, then one panel per finger of ``fingers`` (name ->
    (sensor positions (N, 3), quaternions (N, 4) of the pivot's poses, its result))."""
    panels = [geometry_panel(size)]
    panels += [_finger_panel(name, positions, quaternions, result, size)
               for name, (positions, quaternions, result) in fingers.items()]
    legend = drawing.key_legend(size * len(panels), [
        (GREY, 'sensor positions (pivot poses)'),
        (RED, 'pad centres p + R o with the solved offset'),
        (BLACK, 'pivot point')])
    return drawing.grid_figure(panels, len(panels), f'pivot calibration: {source}', legend)


def write_pivot_figure(path: Path, fingers: dict[str, tuple[np.ndarray, np.ndarray, PivotResult]],
                       source: str) -> None:
    """Write :func:`pivot_figure` as a PNG (atomically: a picture is whole or not there)."""
    ok, encoded = cv2.imencode('.png', pivot_figure(fingers, source))
    if not ok:
        raise OSError(f'{path}: could not encode the PNG')
    with atomic_write(path) as stream:
        stream.write(encoded.tobytes())
