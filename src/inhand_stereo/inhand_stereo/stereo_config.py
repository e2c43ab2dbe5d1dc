"""Parameters of the stereo node, shared with the tools that process a bag's stereo pairs.

One table (:data:`STEREO_PARAMETERS`): stereo_image_proc's disparity parameters, the camera's
pose in the tracker frame, the density of ``stereo/points``, and the registration and grid
parameters the node shares with the mapping nodes (same names, same checks: one YAML value
serves all of them). :class:`StereoConfig` is what the node and ``build_map`` build from it,
so a bag processed offline is coloured as the node would colour it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from inhand_common.frame_names import FrameNames
from inhand_common.parameters import ParameterError, ParamSpec, load_yaml_parameters, validate
from inhand_mapping.mapping_config import OCCUPANCY_PARAMETERS, REGISTRATION_PARAMETERS
from inhand_mapping.occupancy import GridSpec
from inhand_stereo.disparity import DISPARITY_PARAMETERS, DisparityConfig
from inhand_stereo.scene_segmentation import SegmentationConfig
from inhand_stereo.vision_model import NOISE_MODELS, UPDATES, VisionModel

__all__ = ['FOLLOW_REGISTRATION', 'IDENTITY_POSE', 'STEREO_NODE', 'STEREO_PARAMETERS', 'StereoConfig',
           'camera_pose_from', 'load_stereo_config']

STEREO_NODE = 'stereo_node'
IDENTITY_POSE = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
# The stereo node's default mode: the registration node's, so the graph has one mode. The
# bag tools take it from the registration's parameters (bag_stereo_shot.py).
FOLLOW_REGISTRATION = 'follow'


def _shared(table: tuple[ParamSpec, ...], *names: str) -> list[ParamSpec]:
    """The specs of the other nodes' parameters this node shares (same meaning, same
    checks: one YAML value can serve both)."""
    by_name = {spec.name: spec for spec in table}
    return [by_name[name] for name in names]


STEREO_PARAMETERS: tuple[ParamSpec, ...] = (
    *DISPARITY_PARAMETERS,
    ParamSpec('camera_pose', list(IDENTITY_POSE), 'Pose of stereo_left_optical in '
              'polhemus_source: [x, y, z, qx, qy, qz, qw] (m; a point p in the camera frame is '
              'R p + t in the tracker frame); calibrate_camera_tracker writes it',
              minimum=-10.0, maximum=10.0, length=7),
    ParamSpec('point_step', 2, 'stereo/points takes every point_step-th pixel in each '
              'direction (1: all)', minimum=1, maximum=16),
    # The vision sensor model (paper eqs. 5-7; vision_model.py) and the vision local map.
    ParamSpec('vision_epsilon', 0.01, 'Width (m) of the ramp of eq. 6 from free to occupied '
              'around the measured surface', minimum=0.0005, maximum=0.2),
    ParamSpec('vision_tau', 0.005, 'Decay length (m) of eq. 7\'s spread away from the band',
              minimum=0.0001, maximum=0.2),
    ParamSpec('vision_sigma_min', 0.0, 'Range noise (m) of the stereo camera at range 0',
              minimum=0.0, maximum=0.05),
    ParamSpec('vision_zeta', 0.0027, 'Growth of the range noise with range: m per m '
              '(linear) or 1/m (stereo: sigma_min + zeta d^2)', minimum=0.0, maximum=1.0),
    ParamSpec('vision_noise', 'linear', 'Range noise model: linear (the paper: sigma_min + '
              'zeta d) or stereo (sigma_min + zeta d^2)', choices=NOISE_MODELS),
    ParamSpec('vision_update', 'mass', 'A belief over the occupancy value as a probability: '
              'mass (its mass above 1/2) or mean (its mean on [0, 1])', choices=UPDATES),
    ParamSpec('vision_spread_window', 5, 'Pixels: where the depth\'s local spread over this '
              'window exceeds the noise model, it is the noise (weak texture, depth edges); '
              '0: off; odd, at most 31', choices=(0, *range(3, 32, 2))),
    ParamSpec('plane_tolerance', 0.004, 'Points within this distance (m) of a support plane '
              '(the table) lie on it and are not the object', minimum=0.0005, maximum=0.05),
    ParamSpec('support_fraction', 0.2, 'A plane holding this share of the workspace\'s '
              'points, with the rest on one side, is a support and is removed',
              minimum=0.01, maximum=1.0),
    ParamSpec('mode', FOLLOW_REGISTRATION, "follow: the graph's mode, the registration "
              "node's (asked from the node that publishes registration/object_frame); "
              'static or tracked: this mode, whatever the registration node says (a warning '
              'when they differ)', choices=(FOLLOW_REGISTRATION, 'static', 'tracked')),
    *_shared(REGISTRATION_PARAMETERS, 'object_name', 'max_gap', 'frame_prefix',
             'tracker_frame', 'map_frame'),
    *_shared(OCCUPANCY_PARAMETERS, 'workspace_size', 'resolution', 'workspace_centre',
             'clamp_min', 'clamp_max', 'occupied_threshold'),
)


def camera_pose_from(values: Iterable[float]) -> NDArray[np.float64]:
    """The camera_pose parameter, its quaternion normalised; ParameterError if it is none."""
    pose = np.asarray(list(values), dtype=np.float64)
    norm = float(np.linalg.norm(pose[3:]))
    if not norm > 1e-6:
        raise ParameterError([f"parameter 'camera_pose' = {pose.tolist()}: the quaternion "
                              '(last four values) must not be zero'])
    pose[3:] /= norm
    return pose


@dataclass(frozen=True, eq=False)
class StereoConfig:
    """The stereo node's checked parameters."""

    disparity: DisparityConfig
    camera_pose: NDArray[np.float64]     # (7,) x y z qx qy qz qw, quaternion normalised
    point_step: int
    mode: str                            # FOLLOW_REGISTRATION, 'static' or 'tracked'
    object_name: str
    max_gap: float
    grid: GridSpec                       # the occupancy grid (the vision map's too)
    vision: VisionModel
    segmentation: SegmentationConfig
    camera_pose_given: bool = True       # False: no file set camera_pose (no calibration)
    # the occupancy node's: an occupied cell whose surface layer is under it was rescued by
    # the cell judge (texture.texture_cells' ``rescued``)
    occupied_threshold: float = 0.8
    frames: FrameNames = field(default_factory=FrameNames)

    @property
    def resolution(self) -> float:
        return self.grid.resolution

    @property
    def clamp(self) -> tuple[float, float]:
        """The maps' probability clamps (clamp_min, clamp_max): one observation's too."""
        return self.vision.p_free, self.vision.p_occupied

    @classmethod
    def from_parameters(cls, values: Mapping[str, Any], camera_pose_given: bool = True
                        ) -> StereoConfig:
        """From the validated table (``validate(STEREO_PARAMETERS, ...)`` or the node's
        declared values). ParameterError for a camera_pose without a rotation."""
        try:
            grid = GridSpec(float(values['workspace_size']), float(values['resolution']),
                            tuple(float(v) for v in values['workspace_centre']))
            vision = VisionModel(epsilon=float(values['vision_epsilon']),
                                 tau=float(values['vision_tau']),
                                 sigma_min=float(values['vision_sigma_min']),
                                 zeta=float(values['vision_zeta']),
                                 noise=values['vision_noise'], update=values['vision_update'],
                                 p_free=float(values['clamp_min']),
                                 p_occupied=float(values['clamp_max']),
                                 spread_window=int(values['vision_spread_window']))
        except ValueError as error:  # a combination the table cannot refuse on its own
            raise ParameterError([f"stereo_node parameters 'workspace_*', 'resolution', "
                                  f"'vision_*', 'clamp_min', 'clamp_max': {error}"]) from None
        problems: list[str] = []
        frames = FrameNames.from_parameters(values, problems)
        if problems:
            raise ParameterError(problems)
        return cls(disparity=DisparityConfig.from_parameters(
                       {spec.name: values[spec.name] for spec in DISPARITY_PARAMETERS}),
                   camera_pose=camera_pose_from(values['camera_pose']),
                   point_step=int(values['point_step']), mode=str(values['mode']),
                   object_name=str(values['object_name']), max_gap=float(values['max_gap']),
                   grid=grid, vision=vision,
                   segmentation=SegmentationConfig(
                       plane_tolerance=float(values['plane_tolerance']),
                       support_fraction=float(values['support_fraction'])),
                   camera_pose_given=camera_pose_given, frames=frames,
                   occupied_threshold=float(values['occupied_threshold']))


def load_stereo_config(configs: Iterable[str], overrides: Mapping[str, Any] | None = None
                       ) -> StereoConfig:
    """The stereo node's configuration from the ``stereo_node`` sections of ROS parameter
    files (later files override earlier ones, as repeated ``--params-file``), then
    ``overrides`` (only this table's names are taken). ``camera_pose_given`` says whether
    any of them set ``camera_pose``."""
    values: dict[str, Any] = {}
    for config in configs:
        values.update(load_yaml_parameters(config, STEREO_NODE))
    known = {spec.name for spec in STEREO_PARAMETERS}
    values.update({name: value for name, value in (overrides or {}).items() if name in known})
    return StereoConfig.from_parameters(validate(STEREO_PARAMETERS, values),
                                        camera_pose_given='camera_pose' in values)
