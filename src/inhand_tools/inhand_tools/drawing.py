"""Pictures of maps and point clouds like the paper's figures 4, 5 and 8 (numpy + OpenCV).

* Orthographic views: the scale is the same everywhere in a picture, so the scale bar (cm)
  is true for every part of the object. A view is an azimuth about the "up" axis and an
  elevation above the horizontal; the data frame's "up" axis is configurable (-z for the
  tracker frame, whose z points down; +z for the simulator's object frames, where the
  object stands on its +z).
* Framing: a panel shows a view box (:class:`ViewBox`, axis-aligned in the data frame) as
  large as the panel allows (:meth:`Camera.for_box`), leaving room for the labels. Boxes
  come from the object, not from everything recorded (:func:`robust_box`), since the
  fingertips travel far off the object between strokes; what lies outside the box is not
  drawn, and the callers say how much that was (:func:`outside_note`).
* Map cells are drawn as shaded cubes, back to front (painter's algorithm: for equal
  axis-aligned cubes on a lattice seen orthographically, sorting the centres by depth is
  a correct order). Geometry is computed for all cells at once; only the polygon fills
  loop over cells. Probability sets the colour, darker = more probable (as in the
  paper); each visible face gets its own light so the cubes read as 3-D.
* Points are splats with a z-buffer (nearest wins), vectorised; over cubes
  (:func:`render_cells_and_points`) they start from the cubes' depths, so the cubes hide
  what lies behind them. A photograph becomes a panel with :func:`image_panel`.
* Everything is drawn at twice the size and shrunk (anti-aliasing); labels are drawn at
  the final size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ['BACKGROUND', 'OBLIQUE', 'SIDE', 'TOP', 'UP_AXES', 'Camera', 'View', 'ViewBox',
           'annotate', 'bounds_of', 'box_of', 'default_margin', 'grid_figure', 'hstack',
           'image_panel', 'key_legend', 'label', 'outside_note', 'probability_colours',
           'probability_legend', 'render_cells', 'render_cells_and_points', 'render_points',
           'robust_box', 'titled']

BACKGROUND = (255, 255, 255)
SUPERSAMPLE = 2
FONT = cv2.FONT_HERSHEY_SIMPLEX
TEXT = (30, 30, 30)

# "up" axis of the data -> rotation into display coordinates (z up, right-handed).
UP_AXES = {
    'z': np.eye(3),
    '-z': np.diag([1.0, -1.0, -1.0]),
    'y': np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
    '-y': np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
    'x': np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
    '-x': np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]]),
}


@dataclass(frozen=True)
class View:
    name: str
    azimuth: float    # degrees about the up axis, 0: looking along -x (display)
    elevation: float  # degrees above the horizontal


# Display x is the object's length (its front towards +x, e.g. the cat's head): the oblique
# view looks from its right side and a little from the front, from above; the side view is
# nearly a profile (front to the right), from slightly above.
OBLIQUE = View('oblique view', -58.0, 24.0)
SIDE = View('side view', -82.0, 7.0)
TOP = View('top view', 0.0, 89.9)

# Sequential colours, light to dark (RGB anchors), for probabilities 0 .. 1.
_ANCHORS = np.array([[0.0, 247, 251, 255], [0.25, 198, 219, 239], [0.5, 133, 183, 219],
                     [0.7, 66, 146, 198], [0.85, 24, 96, 168], [1.0, 8, 40, 90]])


def probability_colours(probabilities) -> np.ndarray:
    """BGR uint8 colour per probability: light (0) to dark blue (1): darker = more probable."""
    p = np.clip(np.asarray(probabilities, dtype=float), 0.0, 1.0)
    rgb = np.stack([np.interp(p, _ANCHORS[:, 0], _ANCHORS[:, k]) for k in (1, 2, 3)], axis=-1)
    return np.round(rgb[..., ::-1]).astype(np.uint8)


def bounds_of(*point_sets, robust: bool = False) -> tuple[np.ndarray, float]:
    """(centre, radius) of a ball around the given point sets: the centre of their
    bounding box and the largest distance from it (the 0.5-99.5 percentile box and the
    99.5th percentile distance per set if ``robust``); a 1 cm ball if there are no points."""
    sets = []
    for points in point_sets:
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        points = points[np.all(np.isfinite(points), axis=1)]
        if len(points):
            sets.append(points)
    if not sets:
        return np.zeros(3), 0.01
    use_percentiles = [robust and len(points) > 50 for points in sets]
    lows = [np.percentile(p, 0.5, axis=0) if r else p.min(axis=0)
            for p, r in zip(sets, use_percentiles)]
    highs = [np.percentile(p, 99.5, axis=0) if r else p.max(axis=0)
             for p, r in zip(sets, use_percentiles)]
    centre = (np.min(lows, axis=0) + np.max(highs, axis=0)) / 2.0
    radius = 0.0
    for points, r in zip(sets, use_percentiles):
        distance = np.linalg.norm(points - centre, axis=1)
        radius = max(radius, float(np.percentile(distance, 99.5) if r else distance.max()))
    return centre, max(radius, 0.005)


@dataclass(frozen=True, eq=False)
class ViewBox:
    """What a panel shows: an axis-aligned box of the data frame (metres), ``low`` to
    ``high``; nothing outside it is drawn. ``fit``: points that the camera frames tightly
    (the object's, e.g. surface samples), with ``margin`` (m) of room around them; the
    box's corners if None."""

    low: np.ndarray
    high: np.ndarray
    fit: np.ndarray | None = None
    margin: float = 0.0

    FIT_POINTS = 20000  # at most this many framing points are kept (evenly strided)

    def __post_init__(self):
        object.__setattr__(self, 'low', np.asarray(self.low, dtype=float).reshape(3))
        object.__setattr__(self, 'high', np.asarray(self.high, dtype=float).reshape(3))
        if self.fit is not None:
            fit = _finite(self.fit)
            fit = fit[::max(1, -(-len(fit) // self.FIT_POINTS))]
            object.__setattr__(self, 'fit', fit if len(fit) else None)

    @property
    def centre(self) -> np.ndarray:
        return (self.low + self.high) / 2.0

    @property
    def extent(self) -> np.ndarray:
        return self.high - self.low

    def corners(self) -> np.ndarray:
        bounds = (self.low, self.high)
        return np.array([[bounds[i][0], bounds[j][1], bounds[k][2]]
                         for i in (0, 1) for j in (0, 1) for k in (0, 1)])

    def grown(self, margin) -> ViewBox:
        """The box grown by ``margin`` (m, scalar or per axis), framing the same points
        with that much more room."""
        margin = np.asarray(margin, dtype=float)
        return ViewBox(self.low - margin, self.high + margin, self.fit,
                       self.margin + float(np.max(margin)))

    def contains(self, points) -> np.ndarray:
        """Mask of the points (n, 3) inside the box (non-finite points are outside)."""
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        with np.errstate(invalid='ignore'):
            return np.all((points >= self.low) & (points <= self.high), axis=1)


def _finite(points) -> np.ndarray:
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    return points[np.all(np.isfinite(points), axis=1)]


def default_margin(box: ViewBox) -> float:
    """Room around an object's box (m): 8 % of its largest extent, at least 1 cm."""
    return max(0.01, 0.08 * float(box.extent.max()))


def box_of(points, margin: float | None = None) -> ViewBox | None:
    """The bounding box of the (finite) points grown by ``margin`` (default:
    :func:`default_margin`), framing those points; None without points."""
    points = _finite(points)
    if len(points) == 0:
        return None
    box = ViewBox(points.min(axis=0), points.max(axis=0), points)
    return box.grown(default_margin(box) if margin is None else margin)


def robust_box(points, low: float = 5.0, high: float = 95.0, reach: float = 0.02,
               keep: float = 1.0, margin: float | None = None) -> ViewBox | None:
    """A box around where most of the points are, ignoring far, sparse excursions.

    The ``low``-``high`` percentile box of the points (per axis) finds the dense region;
    the points within ``reach`` (m) of it are the object's (its extremities included);
    their ``keep``-(100 - ``keep``) percentile box, grown by ``margin`` (default:
    :func:`default_margin`), is the result, framing the points inside it. None without
    points.
    """
    points = _finite(points)
    if len(points) == 0:
        return None
    core = ViewBox(*np.percentile(points, [low, high], axis=0)).grown(reach)
    near = points[core.contains(points)]
    if len(near) == 0:
        near = points
    box = ViewBox(*np.percentile(near, [keep, 100.0 - keep], axis=0))
    box = ViewBox(box.low, box.high, near[box.contains(near)])
    return box.grown(default_margin(box) if margin is None else margin)


def outside_note(count: int, what: str = 'points') -> str:
    """Subtitle text for what a panel leaves out: '+ 812 points outside the view'."""
    if count == 1 and what.endswith('s'):
        what = what[:-1]
    return f'+ {count:,} {what} outside the view'


class Camera:
    """Orthographic camera framing a ball (``centre``, ``radius``) of the data frame in a
    ``size`` x ``size`` panel; :meth:`for_box` frames a :class:`ViewBox` instead.
    ``offset`` (pixels, right and down) moves the picture of ``centre`` off the panel's
    centre."""

    def __init__(self, view: View, centre, radius: float, size: int, up: str = '-z',
                 fill: float = 0.86):
        if up not in UP_AXES:
            raise ValueError(f'up axis must be one of {", ".join(UP_AXES)}, not {up!r}')
        self.view, self.size, self.up = view, int(size), up
        self.to_display = UP_AXES[up]
        self.centre = np.asarray(centre, dtype=float)
        az, el = math.radians(view.azimuth), math.radians(view.elevation)
        eye = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        right = np.array([-math.sin(az), math.cos(az), 0.0])
        screen_up = np.cross(eye, right)
        # Rows: right, up, towards the camera, in data coordinates.
        self.basis = np.stack([right, screen_up, eye]) @ self.to_display
        self.scale = fill * self.size / 2.0 / max(radius, 1e-6)  # pixels per metre
        self.offset = np.zeros(2)
        self.area = (0.0, 0.0, float(self.size), float(self.size))

    @classmethod
    def for_box(cls, view: View, box: ViewBox, size: int, up: str = '-z') -> Camera:
        """The camera showing ``box`` as large as it fits in the panel's free area (below
        the title and subtitles, above the scale bar, a little in from the sides): its
        framing points with the box's margin around them, else its corners."""
        camera = cls(view, box.centre, 1.0, size, up)
        if box.fit is not None:
            local = (box.fit - camera.centre) @ camera.basis.T
            low = local[:, :2].min(axis=0) - box.margin
            high = local[:, :2].max(axis=0) + box.margin
        else:
            local = (box.corners() - camera.centre) @ camera.basis.T
            low, high = local[:, :2].min(axis=0), local[:, :2].max(axis=0)
        width, height = np.maximum(high - low, 1e-6)
        top, bottom = min(64.0, 0.3 * size), min(28.0, 0.14 * size)
        side = 0.03 * size
        camera.scale = min((size - 2 * side) / width, (size - top - bottom) / height)
        # The middle of the framed extent goes to the middle of the free area.
        middle = (low + high) / 2.0
        camera.offset = np.array([-middle[0] * camera.scale,
                                  (top - bottom) / 2.0 + middle[1] * camera.scale])
        camera.area = (side, top, size - side, size - bottom)
        return camera

    def in_view(self, points, inset: float = 0.0) -> np.ndarray:
        """Mask of the points whose pictures fall inside the panel's ``area`` (left, top,
        right, bottom pixels; the free area of :meth:`for_box`, else the whole panel), at
        least ``inset`` pixels in from its edges."""
        pixels, _ = self.project(points)
        left, top, right, bottom = np.array(self.area) + np.array([1, 1, -1, -1]) * inset
        with np.errstate(invalid='ignore'):
            return ((pixels[:, 0] >= left) & (pixels[:, 0] <= right)
                    & (pixels[:, 1] >= top) & (pixels[:, 1] <= bottom))

    def project(self, points, factor: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (n, 2) float (at ``factor`` times the size) and depth (n,),
        larger = nearer the camera."""
        local = (np.asarray(points, dtype=float).reshape(-1, 3) - self.centre) @ self.basis.T
        half = self.size * factor / 2.0
        pixels = np.empty((len(local), 2))
        pixels[:, 0] = half + (self.offset[0] + local[:, 0] * self.scale) * factor
        pixels[:, 1] = half + (self.offset[1] - local[:, 1] * self.scale) * factor
        return pixels, local[:, 2]

    def light_in_data(self) -> np.ndarray:
        """The pictures' light direction (towards the light) in data coordinates."""
        return self.basis.T @ _LIGHT

    def direction(self, vectors) -> np.ndarray:
        """Screen direction (right, down) of data-frame vectors, pixels per metre."""
        local = np.asarray(vectors, dtype=float).reshape(-1, 3) @ self.basis.T
        return np.stack([local[:, 0], -local[:, 1]], axis=1) * self.scale


def _blank(size: int) -> np.ndarray:
    return np.full((size, size, 3), BACKGROUND, dtype=np.uint8)


def _shrink(image: np.ndarray, size: int) -> np.ndarray:
    return cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)


_CUBE_CORNERS = np.array([[i, j, k] for i in (-0.5, 0.5) for j in (-0.5, 0.5)
                          for k in (-0.5, 0.5)])
# Faces by axis and side: corner indices (in _CUBE_CORNERS order) around the face.
_FACES = {(0, -1): [0, 1, 3, 2], (0, 1): [4, 5, 7, 6], (1, -1): [0, 1, 5, 4],
          (1, 1): [2, 3, 7, 6], (2, -1): [0, 2, 6, 4], (2, 1): [1, 3, 7, 5]}
_LIGHT = np.array([-0.35, 0.75, 0.55])  # in camera coordinates (right, up, towards viewer)
_LIGHT /= np.linalg.norm(_LIGHT)


def render_cells(camera: Camera, centres, resolution: float, colours,
                 edges: bool = True) -> np.ndarray:
    """Cubes of edge ``resolution`` at ``centres`` (data frame), ``colours`` BGR (n, 3) or
    one colour; returns a ``camera.size`` square BGR image."""
    image, _ = _draw_cells(camera, centres, resolution, colours, edges)
    return _shrink(image, camera.size)


def render_cells_and_points(camera: Camera, centres, resolution: float, cell_colours,
                            points, point_colours, radius_px: float = 1.5,
                            depth_cue: float = 0.0, tolerance: float | None = None
                            ) -> np.ndarray:
    """Cubes (as :func:`render_cells`) with points (as :func:`render_points`) over them,
    hidden where a cube is in front: a point is drawn unless the cube pictured there has
    its centre more than ``tolerance`` (m, default one cell edge) nearer the camera, so
    the points on the cubes' surface show and those behind the object do not."""
    image, cell_depth = _draw_cells(camera, centres, resolution, cell_colours, True,
                                    with_depth=True)
    tolerance = resolution if tolerance is None else tolerance
    _splat_points(image, cell_depth - tolerance, camera, points, point_colours, radius_px,
                  depth_cue)
    return _shrink(image, camera.size)


def _draw_cells(camera: Camera, centres, resolution: float, colours, edges: bool,
                with_depth: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """The cubes at the supersampled size: (BGR image, and with ``with_depth`` the depth
    of the nearest cube's centre at every pixel (-inf where there is none))."""
    factor = SUPERSAMPLE
    image = _blank(camera.size * factor)
    depth_image = (np.full(image.shape[:2], -np.inf, dtype=np.float32) if with_depth
                   else None)
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    if len(centres) == 0:
        return image, depth_image
    colours = np.broadcast_to(np.asarray(colours, dtype=float).reshape(-1, 3),
                              (len(centres), 3))
    # Visible faces: the same for every cube in an orthographic view.
    faces, shades = [], []
    for (axis, side), corners in _FACES.items():
        normal = np.zeros(3)
        normal[axis] = side
        facing = camera.basis @ normal  # normal in camera coordinates
        if facing[2] > 1e-3:
            faces.append(corners)
            shades.append(0.55 + 0.45 * max(0.0, float(facing @ _LIGHT)))
    depths = camera.project(centres)[1]
    order = np.argsort(depths, kind='stable')  # far first
    corners = (centres[order, None, :] + _CUBE_CORNERS[None] * resolution).reshape(-1, 3)
    pixels, _ = camera.project(corners, factor)
    shift = 4  # fixed-point sub-pixel bits for OpenCV
    pixels = np.round(pixels * (1 << shift)).astype(np.int32).reshape(len(centres), 8, 2)
    polygons = np.ascontiguousarray(pixels[:, np.array(faces)])  # (n, faces, 4, 2)
    face_colours = colours[order][:, None, :] * np.array(shades)[None, :, None]
    face_colours = np.clip(face_colours, 0, 255).astype(np.uint8).tolist()
    edge_colours = np.clip(colours[order] * 0.55, 0, 255).astype(np.uint8).tolist()
    thickness = max(1, factor // 2)
    if with_depth:
        # A cube's outline: the same corners for every cube (orthographic view).
        hull = cv2.convexHull(pixels[0].astype(np.float32), returnPoints=False).ravel()
        outlines = np.ascontiguousarray(pixels[:, hull])
        cube_depths = depths[order].tolist()
    for index in range(len(centres)):
        quads = polygons[index]
        for face in range(len(faces)):
            cv2.fillPoly(image, [quads[face]], face_colours[index][face], cv2.LINE_8, shift)
        if edges:
            cv2.polylines(image, list(quads), True, edge_colours[index], thickness,
                          cv2.LINE_8, shift)
        if with_depth:
            cv2.fillConvexPoly(depth_image, outlines[index], cube_depths[index], cv2.LINE_8,
                               shift)
    return image, depth_image


def render_points(camera: Camera, points, colours, radius_px: float = 1.5,
                  depth_cue: float = 0.45) -> np.ndarray:
    """Points as round splats, nearest on top; colours BGR (n, 3) or one colour. Far
    points are blended towards the background by up to ``depth_cue``."""
    image = _blank(camera.size * SUPERSAMPLE)
    _splat_points(image, np.full(image.shape[:2], -np.inf), camera, points, colours,
                  radius_px, depth_cue)
    return _shrink(image, camera.size)


def _splat_points(image: np.ndarray, best: np.ndarray, camera: Camera, points, colours,
                  radius_px: float, depth_cue: float) -> None:
    """Draw the points' splats into ``image`` (supersampled) where they are nearer than
    ``best`` (the depth already there, per pixel; updated)."""
    factor = SUPERSAMPLE
    size = camera.size * factor
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    finite = np.all(np.isfinite(points), axis=1)
    points = points[finite]
    if len(points) == 0:
        return
    colours = np.broadcast_to(np.asarray(colours, dtype=float).reshape(-1, 3),
                              (len(finite), 3))[finite]
    pixels, depth = camera.project(points, factor)
    span = np.ptp(depth) if len(depth) > 1 else 0.0
    nearness = (depth - depth.min()) / span if span > 0 else np.ones_like(depth)
    blend = depth_cue * (1.0 - nearness)[:, None]
    shaded = colours * (1.0 - blend) + np.asarray(BACKGROUND, dtype=float) * blend
    # Z-buffer of the splat centres: the nearest point of each pixel (first occurrence in
    # nearest-first order), then the splat disk by shifting that buffer over the offsets,
    # keeping the nearer value at every pixel (whole-image operations, no loop per point).
    base = np.round(pixels).astype(np.int64)
    inside = (base[:, 0] >= 0) & (base[:, 0] < size) & (base[:, 1] >= 0) & (base[:, 1] < size)
    base, depth, shaded = base[inside], depth[inside], shaded[inside]
    order = np.argsort(-depth, kind='stable')
    flat = (base[:, 1] * size + base[:, 0])[order]
    _, first = np.unique(flat, return_index=True)
    chosen = order[first]
    centre_depth = np.full(size * size, -np.inf)
    centre_colour = np.zeros((size * size, 3), dtype=np.uint8)
    centre_depth[flat[first]] = depth[chosen]
    centre_colour[flat[first]] = np.clip(shaded[chosen], 0, 255).astype(np.uint8)
    centre_depth = centre_depth.reshape(size, size)
    centre_colour = centre_colour.reshape(size, size, 3)
    radius = max(radius_px * factor, 0.5)
    r = int(math.ceil(radius))
    for dx in range(-r, r + 1):
        for dy in range(-r, r + 1):
            if dx * dx + dy * dy > radius * radius + 0.25:
                continue
            # Pixel (y, x) takes the centre at (y - dy, x - dx).
            ys = slice(max(dy, 0), size + min(dy, 0))
            xs = slice(max(dx, 0), size + min(dx, 0))
            ys_src = slice(max(-dy, 0), size + min(-dy, 0))
            xs_src = slice(max(-dx, 0), size + min(-dx, 0))
            source = centre_depth[ys_src, xs_src]
            target = best[ys, xs]
            nearer = source > target
            target[nearer] = source[nearer]
            image[ys, xs][nearer] = centre_colour[ys_src, xs_src][nearer]


def label(image, text, origin, scale=0.5, colour=TEXT, thickness=1) -> None:
    """Text at ``origin`` (pixels, the baseline's left end), anti-aliased."""
    _text(image, text, origin, scale, colour, thickness)


def _text(image, text, origin, scale=0.5, colour=TEXT, thickness=1) -> None:
    cv2.putText(image, text, (int(origin[0]), int(origin[1])), FONT, scale, colour, thickness,
                cv2.LINE_AA)


def _text_width(text, scale=0.5, thickness=1) -> int:
    return cv2.getTextSize(text, FONT, scale, thickness)[0][0]


def _nice_length(target: float) -> float:
    """1, 2 or 5 times a power of ten, at most ``target`` (metres)."""
    power = 10.0 ** math.floor(math.log10(target))
    for step in (5.0, 2.0, 1.0):
        if step * power <= target:
            return step * power
    return power


def _length_label(metres: float) -> str:
    if metres >= 0.01:
        cm = metres * 100
        return f'{cm:g} cm'
    return f'{metres * 1000:g} mm'


def annotate(image: np.ndarray, camera: Camera, title: str | None = None,
             subtitle: str | None = None, frame_label: str | None = None) -> np.ndarray:
    """A panel's labels: title, subtitle (lines separated by newlines), a scale bar (cm)
    and the data frame's axes."""
    image = image.copy()
    size = camera.size
    if title:
        _text(image, title, (10, 22), 0.6, TEXT, 1)
    for line, text in enumerate((subtitle or '').split('\n')):
        if text:
            _text(image, text, (10, 42 + 17 * line), 0.45, (90, 90, 90))
    # Scale bar, bottom left.
    length = _nice_length(0.28 * size / camera.scale)
    bar = int(round(length * camera.scale))
    x0, y0 = 14, size - 18
    cv2.line(image, (x0, y0), (x0 + bar, y0), TEXT, 2, cv2.LINE_AA)
    for x in (x0, x0 + bar):
        cv2.line(image, (x, y0 - 5), (x, y0 + 5), TEXT, 1, cv2.LINE_AA)
    label = _length_label(length)
    _text(image, label, (x0 + (bar - _text_width(label, 0.45)) / 2, y0 - 8), 0.45)
    # Axes of the data frame, bottom right.
    origin = np.array([size - 52.0, size - 46.0])
    directions = camera.direction(np.eye(3))
    longest = np.linalg.norm(directions, axis=1).max()
    colours = [(40, 40, 210), (40, 160, 40), (210, 90, 30)]  # x red, y green, z blue (BGR)
    for axis, name in enumerate('xyz'):
        d = directions[axis] / longest * 30.0
        end = origin + d
        if np.linalg.norm(d) < 3.0:  # pointing at (or away from) the viewer
            cv2.circle(image, tuple(int(v) for v in origin), 4, colours[axis], 1, cv2.LINE_AA)
            end = origin + np.array([6.0, -6.0 - 8 * axis])
        else:
            cv2.arrowedLine(image, tuple(int(v) for v in origin), tuple(int(v) for v in end),
                            colours[axis], 2, cv2.LINE_AA, tipLength=0.25)
        _text(image, name, end + np.array([3.0, 4.0]), 0.45, colours[axis])
    if frame_label:
        _text(image, frame_label, (size - _text_width(frame_label, 0.4) - 8, 18), 0.4,
              (110, 110, 110))
    cv2.rectangle(image, (0, 0), (size - 1, size - 1), (205, 205, 205), 1)
    return image


def image_panel(image: np.ndarray, size: int, title: str | None = None,
                subtitle: str | None = None) -> np.ndarray:
    """A photograph (BGR) as a panel ``size`` pixels high, titled like :func:`annotate`'s
    panels: the image scaled (aspect kept) to the height left under the title and
    subtitles, as wide as that makes it."""
    top = int(min(64.0, 0.3 * size))
    side = max(4, int(0.03 * size))
    height = size - top - side
    scale = height / image.shape[0]
    width = max(1, int(round(image.shape[1] * scale)))
    scaled = cv2.resize(np.ascontiguousarray(image), (width, height),
                        interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
    panel = np.full((size, width + 2 * side, 3), BACKGROUND, dtype=np.uint8)
    panel[top:top + height, side:side + width] = scaled
    if title:
        _text(panel, title, (10, 22), 0.6, TEXT, 1)
    for line, text in enumerate((subtitle or '').split('\n')):
        if text:
            _text(panel, text, (10, 42 + 17 * line), 0.45, (90, 90, 90))
    cv2.rectangle(panel, (0, 0), (panel.shape[1] - 1, size - 1), (205, 205, 205), 1)
    return panel


def hstack(images: list[np.ndarray]) -> np.ndarray:
    height = max(image.shape[0] for image in images)
    padded = [np.pad(image, ((0, height - image.shape[0]), (0, 0), (0, 0)),
                     constant_values=255) for image in images]
    return np.concatenate(padded, axis=1)


def titled(body: np.ndarray, title: str, footer: np.ndarray | None = None) -> np.ndarray:
    """``body`` under a title bar, with an optional footer strip (legend) below."""
    width = body.shape[1]
    bar = np.full((40, width, 3), 255, dtype=np.uint8)
    _text(bar, title, (12, 27), 0.7, TEXT, 2)
    parts = [bar, body]
    if footer is not None:
        if footer.shape[1] < width:
            footer = np.pad(footer, ((0, 0), (0, width - footer.shape[1]), (0, 0)),
                            constant_values=255)
        parts.append(footer[:, :width])
    return np.concatenate(parts, axis=0)


def grid_figure(panels: list[np.ndarray], columns: int, title: str,
                footer: np.ndarray | None = None) -> np.ndarray:
    """Panels (equal squares) in rows of ``columns``, under a title."""
    size = panels[0].shape[0]
    rows = []
    for start in range(0, len(panels), columns):
        row = panels[start:start + columns]
        row = row + [np.full((size, size, 3), 255, dtype=np.uint8)] * (columns - len(row))
        rows.append(np.concatenate(row, axis=1))
    return titled(np.concatenate(rows, axis=0), title, footer)


def probability_legend(width: int, thresholds=(0.6, 0.8)) -> np.ndarray:
    """A horizontal colour bar: occupancy probability 0 .. 1, darker = more probable."""
    strip = np.full((48, width, 3), 255, dtype=np.uint8)
    label = 'occupancy probability (darker = more probable)'
    _text(strip, label, (12, 30), 0.45)
    x0 = 24 + _text_width(label, 0.45)
    x1 = min(width - 20, x0 + 320)
    if x1 - x0 < 60:
        return strip
    ramp = probability_colours(np.linspace(0.0, 1.0, x1 - x0))
    strip[12:26, x0:x1] = ramp[None]
    cv2.rectangle(strip, (x0, 12), (x1 - 1, 25), (150, 150, 150), 1)
    for value in sorted({0.0, *thresholds, 1.0}):
        x = int(round(x0 + value * (x1 - x0 - 1)))
        cv2.line(strip, (x, 26), (x, 30), TEXT, 1)
        text = f'{value:g}'
        _text(strip, text, (x - _text_width(text, 0.4) / 2, 42), 0.4)
    return strip


def key_legend(width: int, entries: list[tuple[tuple[int, int, int], str]]) -> np.ndarray:
    """A strip of coloured squares (BGR) with labels."""
    strip = np.full((34, width, 3), 255, dtype=np.uint8)
    x = 12
    for colour, label in entries:
        cv2.rectangle(strip, (x, 10), (x + 14, 24), tuple(int(c) for c in colour), -1)
        cv2.rectangle(strip, (x, 10), (x + 14, 24), (120, 120, 120), 1)
        _text(strip, label, (x + 20, 22), 0.45)
        x += 20 + _text_width(label, 0.45) + 22
    return strip
