"""Parameters of the stereo node, shared with the tools that process a bag's stereo pairs.

One table (:data:`STEREO_PARAMETERS`): stereo_image_proc's disparity parameters, the camera's
pose in the tracker frame, the density of ``stereo/points``, and the registration and grid
parameters the node shares with the mapping nodes (same names, same checks: one YAML value
serves all of them). :class:`StereoConfig` is what the node and ``build_map`` build from it,
so a bag processed offline is coloured as the node would colour it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from inhand_common.parameters import ParameterError, ParamSpec, load_yaml_parameters, validate
from inhand_mapping.mapping_config import OCCUPANCY_PARAMETERS, REGISTRATION_PARAMETERS
from inhand_stereo.disparity import DISPARITY_PARAMETERS, DisparityConfig

__all__ = ['IDENTITY_POSE', 'STEREO_NODE', 'STEREO_PARAMETERS', 'StereoConfig',
           'camera_pose_from', 'load_stereo_config']

STEREO_NODE = 'stereo_node'
IDENTITY_POSE = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


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
    *_shared(REGISTRATION_PARAMETERS, 'mode', 'object_name', 'max_gap'),
    *_shared(OCCUPANCY_PARAMETERS, 'resolution'),
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
    mode: str
    object_name: str
    max_gap: float
    resolution: float
    camera_pose_given: bool = True       # False: no file set camera_pose (no calibration)

    @classmethod
    def from_parameters(cls, values: Mapping[str, Any], camera_pose_given: bool = True
                        ) -> StereoConfig:
        """From the validated table (``validate(STEREO_PARAMETERS, ...)`` or the node's
        declared values). ParameterError for a camera_pose without a rotation."""
        return cls(disparity=DisparityConfig.from_parameters(
                       {spec.name: values[spec.name] for spec in DISPARITY_PARAMETERS}),
                   camera_pose=camera_pose_from(values['camera_pose']),
                   point_step=int(values['point_step']), mode=str(values['mode']),
                   object_name=str(values['object_name']), max_gap=float(values['max_gap']),
                   resolution=float(values['resolution']),
                   camera_pose_given=camera_pose_given)


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
