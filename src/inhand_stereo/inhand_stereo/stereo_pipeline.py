"""One stereo exposure through the pipeline: rectify, disparity, 3D points, texture of the map.

The stereo node's whole job apart from messages, so that it is tested without DDS and a bag
processed offline gives what the node publishes:

1. :meth:`StereoPipeline.process` takes a left/right image pair and the two camera models,
   rectifies (maps cached per calibration), computes the disparity, the depth of every pixel
   of the rectified left image and the 3D points in ``stereo_left_optical``, and keeps the
   result as the *last shot*.
2. :meth:`StereoShot.points_in_map` brings the points into the map frame ``object`` with the
   camera's pose in the tracker frame (``camera_pose``) and the map frame's pose at the
   images' stamp (identity in static mode).
3. :meth:`StereoShot.texture` colours the occupied cells of the current map from that shot,
   only where the camera saw each cell's surface (``texture.py``). The node calls it again on
   every map update: the paper takes one shot before the exploration, so the shot stays while
   the map grows.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from inhand_common.array_types import Matrix3, Vector3
from inhand_common.rotations import matrix_to_quaternion
from inhand_stereo.camera_model import CameraModel
from inhand_stereo.disparity import DisparityConfig, DisparityMatcher, DisparityResult
from inhand_stereo.rectification import StereoRectifier, rectifier_for
from inhand_stereo.reprojection import camera_points_to_map, depth_and_points
from inhand_stereo.texture import CellTexture, depth_holes, texture_cells

__all__ = ['StereoPipeline', 'StereoShot', 'pose_vector']


def pose_vector(rotation: Matrix3, position: Vector3) -> NDArray[np.float64]:
    """[x, y, z, qx, qy, qz, qw] of a pose given as a rotation matrix and a position."""
    return np.concatenate([np.asarray(position, dtype=np.float64).reshape(3),
                           np.asarray(matrix_to_quaternion(rotation), dtype=np.float64)])


@dataclass(frozen=True, eq=False)
class StereoShot:
    """What one exposure gave: everything the map's texture needs, kept for map updates."""

    stamp_ns: int
    disparity: DisparityResult
    depth: NDArray[np.float32]           # (H, W) m along the rectified left optical axis; NaN
    left_rgb: NDArray[np.uint8]          # (H, W, 3) rectified left image, RGB
    points: NDArray[np.float32]          # (N, 3) in stereo_left_optical (raw left camera), m
    colours: NDArray[np.uint8]           # (N, 3) RGB of those points
    rectifier: StereoRectifier
    left_camera: CameraModel             # the left camera as calibrated (its P: rectified)

    def points_in_map(self, camera_pose: ArrayLike, object_pose: ArrayLike | None
                      ) -> NDArray[np.float32]:
        """The points in the map frame ``object``: ``camera_pose`` = [x y z qx qy qz qw] of
        stereo_left_optical in the tracker frame; ``object_pose`` the map frame's pose in the
        tracker frame at the stamp, same layout (None in static mode)."""
        return np.asarray(camera_points_to_map(self.points, camera_pose, object_pose),
                          dtype=np.float32)

    def texture(self, centres: ArrayLike, resolution: float, camera_pose: ArrayLike,
                object_pose: ArrayLike | None, rescued: ArrayLike | None = None) -> CellTexture:
        """Colour and textured mask of occupied cells (map-frame centres) from this shot;
        ``rescued``: those the cell judge rescued (texture.texture_cells)."""
        camera = np.asarray(camera_pose, dtype=np.float64).reshape(7)
        obj = (np.asarray(object_pose, dtype=np.float64).reshape(7) if object_pose is not None
               else np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))
        return texture_cells(centres, resolution, self.left_rgb, self.left_camera,
                             self.rectifier.R_left, (camera[:3], camera[3:]),
                             (obj[:3], obj[3:]), self.depth, depth_hole_mask=self.holes,
                             rescued=rescued)

    @cached_property
    def holes(self) -> NDArray[np.bool_]:
        """The depth's enclosed holes (texture.depth_holes): once per shot, not per map
        update."""
        return depth_holes(self.depth)


class StereoPipeline:
    """Rectify, match and reproject stereo pairs with one disparity configuration."""

    def __init__(self, disparity: DisparityConfig | Mapping[str, Any] | None = None,
                 point_step: int = 1):
        if point_step < 1:
            raise ValueError(f'point_step must be at least 1, got {point_step}')
        self.matcher = DisparityMatcher(disparity)
        self.point_step = point_step

    def process(self, stamp_ns: int, left_image: NDArray[np.uint8],
                right_image: NDArray[np.uint8], encoding: str, left: CameraModel,
                right: CameraModel) -> StereoShot:
        """One exposure. Raises ValueError (CameraModelError, ImageError among them) naming
        the problem when the pair or its calibration cannot be used."""
        for side, image, model in (('left', left_image, left), ('right', right_image, right)):
            if image.shape[1] != model.width or image.shape[0] != model.height:
                raise ValueError(f'{side} image is {image.shape[1]}x{image.shape[0]} but its '
                                 f'camera_info says {model.width}x{model.height}')
        rectifier = rectifier_for(left, right)
        # One remap per image; the left one as RGBA gives the matcher's grey, the shot's RGB
        # and the points' colours (RGBA words) without another conversion.
        frame = rectifier.rectify_frame(left_image, right_image, encoding)
        result = self.matcher.compute(frame.left_grey, frame.right_grey,
                                      cx_offset=rectifier.cx_offset)
        # The depth is the points' z in the rectified camera: one pass gives both.
        depth, points, colours = depth_and_points(result.disparity, rectifier.Q,
                                                  result.min_disparity, image=frame.left_rgba,
                                                  R_left=rectifier.R_left, step=self.point_step,
                                                  encoding='rgba8')
        if colours is None:
            colours = np.zeros((len(points), 3), dtype=np.uint8)
        return StereoShot(stamp_ns=stamp_ns, disparity=result, depth=depth,
                          left_rgb=frame.left_rgb,
                          points=points, colours=colours, rectifier=rectifier, left_camera=left)
