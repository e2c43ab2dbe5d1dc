"""Where the stereo camera sits in the tracker frame: a least-squares rigid fit of point pairs.

A point touched with a tracked fingertip has a position ``q`` in ``polhemus_source`` and,
seen by the stereo camera, a position ``p`` in ``stereo_left_optical``. The camera pose is
the rotation ``R`` and translation ``t`` with ``q = R p + t`` for every pair, found by
least squares (Kabsch / Umeyama without scale: both sides are in metres, so a scale would
only absorb errors and hide a unit mix-up). The rotation is proper (det +1): a reflection
would fit mirrored points better and be no camera pose at all.

The fit needs three points that are not on one line (a line leaves the rotation about it
free), and it refuses point sets whose spread differs so much between the two sides that
they cannot be the same points in metres (centimetres or millimetres typed for metres).
Also here, for ``calibrate_camera_tracker``: the correspondence file a researcher fills in
(CSV or YAML, one row per touched point, the camera side as a point or as rectified pixels),
the triangulation of those pixels with the stereo calibration, and the stereo node's
parameter file with ``camera_pose``. No rclpy.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike

from inhand_common.array_types import Floats, Matrix3, Points, Vector3
from inhand_common.atomic_file import atomic_write
from inhand_common.rotations import matrix_to_quaternion
from inhand_common.yaml_errors import describe_yaml_error
from inhand_stereo.camera_info_yaml import format_float
from inhand_stereo.camera_model import CameraModel

__all__ = ['CAMERA_COLUMNS', 'MIN_POINTS', 'PIXEL_COLUMNS', 'STEREO_NODE_KEY', 'TRACKER_COLUMNS',
           'Correspondence', 'CorrespondenceError', 'RigidFit', 'RigidFitError',
           'camera_points', 'camera_pose_yaml_text', 'fit_rigid', 'read_correspondences',
           'triangulate_rectified', 'write_camera_pose_yaml']

MIN_POINTS = 3
# Across-the-line spread below this fraction of the along-the-line spread: the rotation
# about the line is not determined by the points (their noise would set it).
COLLINEAR_RATIO = 0.02
# Spread (RMS distance to the centroid) below which the points are one spot: 1 mm.
MIN_SPREAD = 1e-3
# The two sides' spreads may differ by noise, never by a factor of this.
MAX_SPREAD_RATIO = 1.25


class RigidFitError(ValueError):
    """Correspondences that do not determine a pose, with what was given."""


@dataclass(frozen=True)
class RigidFit:
    """``tracker = rotation @ camera + translation``, and how well the points agree."""

    rotation: Matrix3          # (3, 3), det +1
    translation: Vector3       # (3,) m
    residuals: Points          # (N, 3) fitted minus measured tracker positions (m)

    @property
    def distances(self) -> Floats:
        """(N,) residual length per point (m)."""
        return np.asarray(np.linalg.norm(self.residuals, axis=1), dtype=np.float64)

    @property
    def rms(self) -> float:
        """Root mean square residual (m)."""
        return float(np.sqrt(np.mean(self.distances ** 2)))

    @property
    def max(self) -> float:
        """Largest residual (m)."""
        return float(self.distances.max())

    @property
    def quaternion(self) -> Floats:
        """(4,) the rotation as x, y, z, w with w >= 0."""
        return np.asarray(matrix_to_quaternion(self.rotation), dtype=np.float64)

    @property
    def pose(self) -> list[float]:
        """``[x, y, z, qx, qy, qz, qw]``: the stereo node's ``camera_pose`` parameter."""
        return [float(v) for v in (*self.translation, *self.quaternion)]

    def apply(self, camera_points: ArrayLike) -> Points:
        """Camera-frame points (N, 3) in the tracker frame."""
        p = np.asarray(camera_points, dtype=np.float64).reshape(-1, 3)
        return np.asarray(p @ self.rotation.T + self.translation, dtype=np.float64)


