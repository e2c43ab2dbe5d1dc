"""Stereo calibration from chessboard image pairs: two CameraInfos as ROS's camera_calibration
would write them.

Steps, as camera_calibration's stereo calibrator takes them:

1. Corners: ``cv2.findChessboardCorners`` (adaptive threshold, normalised image, fast check
   so that frames without a board cost little) refined by ``cv2.cornerSubPix`` with a window
   of half the corner spacing (a wider one drifts to the neighbouring corner). A board
   closer than 8 px to the image edge is dropped: its outer corners may be cut. A pair is
   used for the stereo step only when both images show the whole board; its right corners
   are put in the order of the left ones (the detector may start at either end of the
   board, and a pair ordered differently would pull the extrinsics 180 degrees apart). A
   view that barely moved from one already kept adds no information and is skipped, so a
   bag held still for seconds does not swamp the calibration.
2. Intrinsics: ``cv2.calibrateCamera`` for each camera on every image of it that shows the
   board (also when the other camera missed it): plumb_bob with k1, k2, p1, p2, and k3
   fixed at 0 unless three radial coefficients are asked for (camera_calibration's default
   too: k3 is poorly determined by a narrow lens and a few views, and absorbs noise).
3. Extrinsics: ``cv2.stereoCalibrate`` on the pairs with the intrinsics fixed
   (``CALIB_FIX_INTRINSIC``, camera_calibration's choice: each camera's lens is determined
   by its own views, the pairs only place one camera relative to the other). ``joint``
   refines both cameras' intrinsics together with the extrinsics from the pairs
   (``CALIB_USE_INTRINSIC_GUESS``): a lower stereo RMS, at the price of letting lens and
   pose errors trade against each other.
4. Rectification: ``cv2.stereoRectify`` with ``alpha = 0`` (only valid pixels in the
   rectified images) and zero disparity at infinity -> R1, R2, P1, P2; OpenCV's
   ``P2[0, 3] = fx' * Tx`` with ``Tx = -baseline`` is exactly CameraInfo's ``-fx' * B``.

The epipolar error reported is the mean ``|y_left - y_right|`` of corresponding corners
after rectification (the stereo matcher searches along rows, so this is what it sees).
No rclpy here: bag images are decoded with rosbags' typestore.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeAlias

import cv2
import numpy as np
from numpy.typing import NDArray

from inhand_common.array_types import Matrix3, Vector3
from inhand_stereo.camera_model import CameraModel

__all__ = ['BORDER', 'LEFT_IMAGE_TOPIC', 'MIN_PAIRS', 'RIGHT_IMAGE_TOPIC', 'CalibrationError',
           'Chessboard', 'Detections', 'ImageBag', 'ImagePair', 'StereoCalibration', 'bag_pairs',
           'calibrate_stereo', 'detect_chessboards', 'find_chessboard', 'folder_pairs',
           'image_from_message']

Corners: TypeAlias = NDArray[np.float32]   # (N, 1, 2) pixel positions, OpenCV's layout
Gray: TypeAlias = NDArray[np.uint8]        # (H, W) 8-bit grey image

LEFT_IMAGE_TOPIC = 'stereo/left/image_raw'
RIGHT_IMAGE_TOPIC = 'stereo/right/image_raw'
IMAGE_TYPE = 'sensor_msgs/msg/Image'
IMAGE_SUFFIXES = ('.png', '.jpg', '.jpeg', '.bmp', '.tif', '.tiff', '.pgm', '.ppm')
# Fewest pairs for a calibration worth writing: each view fixes 6 pose unknowns, the two
# cameras have 2 x 8 intrinsics and 6 extrinsics, and a handful of views is needed to see
# the distortion; camera_calibration asks for more (its progress bars), not fewer.
MIN_PAIRS = 6
# A board closer than this to the image edge may be cut (camera_calibration's BORDER).
BORDER = 8
# A view whose corners moved less than this fraction of the image diagonal (mean over the
# corners) from a view already kept is the same view again.
MIN_MOTION = 0.01
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 0.001)
_CALIB_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 200, 1e-9)


class CalibrationError(ValueError):
    """Input that gives no calibration, with what was found and what is needed."""


@dataclass(frozen=True)
class Chessboard:
    """The calibration target: ``columns x rows`` inner corners, ``square`` metres apart."""

    columns: int
    rows: int
    square: float

    @classmethod
    def parse(cls, size: str, square: float) -> Chessboard:
        """From camera_calibration's ``--size 8x6`` (inner corners) and ``--square``."""
        match = re.fullmatch(r'\s*(\d+)\s*[xX]\s*(\d+)\s*', size)
        if not match:
            raise CalibrationError(f"--size '{size}' must be COLUMNSxROWS inner corners, "
                                   'e.g. 8x6')
        columns, rows = int(match.group(1)), int(match.group(2))
        if columns < 2 or rows < 2:
            raise CalibrationError(f"--size '{size}': a chessboard has at least 2x2 inner "
                                   'corners (count the corners where four squares meet)')
        if not (math.isfinite(square) and square > 0):
            raise CalibrationError(f'--square {square:g} must be a positive length in metres')
        return cls(columns, rows, float(square))

    @property
    def count(self) -> int:
        return self.columns * self.rows

    @property
    def label(self) -> str:
        return f'{self.columns}x{self.rows}'

    def object_points(self) -> NDArray[np.float32]:
        """(N, 3) corner positions on the board (m, z = 0), in the detector's order: row by
        row, ``columns`` corners per row."""
        grid = np.mgrid[0:self.columns, 0:self.rows].T.reshape(-1, 2)
        points = np.zeros((self.count, 3), np.float32)
        points[:, :2] = grid * self.square
        return points


