"""Rectification of a calibrated stereo pair, and the pair's geometry (Q, baseline, focal).

The two CameraInfo messages of a stereo pair (as ``camera_calibration`` writes them) say
everything: ``K``/``D`` undistort each raw image, ``R`` rotates it onto the common image
plane and ``P`` projects the rectified image, with ``P_right[0, 3] = -fx' * baseline``. After
:meth:`StereoRectifier.rectify` a scene point lies on the same row of both images and its
disparity ``x_left - x_right`` gives its depth.

The undistort-rectify maps are built once per calibration (``cv2.initUndistortRectifyMap``,
a few milliseconds) and every frame is one ``cv2.remap`` per image. Measured for 640x480
(``test/benchmarks/bench_stereo.py``): float CV_32FC1 maps remap a grey image faster than
the fixed-point CV_16SC2 ones (0.65 against 1.1 ms), and a colour image is remapped fastest
as four channels: RGB -> RGBA, remap, -> RGB takes 0.6 ms where remapping the three
channels directly takes 1.4 ms (CV_16SC2: 1.5), with the very same result. The two map
formats do not give the same image (OpenCV 5 interpolates float maps in floating point,
fixed-point ones on a 1/32 px grid: a tenth of the pixels differ, by up to 3 grey levels),
so the faster is also the one whose disparities the tests and benchmarks hold.

Pairs whose images already are rectified (identity ``R``, no distortion, ``P = [K | t]``,
as a simulator or a camera with on-board rectification publishes) are passed through
without a remap.

:meth:`StereoRectifier.rectify_frame` is the stereo node's per-frame step: it gives
exactly what :meth:`~StereoRectifier.rectify` followed by the grey conversion gives
(colour images remapped, then turned grey), with the left image kept as the RGBA the
remap produced, so that neither the colours of the points nor the map's texture convert it
again.

The node keeps one rectifier per calibration: :func:`rectifier_for` returns the cached one
while the CameraInfo values stay the same and builds a new one when they change.

No rclpy here: the node converts its CameraInfo messages with
:meth:`~inhand_stereo.camera_model.CameraModel.from_fields`.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any, NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray

from inhand_common.array_types import Floats, Matrix3
from inhand_stereo.camera_model import CameraModel, CameraModelError

__all__ = ['Image', 'RectifiedFrame', 'StereoRectifier', 'check_pair',
           'rectifier_for']

Image = NDArray[np.uint8]   # (H, W) mono8 or (H, W, 3) rgb8/bgr8
_MapPair = tuple[NDArray[Any], NDArray[Any]]   # cv2.remap's map1, map2

# Distortion coefficient counts cv2.initUndistortRectifyMap accepts (plumb_bob has 5,
# rational_polynomial 8).
_DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)
# Rectified focal lengths and cy of the two cameras come out of one cv2.stereoRectify call
# and are equal by construction; the tolerance only absorbs the decimals a YAML file keeps.
_FOCAL_RTOL = 1e-5
_PIXEL_ATOL = 1e-3


class RectifiedFrame(NamedTuple):
    """One frame rectified for the stereo node (:meth:`StereoRectifier.rectify_frame`)."""

    left_rgba: NDArray[np.uint8]    # (H, W, 4) the left image, R, G, B (grey replicated), A
    left_rgb: NDArray[np.uint8]     # (H, W, 3) the same, R, G, B (C-contiguous)
    left_grey: Image                # (H, W) for the matcher
    right_grey: Image               # (H, W) for the matcher


# cv2.cvtColor codes: a raw colour image of this encoding -> RGBA in R, G, B order.
_TO_RGBA = {'rgb8': cv2.COLOR_RGB2RGBA, 'bgr8': cv2.COLOR_BGR2RGBA}


def check_pair(left: CameraModel, right: CameraModel) -> None:
    """Refuse (CameraModelError, a ValueError) a pair that cannot be a rectified stereo pair.

    Each camera must pass its own check (sizes, finite values, non-zero focal lengths); then
    the pair must share one image size, the left ``P`` must be the origin of the rectified
    pair (``P[0, 3] = 0``), the right ``P`` must carry a horizontal baseline with the right
    camera on the right (``P[0, 3] = -fx' * baseline < 0``), and both rectified cameras must
    have one focal length and one ``cy`` (else rows do not correspond). ``cx`` may differ
    (verged cameras); the disparity accounts for it.
    """
    left.check()
    right.check()
    for side, model in (('left', left), ('right', right)):
        if len(model.D) not in _DISTORTION_LENGTHS:
            raise CameraModelError(f'{side} camera_info: D has {len(model.D)} coefficients; '
                                   'OpenCV takes 0, 4, 5 (plumb_bob), 8 (rational_polynomial), '
                                   '12 or 14')
    if left.size != right.size:
        raise CameraModelError(f'stereo pair: left image is {left.width}x{left.height}, right '
                               f'is {right.width}x{right.height}; both cameras must have one '
                               'size')
    if right.P[0, 3] == 0.0:
        raise CameraModelError('stereo pair: right P without a baseline (P[0, 3] = 0): the '
                               'right camera_info must come from a stereo calibration, with '
                               "P[0, 3] = -fx' * baseline")
    if right.P[0, 3] > 0.0:
        raise CameraModelError(f'stereo pair: right P[0, 3] = {right.P[0, 3]:g} > 0 puts the '
                               'right camera to the left of the left one (left and right '
                               'swapped?)')
    if left.P[0, 3] != 0.0:
        raise CameraModelError(f'stereo pair: left P[0, 3] = {left.P[0, 3]:g}, expected 0 (the '
                               'left camera is the origin of the rectified pair; left and '
                               'right swapped?)')
    for side, model in (('left', left), ('right', right)):
        if abs(model.P[1, 3]) > _PIXEL_ATOL or abs(model.P[2, 3]) > _PIXEL_ATOL:
            raise CameraModelError(f'stereo pair: {side} P[1, 3] = {model.P[1, 3]:g}, '
                                   f'P[2, 3] = {model.P[2, 3]:g}: only a horizontal baseline '
                                   'is supported (both must be 0)')
    for label, (row, col) in (("fx'", (0, 0)), ("fy'", (1, 1))):
        a, b = left.P[row, col], right.P[row, col]
        if not np.isclose(a, b, rtol=_FOCAL_RTOL, atol=_PIXEL_ATOL):
            raise CameraModelError(f'stereo pair: rectified focal lengths differ ({label} '
                                   f'left {a:g}, right {b:g}); the two P must come from one '
                                   'stereo calibration')
    if not np.isclose(left.P[1, 2], right.P[1, 2], rtol=0.0, atol=_PIXEL_ATOL):
        raise CameraModelError(f"stereo pair: rectified cy' differs (left {left.P[1, 2]:g}, "
                               f'right {right.P[1, 2]:g}): rows would not correspond')


def _read_only(array: NDArray[np.float64]) -> Floats:
    out = np.array(array, dtype=np.float64)
    out.setflags(write=False)
    return out


def _reprojection_matrix(p_left: Floats, p_right: Floats) -> Floats:
    """Q as image_geometry's StereoCameraModel builds it (``updateQ``), acting on
    ``[u, v, x_l - x_r, 1]``: its last entry ``fy (cx_l - cx_r)`` removes the principal
    point offset, so it expects disparities that are *not* pre-adjusted."""
    fx, fy = p_left[0, 0], p_left[1, 1]
    cx, cy = p_left[0, 2], p_left[1, 2]
    tx = p_right[0, 3] / p_right[0, 0]          # = -baseline(); image_geometry's Tx
    q = np.zeros((4, 4))
    q[0, 0] = fy * tx
    q[0, 3] = -fy * cx * tx
    q[1, 1] = fx * tx
    q[1, 3] = -fx * cy * tx
    q[2, 3] = fx * fy * tx
    q[3, 2] = -fy
    q[3, 3] = fy * (cx - p_right[0, 2])
    return q


class StereoRectifier:
    """Undistorts and rectifies the images of one calibrated stereo pair (module doc).

    Build it once per calibration (:func:`rectifier_for` caches); :meth:`rectify` is then
    a remap per image. Raises CameraModelError when the pair is unusable (:func:`check_pair`).
    """

    def __init__(self, left: CameraModel, right: CameraModel) -> None:
        check_pair(left, right)
        self._size = left.size
        self._p_left = _read_only(left.P)
        self._p_right = _read_only(right.P)
        self._r_left = _read_only(left.R)
        self._q = _read_only(_reprojection_matrix(left.P, right.P))
        self._passthrough = left.is_rectified_input and right.is_rectified_input
        self._maps: dict[str, _MapPair] = {}
        if not self._passthrough:
            for side, model in (('left', left), ('right', right)):
                map_x, map_y = cv2.initUndistortRectifyMap(model.K, model.D, model.R,
                                                           model.P[:, :3], model.size,
                                                           cv2.CV_32FC1)
                self._maps[side] = (map_x, map_y)

    # -- geometry -------------------------------------------------------------------------

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of both images."""
        return self._size

    @property
    def passthrough(self) -> bool:
        """Both cameras already deliver rectified images: :meth:`rectify` copies nothing."""
        return self._passthrough

    @property
    def Q(self) -> Floats:
        """(4, 4) reprojection matrix, exactly image_geometry's StereoCameraModel Q.

        ``[X, Y, Z, W]^T = Q [u, v, x_l - x_r, 1]^T`` gives the point ``(X, Y, Z) / W`` in
        the rectified left camera frame. With ``Tx = P_right[0, 3] / P_right[0, 0]`` (minus
        the baseline) it holds ``fy Tx``, ``fx Tx``, ``-fy cx Tx``, ``-fx cy Tx``,
        ``fx fy Tx``, ``-fy`` and ``fy (cx_l - cx_r)``. For disparities pre-adjusted as
        DisparityImage defines them, that last entry must be 0
        (:func:`inhand_stereo.reprojection.points_from_disparity` takes care of it).
        """
        return self._q

    @property
    def baseline(self) -> float:
        """Distance between the two camera centres (m): ``-P_right[0, 3] / P_right[0, 0]``."""
        return float(-self._p_right[0, 3] / self._p_right[0, 0])

    @property
    def focal(self) -> float:
        """Rectified focal length fx' (px), DisparityImage's ``f``."""
        return float(self._p_left[0, 0])

    @property
    def cx_offset(self) -> float:
        """``cx_left - cx_right`` of the rectified cameras (px), 0 unless verged; the
        disparity matcher subtracts it (DisparityImage's pre-adjusted ``d``)."""
        return float(self._p_left[0, 2] - self._p_right[0, 2])

    @property
    def P_left(self) -> Floats:
        """(3, 4) projection of the rectified left image (the left CameraInfo's P)."""
        return self._p_left

    @property
    def R_left(self) -> Matrix3:
        """(3, 3) rotation raw left camera -> rectified left camera (the left CameraInfo's R):
        ``p_rectified = R_left p_raw``, so ``p_raw = R_left^T p_rectified`` brings points
        back to ``stereo_left_optical``."""
        return self._r_left

    # -- images ---------------------------------------------------------------------------

    def rectify(self, left_image: Image, right_image: Image) -> tuple[Image, Image]:
        """Both images rectified (same shape and dtype as given); the inputs themselves when
        the cameras deliver rectified images."""
        return self.rectify_left(left_image), self.rectify_right(right_image)

    def rectify_frame(self, left_image: Image, right_image: Image, encoding: str
                      ) -> RectifiedFrame:
        """What the stereo node needs of a frame: the left image rectified as RGBA and RGB,
        and both rectified images in grey for the matcher.

        The values are exactly those of :meth:`rectify` followed by
        :func:`~inhand_stereo.image_encoding.to_grey` and
        :func:`~inhand_stereo.image_encoding.to_rgb`: a colour image is remapped in colour
        (as four channels, the fastest: module doc) and turned grey afterwards, a mono8
        image remapped as it is. The left colour image goes to RGBA in R, G, B order before
        its remap (a bgr8 image's channels swapped in the same pass), so its grey, its RGB
        and the points' colours (RGBA words) all come from the one remap. ``encoding``:
        'mono8', 'rgb8' or 'bgr8', the order of colour images.
        """
        if left_image.ndim != right_image.ndim:
            raise ValueError(f'left image {left_image.shape} and right image '
                             f'{right_image.shape}: one is mono, the other colour')
        if left_image.ndim == 2:
            left_grey = self._remap('left', left_image)
            right_grey = self._remap('right', right_image)
            return RectifiedFrame(_converted(left_grey, cv2.COLOR_GRAY2RGBA),
                                  _converted(left_grey, cv2.COLOR_GRAY2RGB), left_grey, right_grey)
        if encoding not in _TO_RGBA:
            raise ValueError(f"colour image encoding must be 'rgb8' or 'bgr8', got {encoding!r}")
        left_rgba = self._remap_rgba('left', left_image, _TO_RGBA[encoding])
        right_rgba = self._remap_rgba('right', right_image, _TO_RGBA[encoding])
        return RectifiedFrame(left_rgba, _converted(left_rgba, cv2.COLOR_RGBA2RGB),
                              _converted(left_rgba, cv2.COLOR_RGBA2GRAY),
                              _converted(right_rgba, cv2.COLOR_RGBA2GRAY))

    def rectify_left(self, image: Image) -> Image:
        """The left image rectified (mono8 (H, W) or colour (H, W, 3), uint8)."""
        return self._remap('left', image)

    def rectify_right(self, image: Image) -> Image:
        """The right image rectified (mono8 (H, W) or colour (H, W, 3), uint8)."""
        return self._remap('right', image)

    def _remap(self, side: str, image: Image) -> Image:
        self._check_image(side, image)
        if self._passthrough:
            return image
        image = np.ascontiguousarray(image)
        if image.ndim == 2:
            map_x, map_y = self._maps[side]
            return np.asarray(cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR,
                                        borderMode=cv2.BORDER_CONSTANT), dtype=np.uint8)
        # Four channels remap twice as fast as three (module doc); RGB2RGBA only appends
        # the alpha channel, so it serves BGR images as well.
        rectified = self._remap_rgba(side, image, cv2.COLOR_RGB2RGBA)
        return np.asarray(cv2.cvtColor(rectified, cv2.COLOR_RGBA2RGB), dtype=np.uint8)

    def _remap_rgba(self, side: str, image: Image, code: int) -> NDArray[np.uint8]:
        """A colour image converted to four channels by ``code`` and remapped (only
        converted for pre-rectified cameras)."""
        self._check_image(side, image)
        if image.ndim != 3:
            raise ValueError(f'{side} image: shape {image.shape}, expected a colour image '
                             '(H, W, 3)')
        four = _converted(np.ascontiguousarray(image), code)
        if self._passthrough:
            return four
        map_x, map_y = self._maps[side]
        return np.asarray(cv2.remap(four, map_x, map_y, cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT), dtype=np.uint8)

    def _check_image(self, side: str, image: Image) -> None:
        width, height = self._size
        if (image.dtype != np.uint8 or image.ndim not in (2, 3) or image.shape[:2] != (height, width)
                or (image.ndim == 3 and image.shape[2] != 3)):
            raise ValueError(f'{side} image: shape {image.shape} {image.dtype}, expected uint8 '
                             f'({height}, {width}) mono8 or ({height}, {width}, 3) colour as '
                             'its camera_info says')