def _spread(points: Points) -> tuple[Floats, Floats]:
    """Principal RMS spreads (3,) descending, and the centroid (3,)."""
    centroid = points.mean(axis=0)
    singular = np.linalg.svd(points - centroid, compute_uv=False)
    return np.asarray(singular / np.sqrt(len(points)), dtype=np.float64), centroid


def _check_geometry(points: Points, side: str) -> float:
    """RMS distance to the centroid of one side's points; RigidFitError when they are one
    spot or (nearly) on one line."""
    spreads, _ = _spread(points)
    total = float(np.sqrt(np.sum(spreads ** 2)))
    if total < MIN_SPREAD:
        raise RigidFitError(f'the {len(points)} {side} points lie within {total * 1e3:.2f} mm '
                            'of each other: touch points spread over the workspace')
    if spreads[1] < COLLINEAR_RATIO * spreads[0]:
        raise RigidFitError(
            f'the {len(points)} {side} points are (nearly) on one line: they spread '
            f'{spreads[0] * 1e3:.1f} mm along it and {spreads[1] * 1e3:.2f} mm across it, which '
            'leaves the rotation about that line undetermined; add a point off the line')
    return total


def fit_rigid(camera_points: ArrayLike, tracker_points: ArrayLike) -> RigidFit:
    """Least-squares ``R``, ``t`` with ``tracker ~ R @ camera + t`` over N >= 3 pairs.

    Kabsch: the rotation from the SVD of the cross-covariance of the centred points, with
    the sign of the last singular direction fixed so that ``det R = +1``.
    """
    p = np.asarray(camera_points, dtype=np.float64)
    q = np.asarray(tracker_points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1:] != (3,) or q.shape != p.shape:
        raise RigidFitError(f'need N x 3 camera and tracker points of the same N, got shapes '
                            f'{p.shape} and {q.shape}')
    if len(p) < MIN_POINTS:
        raise RigidFitError(f'{len(p)} point pair{"s" if len(p) != 1 else ""} given: a pose '
                            f'needs at least {MIN_POINTS} points that are not on one line')
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise RigidFitError('a point holds a non-finite coordinate')
    spread_camera = _check_geometry(p, 'camera')
    spread_tracker = _check_geometry(q, 'tracker')
    ratio = spread_tracker / spread_camera
    if not 1 / MAX_SPREAD_RATIO <= ratio <= MAX_SPREAD_RATIO:
        raise RigidFitError(
            f'the tracker points spread {spread_tracker * 1e3:.1f} mm around their centre and '
            f'the camera points {spread_camera * 1e3:.1f} mm ({ratio:.2f}x): the same points '
            'in metres on both sides cannot differ so much (a unit mix-up, or rows out of step?)')
    p_mean, q_mean = p.mean(axis=0), q.mean(axis=0)
    covariance = (q - q_mean).T @ (p - p_mean)
    u, _, vt = np.linalg.svd(covariance)
    fix = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(u @ vt)) or 1.0)])
    rotation = u @ fix @ vt
    translation = q_mean - rotation @ p_mean
    residuals = p @ rotation.T + translation - q
    return RigidFit(np.asarray(rotation, dtype=np.float64),
                    np.asarray(translation, dtype=np.float64),
                    np.asarray(residuals, dtype=np.float64))


# ---------------------------------------------------------------------------------------------
# The correspondences a researcher writes down, and the stereo node's parameter file.

TRACKER_COLUMNS = ('x', 'y', 'z')
CAMERA_COLUMNS = ('x_cam', 'y_cam', 'z_cam')
PIXEL_COLUMNS = ('u_left', 'v_left', 'u_right')
# The node whose parameter file calibrate_camera_tracker writes, in any namespace.
STEREO_NODE_KEY = '/**/stereo_node'