@dataclass(frozen=True)
class ImagePair:
    """A left and a right image taken together (grey), or why they cannot be used."""

    name: str
    left: Gray | None = None
    right: Gray | None = None
    problem: str = ''


@dataclass
class Detections:
    """What the images showed: the boards seen by both cameras, by one of them, and the
    pairs not used with the reason."""

    board: Chessboard
    image_size: tuple[int, int] | None = None               # (width, height)
    pairs: list[tuple[str, Corners, Corners]] = field(default_factory=list)
    left_only: list[tuple[str, Corners]] = field(default_factory=list)
    right_only: list[tuple[str, Corners]] = field(default_factory=list)
    rejected: list[tuple[str, str]] = field(default_factory=list)  # (name, reason)
    seen: int = 0                                             # pairs looked at

    def left_views(self) -> list[Corners]:
        return [left for _, left, _ in self.pairs] + [c for _, c in self.left_only]

    def right_views(self) -> list[Corners]:
        return [right for _, _, right in self.pairs] + [c for _, c in self.right_only]

    def rejection_summary(self, names: int = 4) -> list[str]:
        """One line per reason: how many pairs, and the first few names."""
        by_reason: dict[str, list[str]] = {}
        for name, reason in self.rejected:
            by_reason.setdefault(reason, []).append(name)
        lines = []
        for reason, which in sorted(by_reason.items(), key=lambda item: -len(item[1])):
            shown = ', '.join(which[:names]) + (', ...' if len(which) > names else '')
            lines.append(f'{len(which)} {reason} ({shown})')
        return lines


@dataclass(frozen=True)
class StereoCalibration:
    """The two CameraInfos and how well they fit the corners."""

    left: CameraModel
    right: CameraModel
    rotation: Matrix3          # right camera from left: p_right = rotation @ p_left + translation
    translation: Vector3       # (3,) m
    rms: float                 # stereo reprojection RMS over both cameras (px)
    rms_left: float            # each camera's own calibration (px)
    rms_right: float
    epipolar_error: float      # mean |y_left - y_right| after rectification (px)
    epipolar_max: float
    pairs: int                 # pairs in the stereo step
    left_views: int            # images in each camera's intrinsic calibration
    right_views: int
    joint: bool

    @property
    def baseline(self) -> float:
        """Distance between the optical centres (m)."""
        return float(np.linalg.norm(self.translation))

    @property
    def rotation_angle(self) -> float:
        """Angle between the two cameras' orientations (degrees)."""
        cos = (np.trace(self.rotation) - 1.0) / 2.0
        return math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0))))


# ---------------------------------------------------------------------------------------------
# Corners


