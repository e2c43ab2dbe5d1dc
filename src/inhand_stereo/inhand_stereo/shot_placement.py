"""Stereo shots placed on the object: the map frame's pose at each shot's stamp.

The images are taken in the tracker frame (through ``camera_pose``); the map frame
``object`` rides on the object sensor, so a shot is usable once the object's pose at its
stamp is known, by the fingertips' rules (:meth:`Registrar.object_pose_at`: exact stamp,
interpolation across short gaps, never extrapolated). :class:`ShotPlacer` holds a shot
until the object poses around its stamp have come; in static mode the map frame is the
tracker frame and every shot is placed at once. The graph's mode is the registration
node's: until the node knows it, the placer has no registrar and holds every shot
(:func:`waiting_advice` says why a shot waits, and what to do). The node and the bag tools
share it.
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from inhand_common.array_types import Matrix3, Vector3
from inhand_mapping.occupancy import GridSpec
from inhand_mapping.registration import Registrar
from inhand_stereo.scene_segmentation import (
    DEFAULT_SEGMENTATION,
    Segmentation,
    SegmentationConfig,
    segment_object,
)
from inhand_stereo.segmentation_kernels import back_project
from inhand_stereo.stereo_pipeline import StereoShot, pose_vector
from inhand_stereo.texture import CellTexture, map_to_rectified
from inhand_stereo.vision_model import VisionMap

__all__ = ['PlacedShot', 'ShotPlacer', 'UnplacedShot', 'waiting_advice']

MAX_HELD = 4   # shots waiting for object poses; an older one is given up when more come
MAX_EARLY_POSES = 100_000   # object poses kept while the mode is not known (7 min at 240 Hz)


class PlacedShot(NamedTuple):
    """A shot with the map frame's pose in the tracker frame at its stamp."""

    shot: StereoShot
    object_pose: NDArray[np.float64]     # (7,) x y z qx qy qz qw

    def points_in_map(self, camera_pose: ArrayLike) -> NDArray[np.float32]:
        """The shot's 3D points in the map frame (``camera_pose``: the left camera in the
        tracker frame)."""
        return self.shot.points_in_map(camera_pose, self.object_pose)

    def texture(self, centres: ArrayLike, resolution: float, camera_pose: ArrayLike,
                rescued: ArrayLike | None = None) -> CellTexture:
        """Colours and textured mask of occupied cells (map-frame centres) from the shot;
        ``rescued``: those the cell judge rescued (texture.texture_cells)."""
        return self.shot.texture(centres, resolution, camera_pose, self.object_pose, rescued)

    def map_to_camera(self, camera_pose: ArrayLike) -> tuple[Matrix3, Vector3]:
        """``(M, b)`` with ``p_rectified = M p_map + b`` (the rectified left camera)."""
        camera = np.asarray(camera_pose, dtype=np.float64).reshape(7)
        return map_to_rectified((camera[:3], camera[3:]),
                                (self.object_pose[:3], self.object_pose[3:]),
                                self.shot.rectifier.R_left)

    def pixel_points_in_map(self, camera_pose: ArrayLike) -> NDArray[np.float64]:
        """(H * W, 3) the measured point of every pixel of the rectified left image in the
        map frame, row-major; NaN where there is no depth."""
        depth = np.ascontiguousarray(self.shot.depth, dtype=np.float32)
        matrix, offset = self.map_to_camera(camera_pose)
        points = np.empty((depth.size, 3))
        back_project(depth, np.array(self.shot.left_camera.P, dtype=np.float64).reshape(3, 4),
                     np.array(matrix, dtype=np.float64), np.array(offset, dtype=np.float64).reshape(3),
                     points)
        return points

    def camera_in_map(self, camera_pose: ArrayLike) -> Vector3:
        """Where the (left) camera was, in the map frame."""
        matrix, offset = self.map_to_camera(camera_pose)
        return np.asarray(-np.asarray(matrix).T @ np.asarray(offset))

    def object_points(self, camera_pose: ArrayLike, spec: GridSpec,
                      config: SegmentationConfig = DEFAULT_SEGMENTATION
                      ) -> tuple[NDArray[np.float64], Segmentation]:
        """The measured points (K, 3) of the object in the map frame (the table and the
        backdrop left out: scene_segmentation.py, in the grid ``spec``), and the segmentation
        of every pixel."""
        points = self.pixel_points_in_map(camera_pose)
        segmentation = segment_object(points, spec, config)
        return points[segmentation.keep], segmentation

    def integrate_into(self, vision: VisionMap, camera_pose: ArrayLike,
                       config: SegmentationConfig = DEFAULT_SEGMENTATION
                       ) -> tuple[int, Segmentation]:
        """Add this shot to the vision local map, once: its object's pixels with the whole
        model, the others (table, backdrop: scene_segmentation.py) as free space only.
        Returns how many cells it updated, and the segmentation."""
        _, segmentation = self.object_points(camera_pose, vision.spec, config)
        return self.integrate_segmented(vision, camera_pose, segmentation), segmentation

    def integrate_segmented(self, vision: VisionMap, camera_pose: ArrayLike,
                            segmentation: Segmentation) -> int:
        """:meth:`integrate_into` with the shot's segmentation already made (by
        :meth:`object_points`); how many cells it updated."""
        depth = self.shot.depth
        return vision.integrate(depth, self.shot.left_camera.P, self.map_to_camera(camera_pose),
                                segmentation.keep.reshape(depth.shape))