@dataclass(frozen=True)
class Correspondence:
    """One touched point: its tracker position and either its camera-frame position or its
    pixels in the rectified left and right images."""

    name: str
    tracker: Vector3                    # (3,) m, polhemus_source
    camera: Vector3 | None = None       # (3,) m, stereo_left_optical (the left camera)
    pixels: Vector3 | None = None       # (3,) u_left, v_left, u_right (px, rectified images)


class CorrespondenceError(ValueError):
    """A correspondence file that cannot be used; the message names the file, the row and
    the problem."""


_FORMAT_HINT = ('needs columns x, y, z (tracker, m) and either x_cam, y_cam, z_cam (camera, m) '
                'or u_left, v_left, u_right (rectified pixels)')


def read_correspondences(path: str | os.PathLike[str]) -> list[Correspondence]:
    """The rows of a correspondence file: CSV (``.csv``, a header line, ``#`` comments) or
    YAML (``.yaml``/``.yml``, a list under ``points:`` of mappings with the same keys)."""
    path = Path(path)
    if not path.exists():
        raise CorrespondenceError(f'{path}: no such file')
    suffix = path.suffix.lower()
    try:
        text = path.read_text(encoding='utf-8')
    except (OSError, UnicodeDecodeError) as error:
        raise CorrespondenceError(f'{path}: cannot read it ({error})') from None
    try:
        if suffix in ('.yaml', '.yml'):
            rows = _yaml_rows(text)
        elif suffix in ('.csv', '.txt'):
            rows = _csv_rows(text)
        else:
            raise CorrespondenceError(f'the name must end in .csv or .yaml (got '
                                      f"'{suffix or 'no suffix'}')")
        return [_correspondence(label, row) for label, row in rows]
    except CorrespondenceError as error:
        raise CorrespondenceError(f'{path}: {error}') from None


def _csv_rows(text: str) -> list[tuple[str, dict[str, Any]]]:
    lines = [(number, line) for number, line in enumerate(text.splitlines(), start=1)
             if line.strip() and not line.lstrip().startswith('#')]
    if not lines:
        raise CorrespondenceError(f'no header line and no rows; {_FORMAT_HINT}')
    header_number, header_line = lines[0]
    header = [name.strip().lower() for name in next(csv.reader([header_line]))]
    if any(_is_number(name) for name in header):
        raise CorrespondenceError(f'line {header_number} must be the header naming the columns '
                                  f'(it starts with numbers); {_FORMAT_HINT}')
    missing = [c for c in TRACKER_COLUMNS if c not in header]
    groups = [g for g in (CAMERA_COLUMNS, PIXEL_COLUMNS) if any(c in header for c in g)]
    if not groups:
        missing += ['x_cam, y_cam, z_cam or u_left, v_left, u_right']
    for group in groups:
        missing += [c for c in group if c not in header]
    if missing:
        raise CorrespondenceError(f'missing column{"s" if len(missing) > 1 else ""} '
                                  f'{", ".join(missing)} (the header has {", ".join(header)}); '
                                  f'{_FORMAT_HINT}')
    rows = []
    for number, line in lines[1:]:
        cells = [cell.strip() for cell in next(csv.reader([line]))]
        if len(cells) > len(header) and any(cells[len(header):]):
            raise CorrespondenceError(f'line {number} has {len(cells)} cells, the header '
                                      f'{len(header)}')
        rows.append((f'line {number}', dict(zip(header, cells))))
    if not rows:
        raise CorrespondenceError('a header but no rows')
    return rows


def _yaml_rows(text: str) -> list[tuple[str, dict[str, Any]]]:
    try:
        document = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise CorrespondenceError(describe_yaml_error(error)) from None
    entries = document.get('points') if isinstance(document, dict) else document
    if not isinstance(entries, list) or not entries:
        raise CorrespondenceError(f'expected a non-empty list under points:, each entry a '
                                  f'mapping; {_FORMAT_HINT}')
    rows = []
    for index, entry in enumerate(entries, start=1):
        if not isinstance(entry, dict):
            raise CorrespondenceError(f'point {index} is {entry!r}, not a mapping of x, y, z, ...')
        rows.append((f'point {index}', {str(k).strip().lower(): v for k, v in entry.items()}))
    return rows


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _blank(value: Any) -> bool:
    return value is None or (isinstance(value, str) and not value.strip())


