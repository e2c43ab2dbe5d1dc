"""The fingertip points of a session bag: as recorded (tracker frame) and registered into
the map's frame exactly as ``build_map`` registers them; which frame a bag's map is in.

Every bag read goes through :class:`~inhand_common.bag_source.BagSource` (directly, or
through ``inhand_mapping.bag_mapping``), so a truncated MCAP is read up to the cut.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from inhand_common.bag_source import BagSource
from inhand_common.ros_names import OBJECT_POSE_TOPIC

__all__ = ['BagPoints', 'bag_mode_for_frame', 'bag_topics', 'map_frame_of_bag',
           'read_bag_points']


@dataclass
class BagPoints:
    """Fingertip positions of a bag: raw (tracker frame) and registered (map frame)."""

    raw: np.ndarray          # (n, 3) tracker frame
    raw_fingers: np.ndarray  # (n,) index into finger_names
    registered: np.ndarray   # (m, 3) map frame
    registered_fingers: np.ndarray
    registered_times: np.ndarray
    finger_names: list
    mode: str
    stats: object = None
    problem: str | None = None   # a truncated or damaged bag: what was left out (one line)


def read_bag_points(bag, mode: str, config: str | None = None) -> BagPoints:
    """Raw and registered fingertip positions, registered exactly as ``build_map`` does
    (same parameters, same Registrar, same feeding order), in ``mode`` static/tracked."""
    from inhand_mapping.bag_mapping import BagRegistration
    from inhand_mapping.mapping_config import load_parameters
    bag = Path(bag)
    if not bag.exists():
        raise ValueError(f'{bag}: no such bag')
    registration_config, _ = load_parameters(config, {'mode': mode})
    registration = BagRegistration(bag, registration_config, keep_raw=True)
    batches = [batch for batch in registration if len(batch[0])]
    if batches:
        points, times, finger_ids = (np.concatenate([b[k] for b in batches]) for k in range(3))
    else:
        points, times, finger_ids = np.empty((0, 3)), np.empty(0), np.empty(0, np.int64)
    raw = registration.raw
    raw_points = np.concatenate([r[0] for r in raw]) if raw else np.empty((0, 3))
    raw_fingers = (np.concatenate([r[1] for r in raw]).astype(np.int64) if raw
                   else np.empty(0, np.int64))
    problem = registration.report['truncated']
    if problem:     # every tool that reads points from a bag says so, in one line
        print(f'warning: {bag} is truncated or damaged: {problem}', file=sys.stderr)
    return BagPoints(raw_points, raw_fingers, points, finger_ids.astype(np.int64), times,
                     list(registration_config.finger_names), mode,
                     registration.registrar.stats, problem)


def bag_topics(bag) -> dict[str, str]:
    """Topic name (no leading slash) -> message type of every topic in a bag.

    BagError (a ValueError) for a bag that cannot be opened."""
    with BagSource(Path(bag)) as source:
        return {name: topic.msgtype for name, topic in source.topics.items()}


def bag_mode_for_frame(frame: str) -> str:
    """Registration mode of the map frame: tracked maps are in the object frame."""
    return 'tracked' if frame == 'object' else 'static'


def map_frame_of_bag(bag) -> str:
    """The frame a map of this bag is in: ``object`` if the bag has an object sensor
    (tracked registration), else ``tracker``."""
    return 'object' if OBJECT_POSE_TOPIC in bag_topics(bag) else 'tracker'
