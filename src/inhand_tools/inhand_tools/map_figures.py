"""The PNG pictures of a map like the paper's figures 4-8 (over :mod:`drawing`).

Written to one folder, each picture an oblique and a side view (orthographic, scale bar in
cm, the data frame's axes drawn in the corner):

  raw_points.png         fingertip positions as recorded, tracker frame (needs the bag)
  registered_points.png  the same registered into the map frame (needs the bag)
  map_above_<t>.png      the map's cells with probability > t, one per threshold, shaded
                         by probability (darker = more probable)
  map_thresholds.png     the thresholds side by side (oblique view), like the paper's fig. 5
  regions.png            most explored cells (top hit counts) and the first touched cells
  truth.png              the true surface, its explored part and the stray points (needs
                         the truth)
  stereo_points.png      the bag's stereo points in the colours of the image, map frame,
                         and the rectified left image, the extracted texture (paper's
                         fig. 6; needs a :class:`StereoCloud`)
  textured_map.png       the occupied map (cells above the highest threshold), each
                         textured cell in its camera colour, the others neutral grey
                         (paper's fig. 6; needs a map with colours)
  texture_registration.png  the stereo points over the occupied cells, both in the map
                         frame: do they register? (paper's fig. 7; needs a StereoCloud)
  local_maps.png         a map saved with fusion: the touch and vision local maps, the global
                         map fused from them and its per-cell entropy (paper's fig. 1)
  figure.png             every picture's oblique view in one figure (not the
                         registration's)

One function draws each picture (:func:`draw_raw_points`, :func:`draw_registered_points`,
:func:`draw_stereo_points`, :func:`draw_map_above`, :func:`draw_map_thresholds`,
:func:`draw_textured_map`, :func:`draw_texture_registration`, :func:`draw_regions`,
:func:`draw_truth`, :func:`draw_overview`), sharing a :class:`MapScene`: the cells, the
view box and cameras of the map-frame panels, the output folder and the pictures written;
each returns its panels for the overview. :func:`draw_all` draws every picture the inputs
allow.

The map's and the camera's colours are RGB; OpenCV draws BGR: they are flipped here.

Every panel is framed on the object, not on everything the fingertips went through (they
travel far off the object between strokes and during re-grasps): all map-frame panels show
one view box (:func:`map_view_box`), the raw points their own (:func:`raw_view_box`); what
falls outside a panel is not drawn and its subtitle says how much.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from inhand_common.ground_truth import GroundTruth
from inhand_tools import drawing
from inhand_tools.bag_points import BagPoints
from inhand_tools.drawing import OBLIQUE, SIDE, Camera, View
from inhand_tools.map_cells import Lattice, LocalMaps, MapCells, cell_indices
from inhand_tools.map_quality import explored_mask
from inhand_tools.map_regions import regions

if TYPE_CHECKING:
    from inhand_tools.bag_stereo_shot import BagShot

__all__ = [
    'FINGER_COLOURS',
    'FRAME_LABELS',
    'MapScene',
    'StereoCloud',
    'default_up',
    'draw_all',
    'draw_local_maps',
    'draw_map_above',
    'draw_map_thresholds',
    'draw_overview',
    'draw_raw_points',
    'draw_regions',
    'draw_registered_points',
    'draw_stereo_points',
    'draw_texture_registration',
    'draw_textured_map',
    'draw_truth',
    'map_view_box',
    'near_cells',
    'raw_view_box',
    'regions',
]

# BGR: orange, blue, green, purple, brown (fingers in finger_names order).
FINGER_COLOURS = np.array([[28, 127, 255], [180, 119, 31], [44, 160, 44], [189, 103, 148],
                           [75, 86, 140]], dtype=float)
EXPLORED_COLOUR = (1, 97, 230)     # orange (BGR)
FIRST_COLOUR = (153, 60, 94)       # purple
BASE_COLOUR = (205, 205, 205)      # light grey
STRAY_COLOUR = (40, 40, 215)       # red
SURFACE_COLOUR = (200, 200, 200)
EXPLORED_SURFACE_COLOUR = (80, 150, 60)
UNTEXTURED_COLOUR = (178, 178, 178)  # neutral grey: a cell the camera did not see
REGISTRATION_CELL_COLOUR = (215, 215, 215)
FRAME_LABELS = {'object': 'object frame', 'tracker': 'tracker frame (polhemus_source)',
                None: 'map frame'}
TRUTH_POINTS = 60000  # at most about this many surface samples are drawn


# ------------------------------------------------------------------ framing

def default_up(frame: str | None) -> str:
    """The data axis that points up in the pictures of a map in ``frame``: +z in the object
    frame (the simulator's objects stand on their +z), -z in the tracker frame (its z
    points down) and when the frame is not known."""
    return 'z' if frame == 'object' else '-z'


def map_view_box(cells: MapCells, thresholds, truth=None) -> drawing.ViewBox:
    """What every map-frame panel shows: the object, not the strays.

    With the truth (in the map's frame): its surface's bounding box. Else a robust box of
    the centres of the cells above the highest threshold that has any (all touched cells
    if none has): their 5th-95th percentile box finds the object, the cells within 1.5 cm
    of it are its cells (so that thin extremities stay in view; a 2nd-98th percentile box
    is not enough: a few confident cells left by a stroke far from the object may be more
    than 2 % of them), and the 0.5-99.5 percentile box of those, grown by half a cell, is
    the object's. Either grown by a margin (:func:`drawing.default_margin`).
    """
    if truth is not None and len(truth.surface_points):
        box = drawing.box_of(truth.surface_points)
        if box is not None:
            return box
    resolution = cells.lattice.resolution
    centres = cells.centres
    for threshold in sorted(thresholds, reverse=True):
        above = cells.centres[cells.probabilities > threshold]
        if len(above):
            centres = above
            break
    box = drawing.robust_box(centres, 5.0, 95.0, reach=0.015, keep=0.5, margin=0.0)
    if box is None:
        return drawing.ViewBox(np.full(3, -0.01), np.full(3, 0.01))
    return box.grown(drawing.default_margin(box) + resolution / 2.0)


def raw_view_box(raw) -> drawing.ViewBox | None:
    """What the raw-point panels show (tracker frame): where most fingertip positions are
    (their 5th-95th percentile box), widened to the points within 2 cm of it, cut to
    those points' 1st-99th percentiles (the object, not the lifts and re-grasps), grown by
    a margin."""
    return drawing.robust_box(raw, 5.0, 95.0, reach=0.02, keep=1.0)


def near_cells(points, centres, resolution: float) -> np.ndarray:
    """Mask of the points in a cell of ``centres`` (a lattice of edge ``resolution``) or in
    one of its 26 neighbours: within one cell of the map."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    if len(points) == 0 or len(centres) == 0:
        return np.zeros(len(points), dtype=bool)
    lattice = Lattice(resolution, tuple(float(v) for v in centres[0] - resolution / 2.0))
    cells = cell_indices(centres, lattice)
    offsets = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing='ij'), -1).reshape(-1, 3)
    near = (cells[:, None, :] + offsets[None]).reshape(-1, 3)
    low = near.min(axis=0)
    span = near.max(axis=0) - low + 1

    def keys(indices):
        indices = indices - low
        inside = np.all((indices >= 0) & (indices < span), axis=1)
        flat = (indices[:, 0] * span[1] + indices[:, 1]) * span[2] + indices[:, 2]
        return np.where(inside, flat, -1)
    return np.isin(keys(cell_indices(points, lattice)), np.unique(keys(near)))


