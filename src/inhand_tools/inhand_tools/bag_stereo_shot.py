"""The stereo shot of a session bag, placed as the map of that bag: for the offline tools.

``build_map`` colours a bag's map with it, ``render_map`` draws its points and the coloured
map (the paper's figs. 6-7) and ``map_metrics`` judges it against the truth. The rig's
parameters come from the ``stereo_node`` sections of the same ROS parameter files the
nodes get (``config/stereo.yaml``: the disparity settings and ``camera_pose``); where the
shot is placed follows the map's registration (mode, object sensor, max_gap) and the
texture its cells, so the three tools and the stereo node see the same thing.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from inhand_common.bag_source import BagSource
from inhand_mapping.cloud_layouts import vision_cells, vision_log_odds
from inhand_mapping.mapping_config import OccupancyConfig, RegistrationConfig, load_parameters
from inhand_stereo.bag_stereo import BagStereo, has_stereo_pair, read_bag_stereo
from inhand_stereo.shot_placement import PlacedShot
from inhand_stereo.stereo_config import StereoConfig, load_stereo_config
from inhand_stereo.texture import CellTexture
from inhand_stereo.vision_model import VisionMap

__all__ = ['BagShot', 'bag_has_stereo_pair', 'read_bag_shot', 'read_configured_shot',
           'stereo_config_for_map']


def stereo_config_for_map(configs: Sequence[str], registration: RegistrationConfig,
                          occupancy: OccupancyConfig,
                          overrides: Mapping[str, Any] | None = None) -> StereoConfig:
    """The stereo node's parameters from ``configs``' ``stereo_node`` sections, placed as the
    map is: the registration's mode, object sensor and max_gap, the occupancy grid and its
    clamps (the node shares those parameters with the mapping nodes)."""
    stereo = load_stereo_config(configs, overrides)
    return replace(stereo, mode=registration.mode, object_name=registration.object_name,
                   max_gap=registration.max_gap, grid=occupancy.grid,
                   vision=replace(stereo.vision, p_free=occupancy.model.clamp_min,
                                  p_occupied=occupancy.model.clamp_max))


def bag_has_stereo_pair(bag: Path) -> bool:
    """Whether the bag holds the images of a stereo camera."""
    with BagSource(Path(bag)) as source:
        return has_stereo_pair(source.topics)


@dataclass
class BagShot:
    """The first usable stereo shot of a bag (the one before the exploration, which the
    simulator's truth describes) with the configuration it was processed with, and every
    pair (``pairs.placed``; ``pairs.refused``: one line per unusable pair)."""

    placed: PlacedShot
    config: StereoConfig
    pairs: BagStereo

    @property
    def stamp(self) -> float:
        """Seconds (the images' stamp)."""
        return self.placed.shot.stamp_ns * 1e-9

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """The shot's 3D points in the map frame (N, 3) float32 and their RGB (N, 3) uint8:
        what ``stereo/points`` carries."""
        return self.placed.points_in_map(self.config.camera_pose), self.placed.shot.colours

    def object_points(self) -> tuple[np.ndarray, np.ndarray]:
        """The object's measured points (K, 3) in the map frame, of every usable pair (the
        table and the backdrop left out, as the vision map leaves them out), and where the
        camera was for each (K, 3)."""
        points, cameras = [np.empty((0, 3))], [np.empty((0, 3))]
        for placed in self.pairs.placed:
            seen, _ = placed.object_points(self.config.camera_pose, self.config.grid,
                                           self.config.segmentation)
            points.append(seen)
            cameras.append(np.broadcast_to(placed.camera_in_map(self.config.camera_pose),
                                           seen.shape))
        return np.concatenate(points), np.concatenate(cameras)

    @property
    def latest(self) -> PlacedShot:
        """The bag's last usable pair: the one the stereo node colours the map with (the
        same as ``placed`` in a bag with one pair)."""
        latest = self.pairs.last
        assert latest is not None   # a BagShot is made only for a bag with a usable pair
        return latest

    @property
    def texture_stamp(self) -> float:
        """Seconds: the stamp of the pair :meth:`texture` colours with."""
        return self.latest.shot.stamp_ns * 1e-9

    def texture(self, centres: np.ndarray, rescued: np.ndarray | None = None) -> CellTexture:
        """Colours of occupied cells (map-frame centres; ``rescued``: those the cell judge
        rescued), as ``occupancy/textured``: from :attr:`latest`, as the stereo node colours
        with the latest pair it placed."""
        return self.latest.texture(centres, self.config.resolution, self.config.camera_pose,
                                   rescued)

    def vision_log_odds(self) -> np.ndarray:
        """The vision local map of every usable pair of the bag (each integrated once), as
        the occupancy node receives it: through ``vision/cloud``'s float32 layout."""
        vision = VisionMap(self.config.grid, self.config.vision, self.config.clamp)
        for placed in self.pairs.placed:
            placed.integrate_into(vision, self.config.camera_pose, self.config.segmentation)
        log_odds, _ = vision_log_odds(vision_cells(vision.spec, vision.log_odds), vision.spec)
        return log_odds


def read_bag_shot(bag: Path, config: StereoConfig) -> tuple[BagShot | None, str | None]:
    """(the bag's first usable shot, None) or (None, why there is none); why is None for a
    bag without images (nothing to say)."""
    if not bag_has_stereo_pair(bag):
        return None, None
    if not config.camera_pose_given:
        return None, ('the bag holds a stereo pair, but no stereo_node camera_pose was given '
                      '(e.g. --config config/stereo.yaml)')
    pairs = read_bag_stereo(Path(bag), config)
    if pairs.first is None:
        reasons = '; '.join(pairs.refused) or 'no complete pair'
        return None, f'no usable stereo pair ({reasons})'
    return BagShot(pairs.first, config, pairs), None


def read_configured_shot(bag: Path, configs: Sequence[str],
                         overrides: Mapping[str, Any] | None = None
                         ) -> tuple[BagShot | None, str | None]:
    """:func:`read_bag_shot` with the parameters of the ROS parameter files ``configs``: their
    ``stereo_node`` sections, placed by their registration and occupancy sections
    (``overrides`` on those, e.g. the map's ``mode``)."""
    registration, occupancy = load_parameters(list(configs), dict(overrides or {}))
    return read_bag_shot(Path(bag), stereo_config_for_map(configs, registration, occupancy))
