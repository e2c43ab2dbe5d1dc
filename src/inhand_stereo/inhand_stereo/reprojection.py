"""3D points from a disparity image, and the frames they go through on the way to the map.

Frames (design.md, "Interface contract"): the disparity lives in the *rectified* left
camera; ``R_left`` (the left CameraInfo's R) turns the raw left camera ``stereo_left_optical``
into it, so ``p_raw = R_left^T p_rect``. The calibration parameter ``camera_pose`` is the pose
of ``stereo_left_optical`` in the tracker frame ``polhemus_source``; in tracked mode the map
frame ``object`` is the object sensor's frame, ``p_object = R_o^T (p_tracker - t_o)`` with the
sensor's pose at the images' stamp (as registration does it for fingertips); in static
mode the map frame is the tracker frame.

Disparity convention: DisparityImage's ``d = x_l - x_r - (cx_l - cx_r)`` (what
:class:`~inhand_stereo.disparity.DisparityMatcher` produces), reprojected with
image_geometry's Q (:attr:`~inhand_stereo.rectification.StereoRectifier.Q`). That Q's last
entry ``fy (cx_l - cx_r)`` is for disparities *not* pre-adjusted; applying it to
pre-adjusted ones subtracts the offset twice (the trap of stereo_image_proc's point cloud
with verged cameras, image_pipeline PR #349), so with ``pre_adjusted=True`` (the default)
it is left out here.

Speed: a frame of 640x480 gives some 200,000 points, so the per-pixel rays
``R_left^T Q [u, v, 0, 1]`` are computed once per (Q, R_left, size, step) and kept; a
frame then costs one masked copy per coordinate and a multiply: 1.4-2.3 ms for 208,000
points here (2 shared cores), about what ``cv2.reprojectImageTo3D`` takes for the dense
image alone, before dropping the invalid pixels (``test/benchmarks/bench_stereo.py``).
The stereo node wants the depth map too, whose pass finds the points' pixels and their W:
:func:`depth_and_points` gives both (and the colours, straight from an RGBA image) with
the values of :func:`depth_map` and :func:`points_from_disparity`, 0.2-0.4 ms less than
the two calls. Measured and left: the points as ``z`` times rays pre-divided by ``Q[2, 3]``
(no ``1 / W``: 0.1 ms, but values that differ in the last bit), one masked copy of 12- or
16-byte records instead of one per coordinate, index arrays, row blocks that stay in the
cache, and a second thread for half of the work (the wall time 0.3 ms shorter after a
matcher call, the CPU time 0.7 ms longer): none faster by more than the noise.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any, NamedTuple

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from inhand_common.array_types import Floats, Matrix3, Vector3
from inhand_common.rotations import quaternion_to_matrix

__all__ = ['Reprojection', 'camera_points_to_map', 'camera_to_map_transform', 'depth_and_points',
           'depth_map', 'map_points_to_camera', 'points_from_disparity', 'transform_points']

Points32 = NDArray[np.float32]      # (N, 3) positions (m), float32 like PointCloud2's fields
Colours = NDArray[np.uint8]         # (N, 3) R, G, B


def _reprojection(Q: ArrayLike, pre_adjusted: bool) -> Floats:
    """Q checked to be a rectified pair's reprojection matrix (no disparity term in X, Y, Z;
    W depending on the disparity alone, as both image_geometry's and cv2.stereoRectify's
    are), with the cx term dropped for pre-adjusted disparities."""
    q = np.array(Q, dtype=np.float64)
    if q.shape != (4, 4) or not np.all(np.isfinite(q)):
        raise ValueError(f'Q must be a finite 4x4 matrix, got shape {q.shape}')
    if np.any(q[:3, 2]) or np.any(q[3, :2]) or q[3, 2] == 0.0 or q[2, 3] == 0.0:
        raise ValueError('Q is not the reprojection matrix of a rectified horizontal stereo '
                         'pair (expected zeros at [0:3, 2] and [3, 0:2], non-zero [3, 2] and '
                         '[2, 3])')
    if pre_adjusted:
        q[3, 3] = 0.0
    return q


# -- rays per pixel, cached -----------------------------------------------------------------

_RAYS_CACHE_SIZE = 4
_rays_cache: OrderedDict[bytes, NDArray[np.float32]] = OrderedDict()
_rays_lock = threading.Lock()


def _rays(q: Floats, rotation: Matrix3 | None, height: int, width: int, step: int
          ) -> NDArray[np.float32]:
    """(3, h*w) per sampled pixel ``R^T (Q [u, v, 0, 1])[:3]``: a point is this over W."""
    key = b'|'.join([q.tobytes(), b'' if rotation is None else rotation.tobytes(),
                     f'{height}x{width}/{step}'.encode()])
    with _rays_lock:
        found = _rays_cache.get(key)
        if found is not None:
            _rays_cache.move_to_end(key)
            return found
    u = np.arange(0, width, step, dtype=np.float64)
    v = np.arange(0, height, step, dtype=np.float64)
    grid_u, grid_v = np.meshgrid(u, v)
    base = (q[:3, 0, None, None] * grid_u + q[:3, 1, None, None] * grid_v
            + q[:3, 3, None, None]).reshape(3, -1)
    if rotation is not None:
        base = rotation.T @ base
    rays = np.ascontiguousarray(base, dtype=np.float32)
    rays.setflags(write=False)
    with _rays_lock:
        _rays_cache[key] = rays
        while len(_rays_cache) > _RAYS_CACHE_SIZE:
            _rays_cache.popitem(last=False)
    return rays


class Reprojection(NamedTuple):
    """A disparity image's depth map, points and their colours (:func:`depth_and_points`)."""

    depth: NDArray[np.float32]      # (H, W) z in the rectified left camera (m), NaN: none
    points: Points32                # (N, 3) of the valid (sampled) pixels
    colours: Colours | None         # (N, 3) R, G, B of those, or None without an image