@dataclass
class StereoCloud:
    """What the stereo pictures show of a bag's stereo shot: its points in the map frame
    (N, 3), their colours (N, 3) uint8 RGB, the rectified left image (H, W, 3) uint8 RGB
    (the extracted texture, or None), how many usable pairs the bag held and where the
    left camera was in the map frame (or None)."""

    points: np.ndarray
    colours: np.ndarray
    image: np.ndarray | None = None
    pairs: int = 1
    camera_centre: np.ndarray | None = None

    @classmethod
    def of_shot(cls, shot: BagShot) -> StereoCloud:
        """The first usable shot of a bag (:func:`inhand_tools.bag_stereo_shot.read_bag_shot`)."""
        points, colours = shot.points()
        # p_rectified = M p_map + b: the camera (p_rectified = 0) is at -M^T b (M a rotation).
        matrix, offset = shot.placed.map_to_camera(shot.config.camera_pose)
        return cls(np.asarray(points, dtype=float).reshape(-1, 3),
                   np.asarray(colours, dtype=np.uint8).reshape(-1, 3),
                   shot.placed.shot.left_rgb, len(shot.pairs.placed),
                   -np.asarray(matrix, dtype=float).T @ np.asarray(offset, dtype=float))

    @property
    def bgr(self) -> np.ndarray:
        """The points' colours for OpenCV: (N, 3) float BGR."""
        return self.colours[:, ::-1].astype(float)


