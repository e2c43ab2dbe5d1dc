"""Colour for the map's occupied cells from the rectified left image (``occupancy/textured``).

A cell is textured where the camera saw *that cell's* surface. Each occupied cell centre
goes from the map frame ``object`` into the rectified left camera (map -> tracker with the
object pose, tracker -> ``stereo_left_optical`` with the inverse camera pose, raw ->
rectified with ``R_left``) and is projected with the rectified ``P``. Then:

1. *In front and inside*: depth > 1 mm and the centre's pixel inside the image.
2. *Seen at the cell* (the depth rule): the cell's footprint, its face seen at its depth
   (``f * resolution / z`` pixels a side), is sampled on a fixed ``samples x samples``
   grid (7 x 7). Each sample's stereo depth puts a measured surface point on the pixel's
   ray, and the sample counts when that point lies in the cell's *window*: the cell, grown
   along the line of sight by ``window.in_front`` cells towards the camera (0.25) and
   ``window.behind`` cells away from it (1.0), and across it by ``window.beside`` (0.25),
   unless the point lies in *another occupied cell*: then it is that cell's surface. A
   touch map's cells do not sit on the surface the way a mesh's do: a hand that hovers,
   trembles or presses leaves cells a few millimetres off it, and the seen surface then
   passes beside their centres or through a free neighbour; the window takes those in. A
   cell on the back side is a whole object thickness behind the measured surface, an
   occluded cell is behind another surface, and the back of a thin part right behind its
   front has the front's occupied cells in between: none of these gets samples. At least
   ``min_samples`` (2 of 49) must count, so that a stray depth (a stereo mismatch) does not
   paint a cell on its own. **No stereo depth is no evidence**: a sample without a
   measurement (NaN, inf) takes the depth of the nearest pixel with one within ``fill``
   (2 px: stereo leaves thin gaps at edges), and otherwise never counts (the image alone
   cannot tell the front of an object from its back).
3. *Seen from the map* (``map_view``, the second way a cell gets colour): where the window
   finds too little, the map's own cells say what the camera faces. Every occupied cell's
   face, seen at its depth, is drawn into a depth image of the map (the nearest cell wins);
   a footprint sample counts for a cell when no other cell is in front of it there by more
   than ``MapView.ahead`` (0.7 of a cell) and the stereo depth there (or of the nearest pixel
   with one within ``MapView.reach``, 4 px) lies no more than ``MapView.tolerance`` (a
   cell) in front of the cell's depth and no more than ``MapView.behind`` (4 cells) behind
   it, unless that measured point lies in another occupied cell (then it is that cell's
   surface, as for the window). At least ``MapView.min_samples`` (5 of 49) must count.
   Behind: the camera looks through where the map's front cell is, so the cell is off the
   surface (a hovering finger's layer) or stereo reads the surface too far (dark glass
   reads 5-10 mm behind it); either way the pixel shows that cell's surface. This takes
   the cells a touch map holds a cell or so *inside* the surface (a pressing finger, a
   pad's centre), whose measured surface lies in the free cell in front: the window does
   not reach them, and nothing of the map hides them. A thin part's back stays unpainted
   (its front cells are in front of it). *Blind samples* (``MapView.blind``): a sample
   with no stereo depth within ``reach`` counts too where it lies in a *hole* of the depth
   (missing pixels that measured ones enclose, :func:`depth_holes`: dark glass, a blank
   patch; not the open background, which reaches the image's border) and the cell clearly
   faces the camera (its outward direction over ``BLIND_RADIUS`` cells at least
   ``BLIND_OUTWARD`` cells long and towards the camera): there the map's front cell is the
   only surface the pixel can show. Elsewhere no depth is still no evidence. The colour is
   the median of the samples that count, as for the window.
4. *Facing the camera* (the orientation rule, ``orientation``, off by default): the cell's
   outward direction estimated as its centre minus the centroid of the occupied cells
   around it (``'local'``: a cube of ``2 * orientation_radius + 1`` cells, from
   summed-volume tables; ``'centroid'``: all occupied cells, exact for a sphere); a cell
   whose outward direction points away from the camera is not textured.

The window and the map's view were chosen on touch sessions of other hands and objects
(``test/benchmarks/bench_texture_sessions.py``, its ``tune`` set; docs/stereo.md has the
figures): the cell alone (the rule before) textured 0.70 of the cells the camera saw;
more in front paints more, and more of the back of thin walls (0.75 cells: 0.86 of the
seen cells, 1.9 % of the unseen ones painted far from any seen surface); 0.25 in front and
1 behind: 0.79, 0.8 %; with the map's view 0.81, 0.7 % (1.25 cells of tolerance: 0.83, but
worse colours in the tail). On sessions not used to choose (``report``) 0.65 -> 0.75 ->
0.78, back faces 0.3 -> 0.8 -> 0.9 %. On ``inhand_sim``'s cat from four sides with exact
cells (``bench_texture.py``) it textures 86 % of the seen cells (98 % of the seen area),
1 of 2,812 hidden cells far from the seen surface, no wrong colour; a 6 mm plate's 224
back cells stay unpainted.

The colour is the per-channel median of the samples that count (not one pixel: robust to
noise and to the edges of occluders). Cells that are not textured get colour 0, as the
``occupancy/textured`` contract says. The footprints are read by compiled loops
(``texture_kernels.py``): a 10,000-cell map on a 640x480 image in about 15 ms here.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple, TypeAlias

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage  # type: ignore[import-untyped]

from inhand_common.array_types import Bools, Floats, Matrix3, Points, Vector3
from inhand_common.rotations import quaternion_to_matrix
from inhand_stereo.camera_model import CameraModel
from inhand_stereo.texture_kernels import front_pixels, map_depth, window_pixels

__all__ = ['CellTexture', 'MapView', 'Orientation', 'Pose', 'Projection', 'Window',
           'depth_holes', 'facing_camera', 'map_to_rectified', 'project_cells', 'texture_cells']

Pose: TypeAlias = tuple[ArrayLike, ArrayLike]     # (position (3,) m, quaternion (4,) x y z w)
Orientation: TypeAlias = Literal['local', 'centroid', 'none']
Colours: TypeAlias = NDArray[np.uint8]            # (N, 3) RGB

MIN_DEPTH = 1e-3   # m: closer than this to the camera's centre counts as behind it


class CellTexture(NamedTuple):
    """Colour per cell (RGB, 0 where not textured) and where the camera saw the cell."""

    colours: Colours        # (N, 3) uint8
    textured: Bools         # (N,)


class Projection(NamedTuple):
    """Cells in the rectified left camera: pixel coordinates (u, v) and depth z (m)."""

    u: Floats               # (N,)
    v: Floats               # (N,)
    z: Floats               # (N,) along the rectified optical axis; <= 0 behind the camera


def _pose(pose: Pose, name: str) -> tuple[Matrix3, Vector3]:
    position = np.asarray(pose[0], dtype=np.float64).reshape(-1)
    if position.shape != (3,) or not np.all(np.isfinite(position)):
        raise ValueError(f'{name}: position must be 3 finite numbers, got {pose[0]!r}')
    rotation: Matrix3 = quaternion_to_matrix(np.asarray(pose[1], dtype=np.float64).reshape(4))
    return rotation, position


def map_to_rectified(camera_pose: Pose, object_pose: Pose, R_left: ArrayLike
                     ) -> tuple[Matrix3, Vector3]:
    """(M, b) with ``p_rectified = M @ p_map + b``.

    ``object_pose``: the map frame ``object`` in the tracker frame (identity in static mode);
    ``camera_pose``: ``stereo_left_optical`` in the tracker frame; ``R_left``: the rectifying
    rotation of the left camera (raw -> rectified, CameraInfo's R).
    """
    r_cam, t_cam = _pose(camera_pose, 'camera_pose')
    r_obj, t_obj = _pose(object_pose, 'object_pose')
    rectify = np.asarray(R_left, dtype=np.float64)
    if rectify.shape != (3, 3) or not np.all(np.isfinite(rectify)):
        raise ValueError(f'R_left must be a finite 3x3 rotation, got shape {rectify.shape}')
    to_camera = rectify @ r_cam.T
    matrix: Matrix3 = to_camera @ r_obj
    offset: Vector3 = to_camera @ (t_obj - t_cam)
    return matrix, offset


def project_cells(centres: ArrayLike, camera: CameraModel, R_left: ArrayLike,
                  camera_pose: Pose, object_pose: Pose) -> Projection:
    """Pixel coordinates (ROS convention: integers at pixel centres) and depths of map-frame
    points in the rectified left image, projected with the camera's ``P``."""
    matrix, offset = map_to_rectified(camera_pose, object_pose, R_left)
    return _project(np.asarray(centres, dtype=np.float64).reshape(-1, 3), camera.P, matrix,
                    offset)


def _project(points: Points, P: Floats, matrix: Matrix3, offset: Vector3) -> Projection:
    return _project_rectified(points @ matrix.T + offset, P)


def _project_rectified(rectified: Points, P: Floats) -> Projection:
    """Pixel coordinates and depths of points already in the rectified camera frame."""
    w = rectified @ P[2, :3] + P[2, 3]
    z = rectified[:, 2]
    safe = np.where((z > MIN_DEPTH) & (w > 0.0), w, np.inf)
    u = (rectified @ P[0, :3] + P[0, 3]) / safe
    v = (rectified @ P[1, :3] + P[1, 3]) / safe
    return Projection(u, v, np.where(safe < np.inf, z, -np.inf))


def facing_camera(centres: Points, resolution: float, camera_position: Vector3,
                  orientation: Orientation = 'local', radius: int = 4,
                  min_outward: float = 0.5, flat: bool = True) -> Bools:
    """False for cells whose outward direction (centre minus the centroid of the occupied
    cells around it) points away from ``camera_position`` (map frame); True elsewhere;
    ``flat`` where the neighbourhood is too flat to tell (direction shorter than
    ``min_outward`` cells). ``centres`` are the occupied cells (on the grid's lattice)."""
    count = len(centres)
    if orientation == 'none' or count == 0:
        return np.ones(count, dtype=bool)
    if orientation == 'centroid':
        outward = centres - centres.mean(axis=0)
    elif orientation == 'local':
        outward = _local_outward(centres, resolution, radius)
    else:
        raise ValueError(f"orientation must be 'local', 'centroid' or 'none', got {orientation!r}")
    towards = np.einsum('ij,ij->i', outward, camera_position - centres)
    unknown = np.einsum('ij,ij->i', outward, outward) < (min_outward * resolution) ** 2
    facing: Bools = np.where(unknown, flat, towards >= 0.0)
    return facing


def _lattice(centres: Points, resolution: float, pad: int = 1
             ) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
    """Indices (N, 3) of the cells on their lattice (from the lowest, plus ``pad``) and the
    occupancy of that lattice's box, ``pad`` free cells around the occupied ones."""
    ijk = np.rint((centres - centres.min(axis=0)) / resolution).astype(np.intp) + pad
    occupied = np.zeros(tuple(int(n) for n in ijk.max(axis=0) + pad + 1), dtype=bool)
    occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return ijk, occupied


def _local_outward(centres: Points, resolution: float, radius: int) -> Points:
    """Centre minus the centroid of the occupied cells in the (2r+1)^3 cube around each
    cell, from summed-volume tables over the occupied cells' bounding box."""
    ijk, occupied = _lattice(centres, resolution, pad=radius)
    shape = occupied.shape
    # channels: count, then the sums of i, j, k; a zero plane in front of every axis
    table = np.zeros((4, shape[0] + 1, shape[1] + 1, shape[2] + 1), dtype=np.float64)
    i, j, k = ijk[:, 0] + 1, ijk[:, 1] + 1, ijk[:, 2] + 1
    table[0, i, j, k] = 1.0
    table[1, i, j, k] = ijk[:, 0]
    table[2, i, j, k] = ijk[:, 1]
    table[3, i, j, k] = ijk[:, 2]
    for axis in (1, 2, 3):
        np.cumsum(table, axis=axis, out=table)
    lo, hi = ijk - radius, ijk + radius + 1      # the cube [lo, hi) in table coordinates
    sums = np.zeros((4, len(centres)), dtype=np.float64)
    for corner in range(8):
        a = hi[:, 0] if corner & 1 else lo[:, 0]
        b = hi[:, 1] if corner & 2 else lo[:, 1]
        c = hi[:, 2] if corner & 4 else lo[:, 2]
        sign = 1.0 if bin(corner ^ 7).count('1') % 2 == 0 else -1.0
        sums += sign * table[:, a, b, c]
    centroid = sums[1:].T / sums[0][:, None]
    outward: Points = (ijk - centroid) * resolution
    return outward


# The window around a cell (cells, from its faces) in which a measured point is that cell's
# surface; chosen on simulated sessions of other hands and objects (docs/stereo.md).
IN_FRONT = 0.25   # towards the camera: a cell the touch map holds just inside the surface
BEHIND = 1.0      # away from the camera: a cell the touch map holds just off the surface
BESIDE = 0.25     # across the line of sight
SAMPLES = 7       # per side of the footprint: 49 pixels read per cell
MIN_SAMPLES = 2   # of them in the window: a stray depth alone paints nothing
FILL = 2.0        # px: a pixel without depth this close to one with depth takes its depth


class Window(NamedTuple):
    """Where a measured point counts as a cell's surface (module doc), in cells beyond the
    cell's faces: towards the camera, away from it, across the line of sight."""

    in_front: float = IN_FRONT
    behind: float = BEHIND
    beside: float = BESIDE


WINDOW = Window()


class MapView(NamedTuple):
    """The second rule (module doc, 3): where the map's own cells say a cell is in front,
    and the stereo depth agrees with the cell's depth. In cells, except ``reach`` (px)."""

    min_samples: int = 5      # of the footprint's 49: where it is in front and depth agrees
    tolerance: float = 1.0    # cells: the stereo depth within this of the cell's centre depth
    ahead: float = 0.7        # cells: another occupied cell this much nearer hides the pixel
    reach: float = 4.0        # px: a pixel without depth takes the nearest one's within this
    behind: float = 4.0       # cells: a stereo depth up to this far behind the cell counts
                              # too, unless its point lies in another occupied cell
    blind: bool = True        # a sample with no depth within reach counts, for a cell that
                              # clearly faces the camera (BLIND_RADIUS, BLIND_OUTWARD)


# Where stereo measured nothing, the map's front cell counts only if its outward direction
# (facing_camera, 'local') over this cube is at least BLIND_OUTWARD cells long and points to
# the camera: chosen on the texture sessions' tune set and the bundled bags (docs/stereo.md)
BLIND_RADIUS = 6
BLIND_OUTWARD = 1.0


MAP_VIEW = MapView()


def texture_cells(centres: ArrayLike, resolution: float, image: NDArray[np.uint8],
                  camera: CameraModel, R_left: ArrayLike, camera_pose: Pose, object_pose: Pose,
                  depth: NDArray[np.floating], *, window: Window = WINDOW,
                  samples: int = SAMPLES, min_samples: int = MIN_SAMPLES, fill: float = FILL,
                  orientation: Orientation = 'none', orientation_radius: int = 4,
                  map_view: MapView | None = MAP_VIEW,
                  depth_hole_mask: NDArray[np.bool_] | None = None,
                  rescued: ArrayLike | None = None) -> CellTexture:
    """Colour of each occupied cell where the rectified left camera saw it (module doc).

    ``centres`` (N, 3) occupied cell centres in the map frame; ``resolution`` the cell edge
    (m); ``image`` the rectified left image, (H, W, 3) RGB or (H, W) mono, uint8;
    ``camera`` the rectified left camera (its ``P``, whose third row is ``0 0 1 0`` as in
    every CameraInfo); ``R_left`` raw -> rectified (CameraInfo's R); ``camera_pose``
    ``stereo_left_optical`` in the tracker frame and ``object_pose`` the map frame in the
    tracker frame, each ``(position, quaternion xyzw)``; ``depth`` (H, W) metres along the
    rectified optical axis, NaN or inf where stereo measured nothing. Options (module doc):
    ``window``, ``samples`` per side of the footprint, ``min_samples`` in the window,
    ``fill`` (px), ``orientation`` and ``map_view`` (None: the window rule alone);
    ``depth_hole_mask``: :func:`depth_holes` of ``depth`` when the caller keeps it;
    ``rescued`` (N,) bool: the cells the touch map's cell judge made occupied against its
    surface layer (mostly a second cell across the surface): they are textured where the
    camera saw them, but neither hide another cell in the map's depth image nor take the
    stereo points that fall in them from it. Returns colours (N, 3) uint8 (0 where not
    textured) and the textured mask (N,).
    """
    points = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    _check(image, depth, camera)
    _check_options(resolution, samples, min_samples, fill, window, map_view)
    if depth_hole_mask is not None and depth_hole_mask.shape != depth.shape:
        raise ValueError(f'depth_hole_mask is {depth_hole_mask.shape}, the depth '
                         f'{depth.shape}: they must be the same image')
    solid = _solid(rescued, len(points))
    colours = np.zeros((len(points), 3), dtype=np.uint8)
    textured = np.zeros(len(points), dtype=bool)
    matrix, offset = map_to_rectified(camera_pose, object_pose, R_left)
    P = np.asarray(camera.P, dtype=np.float64)
    rectified = points @ matrix.T + offset
    projection = _project_rectified(rectified, P)
    cells = _candidates(points, projection, resolution, matrix, offset, depth.shape,
                        orientation, orientation_radius)
    if len(cells) == 0:
        return CellTexture(colours, textured)
    u, v, z = projection.u[cells], projection.v[cells], projection.z[cells]
    stereo_depth = np.ascontiguousarray(depth, dtype=np.float32)
    behind = map_view.behind if map_view is not None else 0.0
    # the kernels look this many cells around a cell for the one a measured point lies in
    pad = max(3, math.ceil(max(behind, window.behind) + 1.5))
    ijk, occupied = _lattice(points, resolution, pad=pad)
    occupied[tuple(ijk[~solid].T)] = False    # a point in a rescued cell is its own cell's
    strides = (np.array(occupied.strides) // occupied.itemsize).astype(np.int64)
    inverse = np.linalg.inv(P[:, :3]).astype(np.float64)
    half = resolution / 2.0
    pixels = np.empty((len(cells), samples * samples), dtype=np.int64)
    homes = np.ravel_multi_index(tuple(ijk[cells].T), occupied.shape).astype(np.int64)
    lattice = occupied.reshape(-1)
    to_map = np.ascontiguousarray(matrix, dtype=np.float64)
    shift = np.asarray(inverse @ P[:, 3], dtype=np.float64)
    counts = window_pixels(
        u, v, z, np.ascontiguousarray(rectified[cells]), homes, lattice, strides, to_map,
        stereo_depth, P, inverse, shift, float(resolution), pad, int(samples),
        -half - window.in_front * resolution, half + window.behind * resolution,
        (0.5 + window.beside) * resolution, float(fill), pixels)
    seen = counts >= min_samples
    rest = np.flatnonzero(~seen)
    if map_view is not None and len(rest):
        # the cells the window did not texture, by the second rule; their pixels in place
        front = np.empty(depth.shape, dtype=np.float64)
        map_depth(projection.u[solid], projection.v[solid], projection.z[solid], P,
                  float(resolution), front)
        found = np.empty((len(rest), samples * samples), dtype=np.int64)
        blind = np.zeros(len(rest), dtype=bool)
        holes = np.zeros(depth.shape, dtype=bool)
        if map_view.blind:
            holes = depth_holes(stereo_depth) if depth_hole_mask is None else depth_hole_mask
            near = _footprint_meets(holes, u[rest], v[rest], z[rest], P, resolution) \
                if holes.any() else np.zeros(len(rest), dtype=bool)
            if near.any():
                blind[near] = _facing_clearly(points, cells[rest[near]], resolution,
                                              -matrix.T @ offset)
        counts[rest] = front_pixels(
            u[rest], v[rest], z[rest], np.ascontiguousarray(rectified[cells[rest]]),
            homes[rest], lattice, strides, to_map, front, stereo_depth, P, inverse, shift,
            float(resolution), pad, int(samples), map_view.ahead * resolution,
            map_view.tolerance * resolution, behind * resolution,
            float(map_view.reach), blind, holes, found)
        pixels[rest] = found
        seen[rest] = counts[rest] >= map_view.min_samples
    textured[cells[seen]] = True
    used = np.arange(samples * samples) < counts[seen, None]
    owners = np.repeat(np.arange(int(np.count_nonzero(seen))), counts[seen])
    colours[textured] = _median_colours(image, pixels[seen][used], owners)
    return CellTexture(colours, textured)


def depth_holes(depth: NDArray[np.floating]) -> NDArray[np.bool_]:
    """The pixels without depth (NaN, inf, <= 0) that measured depth encloses: a surface
    stereo found nothing on (weak texture, dark glass), not the open background around
    the object, which reaches the image's border. (What ``ndimage.binary_fill_holes``
    gives, from one labelling of the missing pixels: half its time.)"""
    missing = ~(np.isfinite(depth) & (depth > 0.0))
    labels, count = ndimage.label(missing)
    reaches_border = np.zeros(count + 1, dtype=bool)
    reaches_border[0] = True                       # label 0: the measured pixels
    reaches_border[labels[0]] = reaches_border[labels[-1]] = True
    reaches_border[labels[:, 0]] = reaches_border[labels[:, -1]] = True
    holes: NDArray[np.bool_] = ~reaches_border[labels]
    return holes


def _footprint_meets(mask: NDArray[np.bool_], u: Floats, v: Floats, z: Floats, P: Floats,
                     resolution: float) -> Bools:
    """Whether each cell's footprint (its face seen at its depth, as the kernels sample
    it) holds a pixel of ``mask``: one lookup per cell in the mask's summed-area table."""
    height, width = mask.shape
    table = np.zeros((height + 1, width + 1), dtype=np.int64)
    np.cumsum(np.cumsum(mask, axis=0), axis=1, out=table[1:, 1:])
    half_u, half_v = P[0, 0] / z * resolution / 2.0, P[1, 1] / z * resolution / 2.0
    c0 = np.clip(np.floor(u - half_u + 0.5), 0, width).astype(np.intp)
    c1 = np.clip(np.floor(u + half_u + 0.5) + 1, 0, width).astype(np.intp)
    r0 = np.clip(np.floor(v - half_v + 0.5), 0, height).astype(np.intp)
    r1 = np.clip(np.floor(v + half_v + 0.5) + 1, 0, height).astype(np.intp)
    inside = table[r1, c1] - table[r0, c1] - table[r1, c0] + table[r0, c0]
    meets: Bools = inside > 0
    return meets


def _facing_clearly(points: Points, which: NDArray[np.intp], resolution: float,
                    camera_position: Vector3) -> Bools:
    """Whether the cells ``which`` of ``points`` clearly face the camera (outward over
    ``BLIND_RADIUS`` at least ``BLIND_OUTWARD`` cells long, towards it), from the occupied
    cells around them only: a few hundred cells over a hole, not the whole map's tables."""
    reach = (BLIND_RADIUS + 0.5) * resolution
    low, high = points[which].min(axis=0) - reach, points[which].max(axis=0) + reach
    around = np.flatnonzero(np.all((points >= low) & (points <= high), axis=1))
    facing = facing_camera(points[around], resolution, camera_position, 'local',
                           BLIND_RADIUS, BLIND_OUTWARD, flat=False)
    position = np.searchsorted(around, which)        # ``which`` lies inside ``around``
    clearly: Bools = facing[position]
    return clearly


def _candidates(points: Points, projection: Projection, resolution: float, matrix: Matrix3,
                offset: Vector3, shape: tuple[int, ...], orientation: Orientation,
                orientation_radius: int) -> NDArray[np.intp]:
    """The indices of the cells in front of the camera whose centre's pixel is in the
    image (and that face it, by ``orientation``)."""
    height, width = shape
    column, row = np.floor(projection.u + 0.5), np.floor(projection.v + 0.5)
    candidate = (projection.z > MIN_DEPTH) & (column >= 0) & (column < width) & (row >= 0) & \
        (row < height)
    if orientation != 'none' and len(points):
        camera_in_map = -matrix.T @ offset
        candidate &= facing_camera(points, resolution, camera_in_map, orientation,
                                   orientation_radius)
    cells: NDArray[np.intp] = np.flatnonzero(candidate)
    return cells


def warm_up() -> None:
    """Run the compiled loop once on a scratch scene (two cells in front of a 4 x 4
    camera): numba loads it from its cache (or compiles it) on its first call, which a node
    pays at start rather than on its first map."""
    P = np.array([[4.0, 0.0, 2.0, 0.0], [0.0, 4.0, 2.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    camera = CameraModel(4, 4, P[:, :3], np.zeros(5), np.eye(3), P)
    identity = (np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))
    texture_cells([[0.0, 0.0, 0.5], [0.005, 0.0, 0.5]], 0.005, np.zeros((4, 4, 3), np.uint8),
                  camera, np.eye(3), identity, identity, np.full((4, 4), 0.5, np.float32))


def _check_options(resolution: float, samples: int, min_samples: int, fill: float,
                   window: Window, map_view: MapView | None) -> None:
    """ValueError for options :func:`texture_cells` cannot work with."""
    if not resolution > 0.0 or samples < 1 or not 1 <= min_samples <= samples * samples or \
            fill < 0.0 or not all(0.0 <= extent <= 2.0 for extent in window):
        raise ValueError('resolution must be > 0, samples >= 1, min_samples in [1, '
                         'samples^2], fill >= 0, the window 0-2 cells each way')
    if map_view is not None and not (1 <= map_view.min_samples <= samples * samples
                                     and map_view.tolerance >= 0.0 and map_view.ahead >= 0.0
                                     and map_view.reach >= 0.0
                                     and map_view.tolerance <= map_view.behind <= 10.0):
        raise ValueError(f'map_view: min_samples in [1, samples^2], tolerance, ahead and '
                         f'reach >= 0, behind in [tolerance, 10], got {map_view}')


def _solid(rescued: ArrayLike | None, count: int) -> Bools:
    """The cells that hide others and claim stereo points: all but the ``rescued`` ones."""
    if rescued is None:
        return np.ones(count, dtype=bool)
    solid: Bools = ~np.asarray(rescued, dtype=bool).reshape(-1)
    if len(solid) != count:
        raise ValueError(f'rescued has {len(solid)} values for {count} cells')
    return solid


def _check(image: NDArray[np.uint8], depth: NDArray[np.floating], camera: CameraModel) -> None:
    if depth.ndim != 2 or image.shape[:2] != depth.shape:
        raise ValueError(f'image {image.shape} and depth {depth.shape} must be the same '
                         '(H, W) rectified left image')
    if (depth.shape[1], depth.shape[0]) != camera.size:
        raise ValueError(f'image is {depth.shape[1]}x{depth.shape[0]} but the camera model '
                         f'is {camera.width}x{camera.height}')
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or \
            (image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(f'image must be uint8 (H, W, 3) RGB or (H, W) mono, got '
                         f'{image.dtype} {image.shape}')
    if not np.array_equal(camera.P[2], [0.0, 0.0, 1.0, 0.0]):
        raise ValueError(f'the camera\'s P must end in the row 0 0 1 0 (depth along z), got '
                         f'{camera.P[2].tolist()}')


def _median_colours(image: NDArray[np.uint8], pixels: NDArray[np.intp],
                    owners: NDArray[np.intp]) -> Colours:
    """Per-channel median of each owner's pixels (of an even count, the upper of the two
    middle values), the owners in increasing order: one sort per channel, by owner then
    value, for all cells at once."""
    channels = image.reshape(-1, 1 if image.ndim == 2 else 3)[pixels]
    if len(owners) == 0:
        return np.zeros((0, 3), dtype=np.uint8)
    ordered = np.sort(owners)
    first = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
    counts = np.diff(np.r_[first, len(ordered)])
    middle = first + counts // 2
    median = np.empty((len(first), channels.shape[1]), dtype=np.uint8)
    for channel in range(channels.shape[1]):
        by_value = np.lexsort((channels[:, channel], owners))
        median[:, channel] = channels[by_value, channel][middle]
    result: Colours = np.ascontiguousarray(np.broadcast_to(median, (len(first), 3))) \
        if median.shape[1] == 1 else median
    return result
