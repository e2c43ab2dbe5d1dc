"""A bag of the driver's poses through the mapping library: what the nodes would build.

:class:`BagRegistration` registers a bag's fingertips exactly as ``registration_node``
publishes them (same :class:`~inhand_mapping.registration.Registrar`, same parameters,
through the topic's float32 layout); :func:`build_map_from_bag` integrates them into the
grid as ``occupancy_node`` does. No DDS: ``build_map`` and the metrics tools use this, and
the tests check that the nodes over DDS give the same map bit for bit.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from inhand_common.bag_source import BagSource, Progress
from inhand_mapping.cloud_layouts import pack_registered, unpack_registered
from inhand_mapping.mapping_config import OccupancyConfig, RegistrationConfig
from inhand_mapping.pose_cdr import decode_pose_stamped_many, stamp_seconds
from inhand_mapping.registration import HISTORY_SECONDS

__all__ = ['BagMessages', 'BagRegistration', 'build_map_from_bag']

CHUNK = 4096  # messages decoded and registered together
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'


class BagMessages:
    """The driver's pose topics of a bag, raw, in time order (over :class:`BagSource`).

    Refuses a bag that lacks one of ``topics`` or holds it with another type than
    PoseStamped; ``problem`` says what stopped the reading early (None if the bag was read
    to its end, e.g. a truncated MCAP read up to the cut). ``advice`` per topic: what to do
    when that one is missing, added to the refusal.
    """

    def __init__(self, bag: Path, topics: set[str], advice: dict[str, str] | None = None):
        self.source = BagSource(bag)
        self.bag, self.topics = Path(bag), topics
        self.advice = advice or {}
        self.total = 0

    def __enter__(self) -> BagMessages:
        self.source.__enter__()
        available = self.source.topics
        missing = sorted(self.topics - set(available))
        if missing:
            self.source.__exit__(None, None, None)
            advice = ''.join(f'. {self.advice[topic]}' for topic in missing if topic in self.advice)
            raise ValueError(f'{self.bag}: no {", ".join(missing)} in this bag; it has '
                             f'{sorted(available) or "no topics"}{advice}')
        for topic in sorted(self.topics):
            if available[topic].msgtype != POSE_STAMPED:
                self.source.__exit__(None, None, None)
                raise ValueError(f'{self.bag}: {topic} is {available[topic].msgtype}, '
                                 'expected geometry_msgs/msg/PoseStamped')
        self.total = sum(available[topic].count for topic in self.topics)
        return self

    @property
    def problem(self) -> str | None:
        return self.source.problem

    @property
    def checked(self) -> list[str]:
        """What the integrity check on open could check, per file (MCAP CRCs, sqlite3
        quick_check); damage it found is in ``problem``."""
        return self.source.checked

    @property
    def start_ns(self) -> int:
        return self.source.start_ns

    @property
    def end_ns(self) -> int:
        return self.source.end_ns

    def __iter__(self):
        return self.source.messages(self.topics)

    def __exit__(self, *exc) -> None:
        self.source.__exit__(*exc)


class BagRegistration:
    """The registered fingertip points of a bag, batch by batch, exactly as the
    registration node would publish them (same Registrar, same parameters, through the
    topic's float32 layout). Also keeps the raw fingertip positions when asked, and a
    report of what was read.
    """

    def __init__(self, bag: Path, config: RegistrationConfig, progress: bool = False,
                 keep_raw: bool = False):
        self.bag = bag
        self.config = config
        self.progress = progress
        self.registrar = config.make_registrar()
        self.topics = config.finger_topics
        self.object_topic = config.object_topic
        self.report = {'messages': 0, 'truncated': None, 'bag_start': None, 'bag_end': None,
                       'checked': []}
        self.raw: list[tuple[np.ndarray, np.ndarray]] | None = [] if keep_raw else None

    def __iter__(self):
        wanted = set(self.topics) | ({self.object_topic} if self.object_topic else set())
        report = self.report
        chunk: list[tuple[str, bytes]] = []
        # the common case: a session of an object that stood still, read as tracked
        advice = {self.object_topic: 'Without an object pose the object must stand still: map '
                  'it in static mode (--config config/mapping_static.yaml, or mode:=static on '
                  'the registration node)'} if self.object_topic else {}
        with BagMessages(self.bag, wanted, advice) as source:
            bar = Progress('build_map', source.start_ns, source.end_ns) if self.progress \
                else None
            started = time.monotonic()
            for topic, timestamp, raw in source:
                chunk.append((topic, raw))
                report['bag_start'] = report['bag_start'] or timestamp
                report['bag_end'] = timestamp
                report['messages'] += 1
                if len(chunk) >= CHUNK:
                    yield from self._process(chunk)
                    chunk = []
                    if bar:
                        bar.update(timestamp, report['messages'], source.start_ns,
                                   time.monotonic() - started)
            yield from self._process(chunk)
            if bar:
                bar.update(report['bag_end'] or source.start_ns, report['messages'],
                           source.start_ns, time.monotonic() - started, force=True)
                bar.close()
            report['truncated'] = source.problem
            report['checked'] = list(source.checked)
            report['expected_messages'] = source.total
        yield self._as_published(*self.registrar.finish())

    def _process(self, chunk: list[tuple[str, bytes]]):
        if not chunk:
            return
        stamps, _, poses = decode_pose_stamped_many([raw for _, raw in chunk])
        times = stamp_seconds(stamps)
        is_object = np.array([topic == self.object_topic for topic, _ in chunk])
        finger_ids = np.array([self.topics.get(topic, -1) for topic, _ in chunk])
        if self.raw is not None:
            self.raw.append((poses[~is_object, :3], finger_ids[~is_object]))
        # Feed the registrar in short slices of sensor time, object poses before
        # fingertips, the way a live stream interleaves them.
        slice_ids = np.floor(times / (HISTORY_SECONDS / 2.0))
        for slice_id in np.unique(slice_ids):
            part = slice_ids == slice_id
            for k in np.flatnonzero(part & is_object):
                self.registrar.add_object_pose(times[k], poses[k, :3], poses[k, 3:])
            tips = part & ~is_object
            if tips.any():
                self.registrar.add_fingertips(times[tips], poses[tips, :3], finger_ids[tips],
                                              quaternions=poses[tips, 3:])
            yield self._as_published(*self.registrar.drain())

    @staticmethod
    def _as_published(points, times, finger_ids):
        # Through the topic's float32 layout, so the map equals the node's to the bit.
        return unpack_registered(pack_registered(points, times, finger_ids))


def build_map_from_bag(bag: Path, registration: RegistrationConfig, occupancy: OccupancyConfig,
                       progress: bool = True) -> dict[str, Any]:
    """Run the bag through registration and occupancy; returns the pieces and a report."""
    grid = occupancy.make_grid()
    registered = BagRegistration(bag, registration, progress)
    for points, times, fingers in registered:
        grid.integrate(points, times, fingers)
    grid.flush()   # the samples held back for their dwell weights: the bag has ended
    return {'grid': grid, 'registrar': registered.registrar, 'report': registered.report}