# ------------------------------------------------------------------ what the pictures share

@dataclass
class MapScene:
    """What every picture of one map shares: its cells and thresholds, the view box of the
    map-frame panels (one box, so they compare at a glance), their cameras, the output
    folder and the pictures written so far."""

    cells: MapCells
    thresholds: list
    output: Path
    box: drawing.ViewBox
    frame: str | None = None
    up: str = '-z'
    size: int = 480
    written: list[Path] = field(default_factory=list)

    @classmethod
    def create(cls, cells: MapCells, output: Path, thresholds, truth=None,
               frame: str | None = None, up: str | None = None,
               size: int = 480) -> MapScene:
        """The scene of a map in ``frame`` (its up axis ``up``, default
        :func:`default_up`), framed on the truth's surface if given, else on the map."""
        output.mkdir(parents=True, exist_ok=True)
        return cls(cells, thresholds, output, map_view_box(cells, thresholds, truth), frame,
                   up or default_up(frame), size)

    @property
    def frame_label(self) -> str:
        return FRAME_LABELS.get(self.frame, 'map frame')

    @property
    def width(self) -> int:
        """Pixels across a picture of two views."""
        return 2 * self.size

    def camera(self, view: View) -> Camera:
        """The camera of a map-frame panel."""
        return Camera.for_box(view, self.box, self.size, self.up)

    @property
    def occupied_threshold(self) -> float:
        """The occupied map's threshold: the highest of the pictures' (0.8 if none)."""
        return max(self.thresholds) if self.thresholds else 0.8

    def probability_legend(self, width: int) -> np.ndarray:
        return drawing.probability_legend(width, tuple(t for t in self.thresholds
                                                       if 0 < t < 1))

    def cell_drawer(self, centres, colours):
        """draw(camera) of the cells at ``centres``: those whose cubes reach into the view
        box and whose centres are pictured in the panel's free area."""
        resolution = self.cells.lattice.resolution
        cell_box = self.box.grown(resolution / 2.0)  # a cell is drawn if its cube reaches it

        def draw(camera):
            # The whole cube in the free area: its centre well inside.
            shown = _shown(camera, cell_box, centres, 0.6 * resolution * camera.scale)
            return (drawing.render_cells(camera, centres[shown], resolution, colours[shown]),
                    _outside(shown, 'cells'))
        return draw

    def save(self, name: str, image: np.ndarray) -> None:
        path = self.output / name
        if not cv2.imwrite(str(path), image):
            raise OSError(f'{path}: could not write the PNG')
        self.written.append(path)


def _views(draw, camera_for, frame_label: str, first_line: str | None = None,
           views=(OBLIQUE, SIDE), title: str | None = None) -> list:
    """Panels of ``draw(camera) -> (image, note)`` for each view (oblique and side by
    default), titled with the view's name (or ``title``); the subtitle is ``first_line``
    over the note (what the panel leaves out)."""
    panels = []
    for view in views:
        camera = camera_for(view)
        image, note = draw(camera)
        panels.append(drawing.annotate(image, camera, title or view.name,
                                       _lines(first_line, note), frame_label))
    return panels