def _depth(disparity: NDArray[np.float32], q: Floats, invalid_below: float
           ) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.bool_]]:
    """(depth z with NaN where there is no point, W = Q[3, 2] d + Q[3, 3], the mask of the
    pixels with a point) for a float32 disparity: a point needs a disparity at least
    ``invalid_below`` (NaN compares False) and a finite z > 0 (in front, not at infinity)."""
    w = disparity * np.float32(q[3, 2])
    if q[3, 3]:
        w += np.float32(q[3, 3])
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        z = np.float32(q[2, 3]) / w
    valid = disparity >= np.float32(invalid_below)
    scratch = z > 0                                     # NaN compares False
    valid &= scratch
    np.less(z, np.float32(np.inf), out=scratch)
    valid &= scratch
    np.logical_not(valid, out=scratch)
    np.copyto(z, np.float32(np.nan), where=scratch)
    return z, w, valid


def _points(w: NDArray[np.float32], valid: NDArray[np.bool_], q: Floats,
            rotation: Matrix3 | None, shape: tuple[int, int], step: int,
            image: NDArray[np.uint8] | None, encoding: str) -> tuple[Points32, Colours | None]:
    """The points of the pixels ``valid`` (H', W') of the grid sampled with ``step`` from
    an image of ``shape`` (H, W), from their W, and their colours from ``image`` (None
    without one)."""
    mask = np.ascontiguousarray(valid).reshape(-1)
    # Boolean masks and compress, not index arrays: valid pixels come in runs along rows,
    # which compress copies fastest (measured: half the time of flatnonzero + take).
    with np.errstate(divide='ignore', over='ignore'):
        inverse_w = np.float32(1.0) / np.ascontiguousarray(w).reshape(-1)[mask]
    rays = _rays(q, rotation, shape[0], shape[1], step)
    # One plane per coordinate, returned transposed: writing planes is faster than writing
    # the columns of an (N, 3) array.
    planes = np.empty((3, inverse_w.size), dtype=np.float32)
    for axis in range(3):
        np.multiply(rays[axis][mask], inverse_w, out=planes[axis])
    points: Points32 = planes.T
    return points, None if image is None else _colours(image, mask, encoding, step)


def _check_points_arguments(disparity: NDArray[np.floating[Any]], image: NDArray[np.uint8] | None,
                            step: int) -> None:
    if disparity.ndim != 2:
        raise ValueError(f'disparity must be (H, W), got shape {disparity.shape}')
    if step < 1:
        raise ValueError(f'step must be >= 1, got {step}')
    if image is not None and image.shape[:2] != disparity.shape:
        raise ValueError(f'image {image.shape} and disparity {disparity.shape} differ in size')


def _sampled(array: NDArray[Any], step: int) -> NDArray[Any]:
    return array[::step, ::step] if step > 1 else array