class UnplacedShot(NamedTuple):
    """A shot that cannot be placed, and why (for one log line)."""

    shot: StereoShot
    reason: str


class ShotPlacer:
    """Places shots with the object poses of a :class:`Registrar` (its mode and max_gap).

    ``registrar`` None: the graph's mode is not known yet; shots are held (the newest
    :data:`MAX_HELD`), and so are the object poses (the newest :data:`MAX_EARLY_POSES`: a
    fast replay sends them all before the mode is known), until :meth:`use` gives one.
    """

    def __init__(self, registrar: Registrar | None):
        self.registrar = registrar
        self.held: list[StereoShot] = []
        self.object_poses = 0
        self._early_poses: deque[tuple[float, ArrayLike, ArrayLike]] = deque(
            maxlen=MAX_EARLY_POSES)

    @property
    def mode(self) -> str | None:
        return None if self.registrar is None else self.registrar.mode

    def use(self, registrar: Registrar) -> list[PlacedShot | UnplacedShot]:
        """The graph's mode is known: place the held shots with ``registrar`` and the
        object poses that came before it (ignored in static mode)."""
        self.registrar = registrar
        for t, position, quaternion in self._early_poses:
            registrar.add_object_pose(t, position, quaternion)
        self._early_poses.clear()
        return self._decide()

    def add_object_pose(self, t: float, position: ArrayLike, quaternion: ArrayLike
                        ) -> list[PlacedShot | UnplacedShot]:
        """One object pose (seconds, m, x y z w); the held shots it decides."""
        self.object_poses += 1
        if self.registrar is None:
            self._early_poses.append((t, position, quaternion))
            return []
        self.registrar.add_object_pose(t, position, quaternion)
        return self._decide()

    def add_shot(self, shot: StereoShot) -> list[PlacedShot | UnplacedShot]:
        """A new shot; what is decided now (it, or an older one given up for it)."""
        self.held.append(shot)
        decided: list[PlacedShot | UnplacedShot] = []
        while len(self.held) > MAX_HELD:
            old = self.held.pop(0)
            decided.append(UnplacedShot(old, "the graph's mode was not known yet"
                                        if self.registrar is None else
                                        'no object pose came at or after its stamp'))
        return decided + self._decide()

    def finish(self) -> list[PlacedShot | UnplacedShot]:
        """The input has ended: the held shots can no longer be placed."""
        decided: list[PlacedShot | UnplacedShot] = [
            UnplacedShot(shot, 'no object pose came at or after its stamp')
            for shot in self.held]
        self.held = []
        return decided

    def _decide(self) -> list[PlacedShot | UnplacedShot]:
        if self.registrar is None:
            return []
        decided: list[PlacedShot | UnplacedShot] = []
        still: list[StereoShot] = []
        for shot in self.held:
            where = self.registrar.object_pose_at(shot.stamp_ns * 1e-9)
            if where.state == 'later':
                still.append(shot)
            elif where.rotation is None or where.position is None:
                decided.append(UnplacedShot(shot, f'no object pose at its stamp '
                                                  f'({where.state.replace("_", " ")})'))
            else:
                decided.append(PlacedShot(shot, pose_vector(where.rotation, where.position)))
        self.held = still
        return decided


def waiting_advice(mode: str | None, seconds: float, object_poses: int, object_topic: str,
                   mode_source: str) -> tuple[str, str]:
    """Why a stereo pair has waited ``seconds`` to be placed on the object, and what to do:
    (a short reason, one log line). ``mode``: the graph's mode, None while it is not
    known; ``object_poses``: how many object poses came so far; ``mode_source``: where the
    mode is looked for, or where it came from."""
    waited = f'a stereo pair has waited {seconds:.0f} s to be placed on the object'
    if mode is None:
        return 'mode not known', (
            f"{waited}: the graph's mode is not known: {mode_source}. Start the "
            "registration node (it decides the mode), or set this node's mode parameter "
            'to static or tracked')
    if object_poses == 0:
        return 'no object pose', (
            f'{waited}: the graph is in tracked mode ({mode_source}) and no object pose has '
            f'come on {object_topic}. Is the object sensor connected and named object_name? '
            'If the object does not move, run the graph in static mode (registration_node '
            'mode:=static)')
    return 'object poses behind', (
        f'{waited}: the object poses on {object_topic} have not reached its stamp yet (the '
        'tracker and the camera stamp by different clocks? a tracker stream that stopped?)')