def _view_from(scene: MapScene, direction, name: str) -> View | None:
    """The view looking at the scene from ``direction`` (data frame, towards the viewer),
    or None for no direction."""
    direction = np.asarray(direction, dtype=float).reshape(3)
    length = float(np.linalg.norm(direction))
    if not math.isfinite(length) or length < 1e-9:
        return None
    shown = drawing.UP_AXES[scene.up] @ (direction / length)  # display coordinates
    elevation = math.degrees(math.asin(float(np.clip(shown[2], -1.0, 1.0))))
    return View(name, math.degrees(math.atan2(shown[1], shown[0])),
                float(np.clip(elevation, -89.0, 89.0)))


def _camera_side(scene: MapScene, camera_centre, centres=None, textured=None
                 ) -> View | None:
    """The view from the stereo camera (``camera_centre``, map frame) if known, else from
    the side the textured cells are on (from the occupied cells' centroid to theirs)."""
    if camera_centre is not None:
        return _view_from(scene, np.asarray(camera_centre, float) - scene.box.centre,
                          'from the stereo camera')
    if centres is None or textured is None or not np.any(textured):
        return None
    return _view_from(scene, centres[textured].mean(axis=0) - centres.mean(axis=0),
                      'from the textured side')


def _shown(camera: Camera, box: drawing.ViewBox, points, inset: float = 0.0) -> np.ndarray:
    """Mask of the points a panel draws: inside the view box and pictured inside the
    panel's free area (``inset`` pixels in from its edges)."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    inside = box.contains(points)
    inside[inside] = camera.in_view(points[inside], inset)
    return inside


def _splat_radius(count: int) -> float:
    """Pixels: bigger splats for sparse clouds, small ones for dense clouds."""
    return float(np.clip(2.6 * np.sqrt(3000.0 / max(count, 1)), 1.0, 2.6))


def _finger_colours(fingers: np.ndarray) -> np.ndarray:
    fingers = np.asarray(fingers, dtype=np.int64)
    return FINGER_COLOURS[np.mod(np.maximum(fingers, 0), len(FINGER_COLOURS))]


def _finger_key(names: list[str]) -> list:
    return [(tuple(int(c) for c in FINGER_COLOURS[k % len(FINGER_COLOURS)]), name)
            for k, name in enumerate(names)]


def _lines(*parts) -> str | None:
    """Subtitle lines (the empty ones dropped), or None."""
    text = '\n'.join(part for part in parts if part)
    return text or None


def _outside(inside: np.ndarray, what: str) -> str | None:
    """'+ N <what> outside the view' when some are outside, else None."""
    count = int(np.count_nonzero(~np.asarray(inside, dtype=bool)))
    return drawing.outside_note(count, what) if count else None


# ------------------------------------------------------------------ one function per picture

def draw_raw_points(scene: MapScene, points: BagPoints, raw_up: str) -> list:
    """raw_points.png: the fingertip positions as recorded (tracker frame, ``raw_up`` up),
    framed by :func:`raw_view_box`; returns its overview panel."""
    raw = points.raw
    raw_box = raw_view_box(raw)
    colours = _finger_colours(points.raw_fingers)
    radius_px = _splat_radius(np.count_nonzero(raw_box.contains(raw)))

    def camera_for(view):
        return Camera.for_box(view, raw_box, scene.size, raw_up)

    def draw(camera):
        shown = _shown(camera, raw_box, raw)
        return (drawing.render_points(camera, raw[shown], colours[shown], radius_px),
                _outside(shown, 'points'))

    tracker = FRAME_LABELS['tracker']
    panels = _views(draw, camera_for, tracker)
    footer = drawing.key_legend(scene.width, _finger_key(points.finger_names))
    scene.save('raw_points.png', drawing.titled(
        drawing.hstack(panels), f'Raw fingertip positions ({len(raw):,} points, '
        'tracker frame)', footer))
    return _views(draw, camera_for, tracker, f'{len(raw):,} fingertip positions', (OBLIQUE,),
                  'raw points')


def draw_registered_points(scene: MapScene, points: BagPoints) -> list:
    """registered_points.png: the fingertip positions registered into the map frame, in
    the map's view box; returns its overview panel."""
    registered = points.registered
    colours = _finger_colours(points.registered_fingers)
    in_box = registered[scene.box.contains(registered)]
    radius_px = _splat_radius(len(np.unique(np.round(in_box, 4), axis=0)))

    def draw(camera):
        shown = _shown(camera, scene.box, registered)
        return (drawing.render_points(camera, registered[shown], colours[shown], radius_px),
                _outside(shown, 'points'))

    panels = _views(draw, scene.camera, scene.frame_label)
    footer = drawing.key_legend(scene.width, _finger_key(points.finger_names))
    scene.save('registered_points.png', drawing.titled(
        drawing.hstack(panels), f'Registered fingertip positions ({len(registered):,} '
        f'points, {points.mode} registration, {scene.frame_label})', footer))
    return _views(draw, scene.camera, scene.frame_label,
                  f'{len(registered):,} points, {points.mode} registration', (OBLIQUE,),
                  'registered points')