def points_from_disparity(disparity: NDArray[np.floating[Any]], Q: ArrayLike,
                          invalid_below: float, image: NDArray[np.uint8] | None = None,
                          R_left: ArrayLike | None = None, step: int = 1, *,
                          encoding: str = 'rgb8', pre_adjusted: bool = True
                          ) -> tuple[Points32, Colours | None]:
    """Points (N, 3) float32 of the valid pixels, and their colours (N, 3) uint8 RGB or None.

    ``disparity`` (H, W) in pixels, invalid where below ``invalid_below`` (pass
    :attr:`DisparityResult.min_disparity <inhand_stereo.disparity.DisparityResult>`);
    ``Q`` image_geometry's reprojection matrix; ``pre_adjusted``: the disparity is
    DisparityImage's ``x_l - x_r - (cx_l - cx_r)`` (module doc). Points behind the camera,
    at infinity (zero disparity) or non-finite are dropped too.

    Frame: the rectified left camera, or with ``R_left`` the raw left camera
    ``stereo_left_optical`` (``p_raw = R_left^T p_rect``); z forward, x right, y down, metres.

    ``image``: the rectified left image, mono8 (H, W), colour (H, W, 3) in ``encoding``
    ('rgb8' or 'bgr8') order, or (H, W, 4) R, G, B, A with ``encoding`` 'rgba8'; colours
    come out as R, G, B. ``step`` takes every step-th pixel in both directions (step 2: a
    quarter of the points).

    Both arrays are views laid out for speed: the points are the transpose of (3, N)
    planes (Fortran order), the colours every 4 bytes of RGBA words (for a mono image, its
    values broadcast to three columns, read-only); ``np.ascontiguousarray`` makes C-ordered
    copies where a consumer needs them. :func:`depth_and_points` gives the same points and
    the depth map in one pass.
    """
    _check_points_arguments(disparity, image, step)
    q = _reprojection(Q, pre_adjusted)
    rotation = None if R_left is None else _rotation(R_left, 'R_left')
    sampled = np.ascontiguousarray(_sampled(disparity, step), dtype=np.float32)
    _, w, valid = _depth(sampled, q, invalid_below)
    return _points(w, valid, q, rotation, disparity.shape, step, image, encoding)


def depth_and_points(disparity: NDArray[np.floating[Any]], Q: ArrayLike, invalid_below: float,
                     image: NDArray[np.uint8] | None = None, R_left: ArrayLike | None = None,
                     step: int = 1, *, encoding: str = 'rgb8', pre_adjusted: bool = True
                     ) -> Reprojection:
    """:func:`depth_map` and :func:`points_from_disparity` of one disparity image at once,
    with the same values as the two calls (arguments as there; the depth is of every pixel,
    ``step`` samples the points only): the depth is the points' z in the rectified camera,
    so its pass also finds the points' pixels and their ``W``."""
    _check_points_arguments(disparity, image, step)
    q = _reprojection(Q, pre_adjusted)
    rotation = None if R_left is None else _rotation(R_left, 'R_left')
    depth, w, valid = _depth(np.asarray(disparity, dtype=np.float32), q, invalid_below)
    points, colours = _points(_sampled(w, step), _sampled(valid, step), q, rotation,
                              disparity.shape, step, image, encoding)
    return Reprojection(depth, points, colours)


def _colours(image: NDArray[np.uint8], valid: NDArray[np.bool_], encoding: str, step: int
             ) -> Colours:
    """R, G, B of the ``valid`` pixels (a flat mask of the grid sampled with ``step``), as
    views: a grey image's values broadcast to three columns (read-only), a colour image's
    RGBA words seen as bytes (a stride of 4 per point). One pass over 8- or 32-bit values
    is several times faster than gathering 3-byte rows."""
    if image.ndim == 2:
        grey = np.ascontiguousarray(_sampled(image, step)).reshape(-1)[valid]
        return np.broadcast_to(grey[:, None], (grey.size, 3))
    if encoding == 'rgba8' and image.shape[2] == 4:
        rgba = np.ascontiguousarray(image)
    elif encoding in ('rgb8', 'bgr8') and image.shape[2] == 3:
        code = cv2.COLOR_BGR2RGBA if encoding == 'bgr8' else cv2.COLOR_RGB2RGBA
        rgba = np.asarray(cv2.cvtColor(np.ascontiguousarray(_sampled(image, step)), code),
                          dtype=np.uint8)
        step = 1
    else:
        raise ValueError(f"colour image: (H, W, 3) with encoding 'rgb8' or 'bgr8', or "
                         f"(H, W, 4) with 'rgba8'; got {image.shape} with {encoding!r}")
    words = np.ascontiguousarray(_sampled(rgba.view(np.uint32)[:, :, 0], step))
    colours: Colours = words.reshape(-1)[valid].view(np.uint8).reshape(-1, 4)[:, :3]
    return colours