def find_chessboard(gray: Gray, board: Chessboard) -> Corners | None:
    """The board's inner corners (N, 1, 2) refined to sub-pixel, or None when the whole
    board is not seen (or touches the image border)."""
    flags = (cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
             | cv2.CALIB_CB_FAST_CHECK)
    found, raw = cv2.findChessboardCorners(gray, (board.columns, board.rows), flags=flags)
    if not found or raw is None:
        return None
    corners = np.ascontiguousarray(np.asarray(raw, dtype=np.float32).reshape(-1, 1, 2))
    height, width = gray.shape[:2]
    xy = corners[:, 0, :]
    if (xy.min() < BORDER or xy[:, 0].max() > width - 1 - BORDER
            or xy[:, 1].max() > height - 1 - BORDER):
        return None
    grid = xy.reshape(board.rows, board.columns, 2)
    spacing = min(float(np.linalg.norm(np.diff(grid, axis=1), axis=2).min()),
                  float(np.linalg.norm(np.diff(grid, axis=0), axis=2).min()))
    radius = max(2, math.ceil(spacing * 0.5))
    refined = cv2.cornerSubPix(gray, corners, (radius, radius), (-1, -1), _SUBPIX_CRITERIA)
    return np.asarray(refined, dtype=np.float32).reshape(-1, 1, 2)


def _orderings(corners: Corners, board: Chessboard) -> list[Corners]:
    """The corner orders the detector may give for one board: as found, reversed (the board
    turned 180 degrees), and for a square board the two quarter turns."""
    grid = corners.reshape(board.rows, board.columns, 2)
    options = [grid, grid[::-1, ::-1]]
    if board.rows == board.columns:
        options += [np.rot90(grid, 1), np.rot90(grid, 3)]
    return [np.ascontiguousarray(g.reshape(-1, 1, 2)) for g in options]


def _match_order(left: Corners, right: Corners, board: Chessboard) -> Corners:
    """``right`` in the order of ``left``: in a side-by-side pair corresponding corners have
    about the same row and a common shift along it, a board turned the other way does not."""
    def disagreement(candidate: Corners) -> float:
        delta = candidate[:, 0, :] - left[:, 0, :]
        return float(np.mean(np.abs(delta[:, 1]))
                     + np.mean(np.abs(delta[:, 0] - np.median(delta[:, 0]))))
    return min(_orderings(right, board), key=disagreement)


def _near(corners: Corners, kept: Sequence[Corners], limit: float) -> int | None:
    """Index of a kept view whose corners are within ``limit`` px on average, else None."""
    for index, other in enumerate(kept):
        if float(np.mean(np.linalg.norm(corners - other, axis=2))) < limit:
            return index
    return None


def detect_chessboards(pairs: Iterable[ImagePair], board: Chessboard,
                       min_motion: float = MIN_MOTION,
                       progress: Callable[[int], None] | None = None) -> Detections:
    """Find the board in every pair; keep the corners (not the images, so a long bag fits
    in memory) and the reason for every pair not used."""
    result = Detections(board)
    kept_left: list[tuple[str, Corners]] = []   # every kept view, for the sameness test
    kept_right: list[tuple[str, Corners]] = []
    for pair in pairs:
        result.seen += 1
        if progress is not None:
            progress(result.seen)
        if pair.problem or pair.left is None or pair.right is None:
            result.rejected.append((pair.name, pair.problem or 'missing an image'))
            continue
        sizes = {(img.shape[1], img.shape[0]) for img in (pair.left, pair.right)}
        if len(sizes) > 1:
            result.rejected.append((pair.name, 'left and right images differ in size'))
            continue
        size = sizes.pop()
        if result.image_size is None:
            result.image_size = size
        elif size != result.image_size:
            first = result.image_size
            result.rejected.append((pair.name, f'{size[0]}x{size[1]}, not the '
                                                f'{first[0]}x{first[1]} of the first pair'))
            continue
        left = find_chessboard(pair.left, board)
        right = find_chessboard(pair.right, board)
        if left is not None and right is not None:
            right = _match_order(left, right, board)
        limit = min_motion * math.hypot(*size)
        same_left = _near(left, [c for _, c in kept_left], limit) if left is not None else None
        same_right = (_near(right, [c for _, c in kept_right], limit)
                      if right is not None else None)
        if left is not None and right is not None and (same_left is None or same_right is None):
            result.pairs.append((pair.name, left, right))
            kept_left.append((pair.name, left))
            kept_right.append((pair.name, right))
            continue
        if left is not None and same_left is None:
            result.left_only.append((pair.name, left))
            kept_left.append((pair.name, left))
        if right is not None and same_right is None:
            result.right_only.append((pair.name, right))
            kept_right.append((pair.name, right))
        if left is None and right is None:
            reason = 'no whole chessboard in either image'
        elif left is None:
            reason = 'no whole chessboard in the left image'
        elif right is None:
            reason = 'no whole chessboard in the right image'
        else:
            reason = 'nearly the same view as an earlier pair'
        result.rejected.append((pair.name, reason))
    return result


# ---------------------------------------------------------------------------------------------
# Calibration