def _converted(image: NDArray[np.uint8], code: int) -> NDArray[np.uint8]:
    return np.asarray(cv2.cvtColor(image, code), dtype=np.uint8)


# -- one rectifier per calibration --------------------------------------------------------

_CACHE_SIZE = 4
_cache: OrderedDict[bytes, StereoRectifier] = OrderedDict()
_cache_lock = threading.Lock()


def _calibration_key(left: CameraModel, right: CameraModel) -> bytes:
    """The values a rectifier depends on, as bytes: equal calibrations give equal keys."""
    parts: list[bytes] = []
    for model in (left, right):
        parts.append(f'{model.width}x{model.height}:{model.distortion_model}:{len(model.D)}'
                     .encode())
        for matrix in (model.K, model.D, model.R, model.P):
            parts.append(np.ascontiguousarray(matrix, dtype=np.float64).tobytes())
    return b'|'.join(parts)


def rectifier_for(left: CameraModel, right: CameraModel) -> StereoRectifier:
    """The rectifier of this calibration, built on first use and kept (the last few
    calibrations, least recently used dropped), so a node can call this on every frame:
    CameraInfo repeats the same values with every image and building maps costs
    milliseconds. Thread-safe."""
    key = _calibration_key(left, right)
    with _cache_lock:
        found = _cache.get(key)
        if found is not None:
            _cache.move_to_end(key)
            return found
    rectifier = StereoRectifier(left, right)   # outside the lock: it takes a few ms
    with _cache_lock:
        _cache[key] = rectifier
        _cache.move_to_end(key)
        while len(_cache) > _CACHE_SIZE:
            _cache.popitem(last=False)
    return rectifier
