"""Range errors of a stereo shot's depth, for calibrating the vision sensor model.

Two sources of truth, both giving (true range, measured range - true range) pairs in metres
along the rays of the rectified left camera:

* :func:`truth_range_errors`: the simulator's true depth of the left image, on the object's
  pixels (the truth's ``object_mask``);
* :func:`touch_range_errors`: fingertip positions registered into the map frame; a
  fingertip on the surface the camera sees is a true surface point, so the measured range
  at its pixel minus its own range is an error. Fingertips off the surface, or on a side
  the camera does not see, are far from the measured surface and are left out
  (``reach``).
"""

from __future__ import annotations

import numpy as np

from inhand_common.ground_truth import StereoTruth
from inhand_stereo.texture import project_cells
from inhand_tools.bag_stereo_shot import BagShot

__all__ = ['touch_range_errors', 'truth_range_errors']


def _ray_factor(shot: BagShot, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Range / z along the rays through pixels (u, v) of the rectified left camera."""
    P = shot.placed.shot.left_camera.P
    return np.sqrt(((u - P[0, 2]) / P[0, 0]) ** 2 + ((v - P[1, 2]) / P[1, 1]) ** 2 + 1.0)


def truth_range_errors(shot: BagShot, truth: StereoTruth) -> tuple[np.ndarray, np.ndarray]:
    """(true ranges, errors) on the object's pixels with a measurement. ValueError when the
    truth's image is not the shot's (a rig that rectification changes)."""
    measured = shot.placed.shot.depth.astype(np.float64)
    true = np.asarray(truth.depth, dtype=np.float64)
    if true.shape != measured.shape:
        raise ValueError(f'the truth depth is {true.shape[1]}x{true.shape[0]}, the rectified '
                         f'image {measured.shape[1]}x{measured.shape[0]}')
    if not np.allclose(shot.placed.shot.rectifier.R_left, np.eye(3)):
        raise ValueError('the left camera is rotated by rectification: its true depth is of '
                         'another image; use --touch')
    use = np.asarray(truth.object_mask, dtype=bool) & np.isfinite(measured) & np.isfinite(true)
    v, u = np.nonzero(use)
    factor = _ray_factor(shot, u.astype(np.float64), v.astype(np.float64))
    true_range = true[v, u] * factor
    return true_range, measured[v, u] * factor - true_range


def touch_range_errors(shot: BagShot, points: np.ndarray, reach: float = 0.02
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(fingertip ranges, errors) of registered fingertip positions (N, 3, map frame) that
    project onto a measured pixel and lie within ``reach`` (m) of the measured surface."""
    placed = shot.placed
    camera = np.asarray(shot.config.camera_pose, dtype=np.float64)
    projection = project_cells(points, placed.shot.left_camera, placed.shot.rectifier.R_left,
                               (camera[:3], camera[3:]),
                               (placed.object_pose[:3], placed.object_pose[3:]))
    depth = placed.shot.depth
    height, width = depth.shape
    u, v = np.rint(projection.u), np.rint(projection.v)
    inside = (projection.z > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    # the fingertip's range along its own ray, and the measured range on the ray of its pixel
    true_range = projection.z[inside] * _ray_factor(shot, projection.u[inside],
                                                    projection.v[inside])
    measured = depth[v[inside].astype(np.intp), u[inside].astype(np.intp)].astype(np.float64)
    error = measured * true_range / projection.z[inside] - true_range
    keep = np.isfinite(error) & (np.abs(error) < reach)
    return true_range[keep], error[keep]
