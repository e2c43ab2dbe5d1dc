"""The stereo pairs of a bag through the stereo pipeline: what ``stereo_node`` would see.

:func:`read_bag_stereo` reads a bag's images, camera_infos and (tracked mode) the object
sensor's poses in time order through :class:`~inhand_common.bag_source.BagSource`, pairs
and checks them with :class:`~inhand_stereo.stereo_inputs.StereoInputs`, runs the
:class:`~inhand_stereo.stereo_pipeline.StereoPipeline` and places each shot on the object
with :class:`~inhand_stereo.shot_placement.ShotPlacer`: the same code as the node, so
``build_map``, ``render_map`` and ``map_metrics`` colour and judge a map as the graph does.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from inhand_common.bag_source import BagSource, BagTopic
from inhand_common.ros_names import station_pose_topic
from inhand_mapping.pose_cdr import decode_pose_stamped_many, stamp_seconds
from inhand_mapping.registration import Registrar
from inhand_stereo.shot_placement import PlacedShot, ShotPlacer, UnplacedShot
from inhand_stereo.stereo_config import StereoConfig
from inhand_stereo.stereo_inputs import StereoInputs, StereoPair, shot_from_messages
from inhand_stereo.stereo_pipeline import StereoPipeline

__all__ = ['IMAGE_TOPICS', 'INFO_TOPICS', 'BagStereo', 'has_stereo_pair', 'read_bag_stereo']

IMAGE_TOPICS = {'stereo/left/image_raw': 'left', 'stereo/right/image_raw': 'right'}
INFO_TOPICS = {'stereo/left/camera_info': 'left', 'stereo/right/camera_info': 'right'}
IMAGE_TYPE = 'sensor_msgs/msg/Image'
INFO_TYPE = 'sensor_msgs/msg/CameraInfo'


def has_stereo_pair(topics: Mapping[str, BagTopic]) -> bool:
    """Whether a bag's topics (``BagSource.topics``) hold both images of a stereo camera."""
    return all(topic in topics and topics[topic].msgtype == IMAGE_TYPE and topics[topic].count
               for topic in IMAGE_TOPICS)


@dataclass
class BagStereo:
    """What a bag's stereo pairs gave: the placed shots in time order, one line per pair
    that could not be used, and what stopped the reading early (a damaged bag)."""

    placed: list[PlacedShot] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)
    unpaired: int = 0        # images whose partner never came
    problem: str | None = None

    @property
    def first(self) -> PlacedShot | None:
        """The shot before the exploration (the paper's one shot), if any was usable."""
        return self.placed[0] if self.placed else None

    @property
    def last(self) -> PlacedShot | None:
        """The latest usable shot: the one the stereo node colours the map with."""
        return self.placed[-1] if self.placed else None


def read_bag_stereo(bag: Path, config: StereoConfig) -> BagStereo:
    """Every stereo pair of ``bag`` through the pipeline with ``config`` (its disparity
    parameters, ``mode``, ``object_name``, ``max_gap``). ValueError for a bag without
    a stereo pair or whose stereo topics have another type."""
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    result = BagStereo()
    pipeline = StereoPipeline(config.disparity, point_step=config.point_step)
    inputs: StereoInputs[Any, Any] = StereoInputs()
    placer = ShotPlacer(Registrar(config.mode, config.max_gap))
    object_topic = station_pose_topic(config.object_name) if config.mode == 'tracked' else None

    def decided(outcomes: list[PlacedShot | UnplacedShot]) -> None:
        for outcome in outcomes:
            if isinstance(outcome, PlacedShot):
                result.placed.append(outcome)
            else:
                result.refused.append(f'stereo pair at {outcome.shot.stamp_ns * 1e-9:.3f} s: '
                                      f'{outcome.reason}; the images cannot be placed on the '
                                      'object')

    def process(pair: StereoPair[Any, Any] | None) -> None:
        if pair is None:
            return
        try:
            shot = shot_from_messages(pipeline, pair)
        except ValueError as error:
            result.refused.append(f'stereo pair at {pair.stamp_ns * 1e-9:.3f} s: {error}')
            return
        decided(placer.add_shot(shot))

    with BagSource(bag) as source:
        if not has_stereo_pair(source.topics):
            raise ValueError(f'{bag}: no stereo pair (needs {" and ".join(IMAGE_TOPICS)} '
                             f'of type {IMAGE_TYPE})')
        for topic in INFO_TOPICS:
            if topic in source.topics and source.topics[topic].msgtype != INFO_TYPE:
                raise ValueError(f'{bag}: {topic} is {source.topics[topic].msgtype}, expected '
                                 f'{INFO_TYPE}')
        topics = set(IMAGE_TOPICS) | (set(INFO_TOPICS) & set(source.topics))
        if object_topic is not None and object_topic in source.topics:
            topics.add(object_topic)
        for topic, _, raw in source.messages(topics):
            if topic == object_topic:
                stamps, _, poses = decode_pose_stamped_many([raw])
                decided(placer.add_object_pose(float(stamp_seconds(stamps)[0]), poses[0, :3],
                                               poses[0, 3:]))
            elif topic in INFO_TOPICS:
                process(inputs.add_info(INFO_TOPICS[topic],
                                        store.deserialize_cdr(raw, INFO_TYPE)))
            else:
                image = store.deserialize_cdr(raw, IMAGE_TYPE)
                stamp_ns = image.header.stamp.sec * 1_000_000_000 + image.header.stamp.nanosec
                process(inputs.add_image(IMAGE_TOPICS[topic], stamp_ns, image))
        result.problem = source.problem
    if inputs.held is not None:
        result.refused.append(f'stereo pair at {inputs.held[0] * 1e-9:.3f} s: no camera_info '
                              f'for the {" and ".join(inputs.missing_infos())} camera')
    decided(placer.finish())
    result.unpaired = inputs.pairs.dropped + inputs.pairs.waiting
    return result