def _refusal(detections: Detections, need: str) -> CalibrationError:
    board = detections.board
    lines = [f'{len(detections.pairs)} of {detections.seen} pairs show the whole '
             f'{board.label} chessboard in both images; {need}']
    reasons = detections.rejection_summary()
    if reasons:
        lines.append('Not used: ' + '; '.join(reasons))
    if not detections.pairs and not detections.left_only and not detections.right_only:
        lines.append(f'Is --size {board.label} the count of inner corners (where four squares '
                     'meet), columns x rows?')
    return CalibrationError('. '.join(lines))


def _f64(array: Any) -> NDArray[np.float64]:
    """An OpenCV result as a float64 array (its stubs type results as Mat | ndarray)."""
    return np.asarray(array, dtype=np.float64)


def _calibrate_camera(views: Sequence[Corners], board: Chessboard, size: tuple[int, int],
                      flags: int) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    objects = [board.object_points()] * len(views)
    try:
        rms, k, d, _, _ = cv2.calibrateCamera(objects, list(views), size, None, None,
                                              flags=flags, criteria=_CALIB_CRITERIA)
    except cv2.error as error:
        raise CalibrationError(f'OpenCV could not calibrate a camera from {len(views)} views '
                               f'({_opencv_reason(error)})') from None
    return float(rms), _f64(k), _f64(d).reshape(-1)


def _opencv_reason(error: cv2.error) -> str:
    """The last line of an OpenCV error: its assertion or message, without the source path."""
    lines = [line for line in str(error).splitlines() if line.strip()]
    return lines[-1].split(' error: ', 1)[-1] if lines else type(error).__name__