def draw_stereo_points(scene: MapScene, stereo: StereoCloud) -> list:
    """stereo_points.png: the stereo shot's points in the colours of the image, in the map
    frame and the map's view box (oblique and side views), and the rectified left image
    (the extracted texture) scaled to the panel height; returns its overview panel."""
    points, colours = stereo.points, stereo.bgr
    radius_px = _splat_radius(np.count_nonzero(scene.box.contains(points)))
    count = f'{len(points):,} stereo points'

    def draw(camera):
        shown = _shown(camera, scene.box, points)
        return (drawing.render_points(camera, points[shown], colours[shown], radius_px, 0.15),
                _outside(shown, 'points'))

    panels = _views(draw, scene.camera, scene.frame_label, f'{count}, camera colours')
    if stereo.image is not None and stereo.image.ndim == 3 and stereo.image.size:
        height, width = stereo.image.shape[:2]
        panels.append(drawing.image_panel(
            np.ascontiguousarray(stereo.image[..., ::-1]), scene.size, 'extracted texture',
            f'rectified left image, {width} x {height} px'))
    pairs = f'first of {stereo.pairs} usable pairs' if stereo.pairs > 1 else 'one stereo pair'
    scene.save('stereo_points.png', drawing.titled(
        drawing.hstack(panels), f'Stereo points in the colours of the image ({len(points):,} '
        f'points, {pairs}, {scene.frame_label})'))
    return _views(draw, scene.camera, scene.frame_label, count, (OBLIQUE,), 'stereo points')


def draw_textured_map(scene: MapScene, camera_centre=None) -> list:
    """textured_map.png: the occupied map (cells above the highest threshold), each
    textured cell in its camera colour and the others neutral grey: oblique and side
    views, and the view from the stereo camera (``camera_centre``, map frame; else from
    the side the textured cells are on); returns its overview panel (oblique). Needs a
    map with colours."""
    cells = scene.cells
    if not cells.has_colours:
        raise ValueError('the map has no colours')
    threshold = scene.occupied_threshold
    keep = cells.probabilities > threshold
    textured = cells.textured[keep]
    colours = np.where(textured[:, None], cells.colours[keep][:, ::-1].astype(float),
                       np.array(UNTEXTURED_COLOUR, dtype=float))
    draw = scene.cell_drawer(cells.centres[keep], colours)
    note = f'{np.count_nonzero(textured)} of {np.count_nonzero(keep)} cells textured'
    views = [OBLIQUE, SIDE]
    towards = _camera_side(scene, camera_centre, cells.centres[keep], textured)
    if towards is not None:
        views.append(towards)
    panels = _views(draw, scene.camera, scene.frame_label, note, views)
    keys = [(UNTEXTURED_COLOUR, 'grey: untextured (not seen by the stereo camera)')]
    if textured.any():
        typical = np.median(colours[textured], axis=0)
        keys.insert(0, (tuple(int(c) for c in typical), 'textured: the colour of the cell '
                                                        'in the camera image'))
    scene.save('textured_map.png', drawing.titled(
        drawing.hstack(panels), f'Textured map: cells with probability > {threshold:g} in '
        f'the camera colours ({note})', drawing.key_legend(scene.size * len(panels), keys)))
    return _views(draw, scene.camera, scene.frame_label, note, (OBLIQUE,),
                  f'textured map, p > {threshold:g}')