def _group(label: str, row: dict[str, Any], columns: tuple[str, ...]) -> Vector3 | None:
    """The three numbers of a column group, None when all are blank."""
    filled = [c for c in columns if not _blank(row.get(c))]
    if not filled:
        return None
    if len(filled) < len(columns):
        empty = [c for c in columns if c not in filled]
        raise CorrespondenceError(f'{label}: {", ".join(filled)} given but {", ".join(empty)} '
                                  'empty')
    values = []
    for column in columns:
        value = row[column]
        if isinstance(value, bool):
            value = repr(value)
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise CorrespondenceError(f'{label}: {column} is {value!r}, not a number') from None
        if not np.isfinite(number):
            raise CorrespondenceError(f'{label}: {column} is {value!r}, not a finite number')
        values.append(number)
    return np.array(values, dtype=np.float64)


def _correspondence(label: str, row: dict[str, Any]) -> Correspondence:
    tracker = _group(label, row, TRACKER_COLUMNS)
    if tracker is None:
        raise CorrespondenceError(f'{label}: the tracker position x, y, z is missing')
    camera = _group(label, row, CAMERA_COLUMNS)
    pixels = _group(label, row, PIXEL_COLUMNS)
    if camera is not None and pixels is not None:
        raise CorrespondenceError(f'{label}: give either x_cam, y_cam, z_cam or u_left, '
                                  'v_left, u_right, not both')
    if camera is None and pixels is None:
        raise CorrespondenceError(f'{label}: neither x_cam, y_cam, z_cam nor u_left, v_left, '
                                  'u_right is given')
    name = row.get('name')
    return Correspondence(label if _blank(name) else str(name).strip(), tracker, camera, pixels)


def triangulate_rectified(left: CameraModel, right: CameraModel, pixels: ArrayLike,
                          names: Sequence[str] | None = None) -> Points:
    """Points (N, 3) in ``stereo_left_optical`` (the left camera) from their pixels
    ``(u_left, v_left, u_right)`` (N, 3) in the rectified images of a horizontal pair.

    With CameraInfo's rectified projections ``P_left = [f 0 cx_l 0; 0 f cy 0; 0 0 1 0]`` and
    ``P_right[0, 3] = -f * B``: ``Z = f B / ((u_l - cx_l) - (u_r - cx_r))``, ``X = (u_l -
    cx_l) Z / fx``, ``Y = (v_l - cy) Z / fy`` in the rectified left camera, then turned back
    into the left camera itself with the left ``R`` (``p = R^T p_rect``), as the stereo node
    does with its points before ``camera_pose`` applies: fitting the rectified frame instead
    would tilt the pose by the rectification rotation (a few degrees). ``names`` label the
    points in the refusal of a point at or beyond infinity.
    """
    _check_rectified_pair(left, right)
    uvu = np.asarray(pixels, dtype=np.float64).reshape(-1, 3)
    fx, fy = left.P[0, 0], left.P[1, 1]
    cx_l, cy, cx_r = left.P[0, 2], left.P[1, 2], right.P[0, 2]
    baseline = -right.P[0, 3] / right.P[0, 0]
    disparity = (uvu[:, 0] - cx_l) - (uvu[:, 2] - cx_r)
    bad = np.flatnonzero(~(disparity > 0))
    if len(bad):
        i = int(bad[0])
        name = names[i] if names is not None else f'point {i + 1}'
        raise CorrespondenceError(
            f'{name}: u_left - u_right = {uvu[i, 0] - uvu[i, 2]:g} px (disparity '
            f'{disparity[i]:g} px after the principal points) puts it at or beyond infinity: '
            'left and right swapped, or not rectified pixels?')
    z = fx * baseline / disparity
    rectified = np.stack([(uvu[:, 0] - cx_l) * z / fx, (uvu[:, 1] - cy) * z / fy, z], axis=1)
    return np.asarray(rectified @ left.R, dtype=np.float64)  # rows: (R^T p)^T = p^T R