def calibrate_stereo(detections: Detections, k_coefficients: int = 2, joint: bool = False,
                     names: tuple[str, str] = ('stereo/left', 'stereo/right'),
                     min_pairs: int = MIN_PAIRS) -> StereoCalibration:
    """The left and right CameraModels of the pairs in ``detections`` (see the module's
    steps). CalibrationError when fewer than ``min_pairs`` pairs show the board, or when the
    result is not a side-by-side pair with the right camera on the right."""
    if k_coefficients not in (2, 3):
        raise CalibrationError(f'k_coefficients must be 2 or 3, not {k_coefficients}')
    if len(detections.pairs) < min_pairs or detections.image_size is None:
        raise _refusal(detections, f'at least {min_pairs} are needed')
    board, size = detections.board, detections.image_size
    radial = cv2.CALIB_FIX_K3 if k_coefficients == 2 else 0
    rms_left, k1, d1 = _calibrate_camera(detections.left_views(), board, size, radial)
    rms_right, k2, d2 = _calibrate_camera(detections.right_views(), board, size, radial)
    left_pts = [left for _, left, _ in detections.pairs]
    right_pts = [right for _, _, right in detections.pairs]
    objects = [board.object_points()] * len(left_pts)
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | radial) if joint else cv2.CALIB_FIX_INTRINSIC
    try:
        stereo = cv2.stereoCalibrate(objects, left_pts, right_pts, k1, d1, k2, d2, size,
                                     flags=flags, criteria=_CALIB_CRITERIA)
    except cv2.error as error:
        raise CalibrationError(f'OpenCV could not calibrate the pair from {len(left_pts)} '
                               f'pairs ({_opencv_reason(error)})') from None
    rms = float(stereo[0])
    k1, k2 = _f64(stereo[1]), _f64(stereo[3])
    d1, d2 = _f64(stereo[2]).reshape(-1), _f64(stereo[4]).reshape(-1)
    rotation, translation = _f64(stereo[5]), _f64(stereo[6]).reshape(3)
    _check_side_by_side(translation)
    rectified = cv2.stereoRectify(k1, d1, k2, d2, size, rotation, translation.reshape(3, 1),
                                  flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
    r1, r2, p1, p2 = (_f64(m) for m in rectified[:4])
    width, height = size
    left = CameraModel(width, height, k1, d1, r1, p1, 'plumb_bob', names[0])
    right = CameraModel(width, height, k2, d2, r2, p2, 'plumb_bob', names[1])
    left.check()
    right.check()
    dy = _epipolar_offsets(detections, left, right)
    return StereoCalibration(
        left, right, rotation, translation, rms, rms_left, rms_right,
        float(np.mean(np.abs(dy))), float(np.max(np.abs(dy))), len(detections.pairs),
        len(detections.left_views()), len(detections.right_views()), joint)


def _epipolar_offsets(detections: Detections, left: CameraModel, right: CameraModel
                      ) -> NDArray[np.float64]:
    """``y_left - y_right`` (px) of every corner of every pair in the rectified images."""
    offsets = []
    for _, left_corners, right_corners in detections.pairs:
        y_left = _f64(cv2.undistortPoints(left_corners, left.K, left.D, R=left.R,
                                          P=left.P))[:, 0, 1]
        y_right = _f64(cv2.undistortPoints(right_corners, right.K, right.D, R=right.R,
                                           P=right.P))[:, 0, 1]
        offsets.append(y_left - y_right)
    return np.concatenate(offsets)


def _check_side_by_side(translation: Vector3) -> None:
    """CameraInfo's stereo convention (and the stereo node) wants the right camera to the
    right of the left one, along the left camera's x axis: ``T`` (left -> right camera
    coordinates) then points along -x."""
    tx, ty, tz = (float(v) for v in translation)
    where = f'T = [{tx * 1e3:.1f}, {ty * 1e3:.1f}, {tz * 1e3:.1f}] mm'
    if abs(tx) < max(abs(ty), abs(tz)):
        raise CalibrationError(f'the cameras are not side by side ({where}: the right camera '
                               "is not beside the left one along the image's x axis)")
    if tx > 0:
        raise CalibrationError(f'the right camera is to the left of the left camera ({where}): '
                               'are the left and right images swapped?')


# ---------------------------------------------------------------------------------------------
# Image sources


def _image_files(folder: Path, prefix: str) -> dict[str, Path]:
    files = {}
    for path in folder.iterdir():
        if (path.is_file() and path.name.lower().startswith(prefix)
                and path.suffix.lower() in IMAGE_SUFFIXES):
            files[path.name[len(prefix):]] = path
    return files


def _natural_key(text: str) -> list[Any]:
    return [int(part) if part.isdigit() else part for part in re.split(r'(\d+)', text)]


def _pair_name(rest: str) -> str:
    stem = rest.rsplit('.', 1)[0].strip('-_. ')
    return stem or rest


def folder_pairs(folder: str | os.PathLike[str]) -> tuple[int, Iterator[ImagePair]]:
    """The pairs of a folder: ``left<rest>`` with ``right<rest>`` (any image suffix, the
    prefix in any case), e.g. ``left-0001.png`` and ``right-0001.png`` as camera_calibration
    saves them. Returns the number of pairs (unmatched images included, as pairs with a
    problem) and an iterator that reads the images one pair at a time."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(f'{folder}: no such folder' if not folder.exists()
                               else f'{folder}: not a folder (give the folder of the images)')
    lefts, rights = _image_files(folder, 'left'), _image_files(folder, 'right')
    if not lefts and not rights:
        hint = ''
        if (folder / 'left').is_dir() or (folder / 'right').is_dir():
            hint = ('; it has left/ and right/ subfolders: put the images in one folder named '
                    'left<rest> and right<rest> instead')
        raise CalibrationError(f'{folder}: no left*.png / right*.png images{hint}')
    keys = sorted(set(lefts) | set(rights), key=_natural_key)

    def read() -> Iterator[ImagePair]:
        for key in keys:
            name = _pair_name(key)
            # Generic reasons (the name says which pair), so that they group in the report.
            if key not in rights:
                yield ImagePair(name, problem='left image without a right one of the same name')
                continue
            if key not in lefts:
                yield ImagePair(name, problem='right image without a left one of the same name')
                continue
            left = cv2.imread(str(lefts[key]), cv2.IMREAD_GRAYSCALE)
            right = cv2.imread(str(rights[key]), cv2.IMREAD_GRAYSCALE)
            if left is None or right is None:
                yield ImagePair(name, problem='image that cannot be read')
                continue
            yield ImagePair(name, np.asarray(left, np.uint8), np.asarray(right, np.uint8))

    return len(keys), read()


def image_from_message(message: Any) -> Gray:
    """A sensor_msgs/Image (rosbags or rclpy message: ``height``, ``width``, ``encoding``,
    ``step``, ``data``) as a grey image; ValueError for other encodings."""
    height, width, step = int(message.height), int(message.width), int(message.step)
    encoding = str(message.encoding).lower()
    channels = {'mono8': 1, '8uc1': 1, 'rgb8': 3, 'bgr8': 3, '8uc3': 3,
                'rgba8': 4, 'bgra8': 4}.get(encoding)
    if channels is None:
        raise ValueError(f"encoding '{message.encoding}' is not supported (mono8, rgb8, bgr8)")
    data = np.frombuffer(bytes(message.data) if not isinstance(message.data, np.ndarray)
                         else message.data.tobytes(), dtype=np.uint8)
    if height <= 0 or width <= 0 or step < width * channels or data.size < step * height:
        raise ValueError(f'{width}x{height} {encoding} with step {step} does not fit its '
                         f'{data.size} bytes')
    rows = data[:step * height].reshape(height, step)[:, :width * channels]
    if channels == 1:
        return np.ascontiguousarray(rows)
    pixels = np.ascontiguousarray(rows.reshape(height, width, channels))
    code = {'rgb8': cv2.COLOR_RGB2GRAY, 'bgr8': cv2.COLOR_BGR2GRAY, '8uc3': cv2.COLOR_BGR2GRAY,
            'rgba8': cv2.COLOR_RGBA2GRAY, 'bgra8': cv2.COLOR_BGRA2GRAY}[encoding]
    return np.asarray(cv2.cvtColor(pixels, code), dtype=np.uint8)


class ImageBag(Protocol):
    """What :func:`bag_pairs` needs of an open bag: ``inhand_common.bag_source.BagSource``
    (topic name -> ``.msgtype``, ``.count``; raw messages in time order; ``problem``)."""

    @property
    def topics(self) -> Mapping[str, Any]: ...

    @property
    def problem(self) -> str | None: ...

    def messages(self, topics: set[str]) -> Iterator[tuple[str, int, bytes]]: ...


def bag_pairs(bag: ImageBag, left_topic: str = LEFT_IMAGE_TOPIC,
              right_topic: str = RIGHT_IMAGE_TOPIC, max_pending: int = 64,
              name: str = 'the bag') -> tuple[int, Iterator[ImagePair]]:
    """The image pairs of an open bag, paired by exact ``header.stamp``. Returns the smaller
    of the two topics' message counts and the iterator (to run while the bag is open).

    CDR is decoded with rosbags' typestore (no rclpy). An image waits for its partner among
    the ``max_pending`` most recent images of the other camera; older ones are reported as
    unpaired. CalibrationError when a topic is missing or not sensor_msgs/Image.
    """
    from rosbags.typesys import Stores, get_typestore

    for topic in (left_topic, right_topic):
        info = bag.topics.get(topic)
        if info is None:
            have = ', '.join(sorted(bag.topics)) or 'no topics'
            raise CalibrationError(f'{name}: no {topic} topic (it has {have})')
        if info.msgtype != IMAGE_TYPE:
            raise CalibrationError(f'{name}: {topic} holds {info.msgtype}, not {IMAGE_TYPE}')
    count = min(int(bag.topics[left_topic].count), int(bag.topics[right_topic].count))
    store = get_typestore(Stores.ROS2_JAZZY)

    def read() -> Iterator[ImagePair]:
        pending: dict[str, dict[int, Any]] = {left_topic: {}, right_topic: {}}
        for topic, _, raw in bag.messages({left_topic, right_topic}):
            message: Any = store.deserialize_cdr(raw, IMAGE_TYPE)
            stamp = message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec
            other = right_topic if topic == left_topic else left_topic
            partner = pending[other].pop(stamp, None)
            if partner is None:
                mine = pending[topic]
                mine[stamp] = message
                while len(mine) > max_pending:
                    old = next(iter(mine))
                    del mine[old]
                    yield ImagePair(_stamp_name(old), problem=_unpaired(topic, left_topic))
                continue
            left, right = (message, partner) if topic == left_topic else (partner, message)
            yield _decoded_pair(_stamp_name(stamp), left, right)
        for topic, waiting in pending.items():
            for stamp in waiting:
                yield ImagePair(_stamp_name(stamp), problem=_unpaired(topic, left_topic))
        if bag.problem:
            yield ImagePair('end of bag', problem=f'the bag is damaged: {bag.problem}')

    return count, read()


def _unpaired(topic: str, left_topic: str) -> str:
    side, other = ('left', 'right') if topic == left_topic else ('right', 'left')
    return f'{side} image with no {other} image of the same stamp'


def _stamp_name(stamp: int) -> str:
    return f'{stamp // 1_000_000_000}.{stamp % 1_000_000_000:09d}'


def _decoded_pair(name: str, left: Any, right: Any) -> ImagePair:
    try:
        return ImagePair(name, image_from_message(left), image_from_message(right))
    except ValueError as error:
        return ImagePair(name, problem=str(error))