def draw_texture_registration(scene: MapScene, stereo: StereoCloud) -> list:
    """texture_registration.png: the stereo points (camera colours) over the occupied
    cells (light grey), both in the map frame, oblique and side views and the view from
    the stereo camera (if known); the cells hide the points behind them. The subtitle says
    how many of the points in the view box lie within one cell of an occupied cell (a
    table or backdrop in the box counts against it). No overview panel (returns [])."""
    cells = scene.cells
    threshold = scene.occupied_threshold
    keep = cells.probabilities > threshold
    centres = cells.centres[keep]
    resolution = cells.lattice.resolution
    points, colours = stereo.points, stereo.bgr
    in_box = scene.box.contains(points)
    radius_px = _splat_radius(np.count_nonzero(in_box))
    near = near_cells(points[in_box], centres, resolution)
    cell_box = scene.box.grown(resolution / 2.0)

    def draw(camera):
        cell_shown = _shown(camera, cell_box, centres, 0.6 * resolution * camera.scale)
        shown = _shown(camera, scene.box, points)
        image = drawing.render_cells_and_points(
            camera, centres[cell_shown], resolution, REGISTRATION_CELL_COLOUR, points[shown],
            colours[shown], radius_px)
        return image, _outside(shown, 'points')

    share = (f'{np.count_nonzero(near) / len(near):.0%} of the {len(near):,} points in the '
             f'box within a cell of the map' if len(near) else 'no stereo point in the box')
    views = [OBLIQUE, SIDE]
    towards = _camera_side(scene, stereo.camera_centre)
    if towards is not None:
        views.append(towards)
    panels = _views(draw, scene.camera, scene.frame_label, share, views)
    keys = [(REGISTRATION_CELL_COLOUR, f'map, p > {threshold:g} ({len(centres)} cells)'),
            ((60, 110, 150), 'stereo points in the colours of the image')]
    if len(points):
        keys[1] = (tuple(int(c) for c in np.median(colours[in_box] if in_box.any()
                                                   else colours, axis=0)), keys[1][1])
    scene.save('texture_registration.png', drawing.titled(
        drawing.hstack(panels), f'Registration of the stereo data and the map '
        f'({scene.frame_label})', drawing.key_legend(scene.size * len(panels), keys)))
    return []


def explored_above(cells: MapCells, threshold: float) -> np.ndarray:
    """The cells a picture at ``threshold`` shows: probability above it and, below 1/2,
    only the touched cells and those observed occupied (the paper's fig. 5 shows what was
    explored). A fused map gives every cell the camera saw free a probability above 0;
    those would bury the object in a block of free space. Maps without hit counts: all."""
    keep: np.ndarray = cells.probabilities > threshold
    if threshold < 0.5 and np.any(cells.hits):
        keep &= (cells.hits > 0) | (cells.probabilities > 0.5)
    return keep


def draw_map_above(scene: MapScene, threshold: float) -> list:
    """map_above_<threshold>.png: the cells with probability > ``threshold``, shaded by
    probability; returns its panel of map_thresholds.png."""
    cells = scene.cells
    keep = explored_above(cells, threshold)
    draw = scene.cell_drawer(cells.centres[keep],
                             drawing.probability_colours(cells.probabilities[keep]))
    note = f'{np.count_nonzero(keep)} cells'
    lowest = float(cells.probabilities.min())
    if not cells.complete and threshold < lowest:
        note += f' (file holds only p > {lowest:.2f})'
    panels = _views(draw, scene.camera, scene.frame_label, note)
    scene.save(f'map_above_{threshold:g}.png', drawing.titled(
        drawing.hstack(panels), f'Probabilistic map: cells with probability > {threshold:g} '
        f'({note})', scene.probability_legend(scene.width)))
    return _views(draw, scene.camera, scene.frame_label, note, (OBLIQUE,),
                  f'map, p > {threshold:g}')


def draw_map_thresholds(scene: MapScene) -> list:
    """map_above_<t>.png for every threshold, then map_thresholds.png: their oblique views
    side by side (the paper's fig. 5); returns those panels."""
    panels = []
    for threshold in scene.thresholds:
        panels += draw_map_above(scene, threshold)
    scene.save('map_thresholds.png', drawing.grid_figure(
        panels, len(panels),
        f'Probabilistic map at thresholds {", ".join(f"> {t:g}" for t in scene.thresholds)} '
        '(oblique view)', scene.probability_legend(scene.size * len(panels))))
    return panels