def _check_rectified_pair(left: CameraModel, right: CameraModel) -> None:
    problems = []
    if abs(left.P[0, 3]) > 1e-9 or abs(left.P[1, 3]) > 1e-9:
        problems.append(f'the left P has a translation ({left.P[0, 3]:g}, {left.P[1, 3]:g}); '
                        'is it the right camera?')
    if not right.P[0, 3] < 0:
        problems.append(f'the right P[0, 3] = {right.P[0, 3]:g} should be -fx * baseline < 0 '
                        '(the right camera of a horizontal pair)')
    if abs(right.P[1, 3]) > 1e-9:
        problems.append(f'the right P[1, 3] = {right.P[1, 3]:g}: a vertical pair')
    for label, (a, b) in {'fx': (left.P[0, 0], right.P[0, 0]), 'fy': (left.P[1, 1], right.P[1, 1]),
                          'cy': (left.P[1, 2], right.P[1, 2])}.items():
        if abs(a - b) > 1e-6 * max(abs(a), 1.0):
            problems.append(f'{label} differs ({a:g} left, {b:g} right)')
    if problems:
        raise CorrespondenceError('--left/--right are not the rectified pair of one stereo '
                                  'calibration: ' + '; '.join(problems))


def camera_points(correspondences: Sequence[Correspondence], left: CameraModel | None = None,
                  right: CameraModel | None = None) -> Points:
    """(N, 3) camera-frame points of the correspondences, triangulating those given as
    pixels with the ``left``/``right`` camera_info."""
    points = np.zeros((len(correspondences), 3))
    pixel_rows = [i for i, c in enumerate(correspondences) if c.pixels is not None]
    if pixel_rows and (left is None or right is None):
        names = ', '.join(correspondences[i].name for i in pixel_rows[:3])
        raise CorrespondenceError(f'{len(pixel_rows)} point(s) ({names}'
                                  f'{", ..." if len(pixel_rows) > 3 else ""}) are given as pixels: '
                                  'pass --left and --right camera_info YAML to triangulate them')
    for i, c in enumerate(correspondences):
        if c.camera is not None:
            points[i] = c.camera
    if pixel_rows:
        assert left is not None and right is not None
        pixels = np.array([correspondences[i].pixels for i in pixel_rows], dtype=np.float64)
        points[pixel_rows] = triangulate_rectified(
            left, right, pixels, [correspondences[i].name for i in pixel_rows])
    return points


def camera_pose_yaml_text(fit: RigidFit, comments: Sequence[str] = ()) -> str:
    """The stereo node's parameter file: ``camera_pose`` under ``/**/stereo_node`` (the
    wildcard applies it in any namespace), floats written with a decimal point so ROS reads
    a double array."""
    header = [f'# {line}' for line in comments]
    header += ['# camera_pose = [x, y, z, qx, qy, qz, qw]: the pose of stereo_left_optical in '
               'polhemus_source',
               '# (a point p in the camera frame is R p + t in the tracker frame; metres).']
    values = ', '.join(format_float(v) for v in fit.pose)
    body = [f'{STEREO_NODE_KEY}:', '  ros__parameters:', f'    camera_pose: [{values}]']
    return '\n'.join(header + body) + '\n'


def write_camera_pose_yaml(path: str | os.PathLike[str], fit: RigidFit,
                           comments: Sequence[str] = ()) -> Path:
    """Write the parameter file atomically; returns the path."""
    path = Path(path)
    text = camera_pose_yaml_text(fit, comments)
    with atomic_write(path) as stream:
        stream.write(text.encode('utf-8'))
    return path