def depth_map(disparity: NDArray[np.floating[Any]], Q: ArrayLike, invalid_below: float, *,
              pre_adjusted: bool = True) -> NDArray[np.float32]:
    """(H, W) float32 depth z (m) along the rectified left camera's optical axis per pixel,
    NaN where there is no measurement (invalid, zero or negative disparity).

    With the rectified left camera's ``P`` (:attr:`StereoRectifier.P_left
    <inhand_stereo.rectification.StereoRectifier>`), a point ``p_rect`` in that frame
    lands at pixel ``P [p_rect, 1]`` and is visible there when its z is this depth; the
    map goes into that frame through ``R_left`` (:attr:`StereoRectifier.R_left`).
    """
    q = _reprojection(Q, pre_adjusted)
    depth, _, _ = _depth(np.asarray(disparity, dtype=np.float32), q, invalid_below)
    return depth


# -- frames ----------------------------------------------------------------------------------

def _rotation(matrix: ArrayLike, name: str) -> Matrix3:
    rotation = np.asarray(matrix, dtype=np.float64)
    if rotation.shape != (3, 3) or not np.all(np.isfinite(rotation)):
        raise ValueError(f'{name} must be a finite 3x3 rotation, got shape {rotation.shape}')
    return rotation


def _pose(pose: ArrayLike, name: str) -> tuple[Matrix3, Vector3]:
    """Rotation and translation of ``[x, y, z, qx, qy, qz, qw]``."""
    values = np.asarray(pose, dtype=np.float64).reshape(-1)
    if values.shape != (7,) or not np.all(np.isfinite(values)):
        raise ValueError(f'{name} must be 7 finite numbers [x, y, z, qx, qy, qz, qw], got '
                         f'{values.size}')
    return quaternion_to_matrix(values[3:]), values[:3]


def transform_points(points: NDArray[np.floating[Any]], position: ArrayLike,
                     quaternion_xyzw: ArrayLike) -> NDArray[np.floating[Any]]:
    """``R p + t`` for every row of ``points`` (N, 3), in the points' own float type
    (float32 stays float32 for PointCloud2)."""
    rotation = quaternion_to_matrix(np.asarray(quaternion_xyzw, dtype=np.float64))
    return _apply(points, rotation, np.asarray(position, dtype=np.float64).reshape(3))


def _apply(points: NDArray[np.floating[Any]], rotation: Matrix3, offset: Vector3
           ) -> NDArray[np.floating[Any]]:
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f'points must be (N, 3), got shape {array.shape}')
    dtype = array.dtype if array.dtype in (np.float32, np.float64) else np.dtype(np.float64)
    result: NDArray[np.floating[Any]] = array.astype(dtype, copy=False) @ rotation.T.astype(dtype)
    result += offset.astype(dtype)
    return result


def camera_to_map_transform(camera_pose: ArrayLike, object_pose: ArrayLike | None = None
                            ) -> tuple[Matrix3, Vector3]:
    """(R, t) with ``p_map = R p_camera + t``: camera (``stereo_left_optical``) -> tracker
    (``camera_pose``, the camera's pose in ``polhemus_source``) -> map frame ``object``
    (the inverse of ``object_pose``, the object sensor's pose at the images' stamp, in
    tracked mode; nothing in static mode, where ``object_pose`` is None). Both poses are
    ``[x, y, z, qx, qy, qz, qw]``."""
    r_cam, t_cam = _pose(camera_pose, 'camera_pose')
    if object_pose is None:
        return r_cam, t_cam
    r_obj, t_obj = _pose(object_pose, 'object_pose')
    return r_obj.T @ r_cam, r_obj.T @ (t_cam - t_obj)


def camera_points_to_map(points: NDArray[np.floating[Any]], camera_pose: ArrayLike,
                         object_pose: ArrayLike | None = None) -> NDArray[np.floating[Any]]:
    """Points (N, 3) from ``stereo_left_optical`` into the map frame ``object``
    (:func:`camera_to_map_transform`), in the points' own float type."""
    rotation, offset = camera_to_map_transform(camera_pose, object_pose)
    return _apply(points, rotation, offset)


def map_points_to_camera(points: NDArray[np.floating[Any]], camera_pose: ArrayLike,
                         object_pose: ArrayLike | None = None) -> NDArray[np.floating[Any]]:
    """The inverse of :func:`camera_points_to_map`: map-frame points in
    ``stereo_left_optical`` (then ``R_left @ p`` puts them in the rectified camera)."""
    rotation, offset = camera_to_map_transform(camera_pose, object_pose)
    return _apply(points, rotation.T, -(rotation.T @ offset))