def draw_regions(scene: MapScene, top_fraction: float = 0.1,
                 first_fraction: float = 0.1) -> list:
    """regions.png: the most explored and the first touched cells (:func:`regions`) over
    the occupied map (cells above the highest threshold); returns its overview panel."""
    cells = scene.cells
    most, first, hit_cut, first_cut = regions(cells.hits, cells.first_touch, top_fraction,
                                              first_fraction)
    base_threshold = max(t for t in scene.thresholds) if scene.thresholds else 0.8
    show = (cells.probabilities > base_threshold) | most | first
    colours = np.tile(np.array(BASE_COLOUR, dtype=float), (len(cells.centres), 1))
    colours[most] = EXPLORED_COLOUR
    colours[first] = FIRST_COLOUR
    keys = [(BASE_COLOUR, f'map, p > {base_threshold:g}')]
    if np.isfinite(hit_cut):
        keys.append((EXPLORED_COLOUR, f'most explored: top {top_fraction:.0%} hit counts '
                                      f'(>= {hit_cut:g} hits, {np.count_nonzero(most)} cells)'))
    if np.isfinite(first_cut):
        keys.append((FIRST_COLOUR, f'first touched: earliest {first_fraction:.0%} '
                                   f'(first {first_cut:.2f} s, {np.count_nonzero(first)} cells)'))
    # Highlighted cells are drawn whatever their probability (a first touch may be one hit).
    draw = scene.cell_drawer(cells.centres[show], colours[show])
    subtitle = None if np.isfinite(hit_cut) else 'the map has no hit counts'
    panels = _views(draw, scene.camera, scene.frame_label, subtitle)
    scene.save('regions.png', drawing.titled(
        drawing.hstack(panels), 'Most explored region and first region touched',
        drawing.key_legend(scene.width, keys)))
    return _views(draw, scene.camera, scene.frame_label, 'orange: most hits, purple: first',
                  (OBLIQUE,), 'most explored / first touched')


def draw_truth(scene: MapScene, truth: GroundTruth) -> list:
    """truth.png: the true surface (shaded, its explored part green) and the stray
    fingertip positions (red), in the map's frame; returns its overview panel."""
    step = max(1, len(truth.surface_points) // TRUTH_POINTS)
    surface = truth.surface_points[::step]
    normals = truth.surface_normals[::step]
    explored = explored_mask(surface, truth.contacts, 0.005)
    colours = np.where(explored[:, None], np.array(EXPLORED_SURFACE_COLOUR, dtype=float),
                       np.array(SURFACE_COLOUR, dtype=float))

    def draw(camera):
        # Lambert shading from the surface normals (facing away: as dim as the dimmest);
        # the strays in view drawn with the surface (z-buffered: the object hides those
        # behind it).
        light = np.clip(normals @ camera.light_in_data(), 0.0, 1.0)
        shaded = colours * (0.55 + 0.45 * light)[:, None]
        shown = _shown(camera, scene.box, truth.stray_points)
        points = np.concatenate([surface, truth.stray_points[shown]])
        point_colours = np.concatenate([shaded, np.tile(np.array(STRAY_COLOUR, float),
                                                        (np.count_nonzero(shown), 1))])
        return (drawing.render_points(camera, points, point_colours, 1.5, 0.0),
                _outside(shown, 'stray points'))

    panels = _views(draw, scene.camera, scene.frame_label,
                    f'{len(truth.stray_points)} stray points')
    keys = [(SURFACE_COLOUR, 'true surface'),
            (EXPLORED_SURFACE_COLOUR, 'explored (within 5 mm of a true contact)'),
            (STRAY_COLOUR, 'stray fingertip positions')]
    scene.save('truth.png', drawing.titled(
        drawing.hstack(panels), f'Ground truth: {truth.object_name} ({scene.frame_label})',
        drawing.key_legend(scene.width, keys)))
    return _views(draw, scene.camera, scene.frame_label, 'green: explored, red: strays',
                  (OBLIQUE,), 'ground truth')


def draw_local_maps(scene: MapScene, local: LocalMaps) -> list:
    """local_maps.png, the paper's Fig. 1 (a global map from local maps): the touch map, the
    vision map and the global map fused from them (cells above the highest threshold,
    shaded by probability), and the global map's cells above 1/2 coloured by their entropy
    (darker: more certain); oblique views. Returns the global map's panel for the
    overview."""
    from inhand_mapping.entropy import cell_entropy
    threshold = scene.occupied_threshold
    panels = []
    for title, probability in (('touch map', local.touch), ('vision map', local.vision),
                               ('global map', local.global_)):
        keep = probability > threshold
        draw = scene.cell_drawer(local.centres[keep],
                                 drawing.probability_colours(probability[keep]))
        panels += _views(draw, scene.camera, scene.frame_label,
                         f'{np.count_nonzero(keep)} cells', (OBLIQUE,),
                         f'{title}, p > {threshold:g}')
    likely = local.global_ > 0.5
    certainty = 1.0 - cell_entropy(local.global_[likely])
    draw = scene.cell_drawer(local.centres[likely], drawing.probability_colours(certainty))
    panels += _views(draw, scene.camera, scene.frame_label,
                     f'{np.count_nonzero(likely)} cells, p > 0.5; darker: lower entropy',
                     (OBLIQUE,), 'global map, per-cell entropy')
    scene.save('local_maps.png', drawing.grid_figure(
        panels, 2, 'Local maps and the global map fused from them (paper Fig. 1)',
        scene.probability_legend(scene.size * 2)))
    return panels[2:3]


def draw_overview(scene: MapScene, panels: list, title: str) -> None:
    """figure.png: every picture's oblique view (``panels``) in one figure."""
    columns = {1: 1, 2: 2, 3: 3, 4: 2, 5: 3, 6: 3, 9: 3}.get(len(panels), 4)
    scene.save('figure.png', drawing.grid_figure(panels, columns, title,
                                                 scene.probability_legend(scene.size * columns)))


def draw_all(cells: MapCells, output: Path, thresholds, bag_points: BagPoints | None = None,
             truth: GroundTruth | None = None, frame: str | None = None, *,
             up: str | None = None, size: int = 480, top_fraction: float = 0.1,
             first_fraction: float = 0.1, name: str = 'map',
             raw_up: str | None = None, stereo: StereoCloud | None = None,
             local: LocalMaps | None = None) -> list[Path]:
    """Every picture of the module docstring that the inputs allow; returns the paths.

    ``up``: the map frame's up axis (default :func:`default_up` of ``frame``); ``raw_up``:
    the tracker frame's, for the raw points (default -z, or ``up`` for a tracker-frame map);
    ``stereo``: the bag's stereo shot in the map frame (stereo_points.png and
    texture_registration.png). textured_map.png is drawn when the map has colours;
    ``local``: the local maps of a fused map (local_maps.png).
    """
    scene = MapScene.create(cells, output, thresholds, truth, frame, up, size)
    overview: list[np.ndarray] = []
    if bag_points is not None and len(bag_points.raw):
        overview += draw_raw_points(scene, bag_points,
                                    raw_up or (scene.up if frame == 'tracker' else '-z'))
    if bag_points is not None and len(bag_points.registered):
        overview += draw_registered_points(scene, bag_points)
    if stereo is not None:
        overview += draw_stereo_points(scene, stereo)
    overview += draw_map_thresholds(scene)
    if cells.has_colours:
        overview += draw_textured_map(
            scene, None if stereo is None else stereo.camera_centre)
    if stereo is not None:
        overview += draw_texture_registration(scene, stereo)
    if local is not None:
        overview += draw_local_maps(scene, local)
    overview += draw_regions(scene, top_fraction, first_fraction)
    if truth is not None:
        overview += draw_truth(scene, truth)
    what = ['probabilistic map']
    if cells.has_colours or stereo is not None:
        what.append('texture')
    if bag_points is not None:
        what[:0] = ['raw data', 'registration']
    draw_overview(scene, overview, f'{name}: {", ".join(what[:-1])} and {what[-1]}'
                  if len(what) > 1 else f'{name}: {what[0]}')
    return scene.written
