"""Where the emulated Liberty's poses come from: a built-in motion, a text file, or a bag.

A motion source answers one question, ``sample(t)``: the pose of every station ``t``
seconds after streaming started, in the source frame, SI units (metres, quaternion
x, y, z, w). Recorded sources play back with their recorded timing, hold the last pose
between samples, and loop.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from inhand_common.bag_source import BagSource
from inhand_common.ros_names import station_pose_topic
from inhand_common.rotations import (
    euler_zyx_to_quaternion,
    quaternion_multiply,
    quaternion_normalize,
    rotate_vectors,
)

__all__ = [
    'BuiltinMotion',
    'MotionSource',
    'RecordedMotion',
    'load_plhm_text',
    'load_pose_bag',
    'open_motion_source',
]

Pose = tuple[np.ndarray, np.ndarray]


class MotionSource(Protocol):
    stations: tuple[int, ...]

    def sample(self, t: float) -> dict[int, Pose]:
        """Pose of each station at ``t`` seconds (position m, quaternion x, y, z, w)."""


class BuiltinMotion:
    """Three fingertips stroking a 4 cm sphere held 25 cm in front of the transmitter.

    Station 4 (the object sensor) sways +-15 degrees about its vertical axis and drifts
    +-2 cm, and the fingertips ride along with it, so registration has something to undo.
    Deterministic in ``t``: the same time gives the same poses.
    """

    def __init__(self, stations: Sequence[int] = (1, 2, 3, 4), radius: float = 0.04,
                 centre: Sequence[float] = (0.25, 0.0, 0.05)):
        self.stations = tuple(stations)
        self.radius = radius
        self.centre = np.asarray(centre, dtype=float)

    def object_pose(self, t: float) -> Pose:
        sway = math.radians(15.0) * math.sin(2 * math.pi * 0.1 * t)
        position = self.centre + 0.02 * np.array([math.sin(2 * math.pi * 0.05 * t),
                                                  math.sin(2 * math.pi * 0.07 * t), 0.0])
        return position, euler_zyx_to_quaternion(sway, 0.0, 0.0)

    def sample(self, t: float) -> dict[int, Pose]:
        object_position, object_q = self.object_pose(t)
        poses: dict[int, Pose] = {}
        for index, station in enumerate(self.stations):
            if station == self.stations[-1] and len(self.stations) > 1:
                poses[station] = (object_position, object_q)
                continue
            # Each finger follows its own great circle, phase-shifted, in the object frame.
            phase = 2 * math.pi * index / 3.0
            polar = math.pi * (0.5 + 0.4 * math.sin(2 * math.pi * 0.13 * t + phase))
            azimuth = 2 * math.pi * 0.2 * t + phase
            local = self.radius * np.array([math.sin(polar) * math.cos(azimuth),
                                            math.sin(polar) * math.sin(azimuth),
                                            math.cos(polar)])
            finger_q = quaternion_multiply(object_q, euler_zyx_to_quaternion(azimuth, polar, 0.0))
            poses[station] = (object_position + rotate_vectors(object_q, local),
                              quaternion_normalize(finger_q))
        return poses


@dataclass
class RecordedMotion:
    """Poses recorded at ``times`` (s, from 0): ``positions[frame, k]``, ``quaternions[frame, k]``
    for ``stations[k]``. Between samples the last pose holds; past the end it loops."""

    stations: tuple[int, ...]
    times: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    loop: bool = True
    malformed_lines: int = 0

    def __post_init__(self) -> None:
        if len(self.times) == 0:
            raise ValueError('a recorded motion needs at least one frame')
        # Loop period: the recording's span plus one typical frame interval.
        step = float(np.median(np.diff(self.times))) if len(self.times) > 1 else 1.0
        self.period = float(self.times[-1] - self.times[0]) + step

    @property
    def duration(self) -> float:
        return self.period

    def sample(self, t: float) -> dict[int, Pose]:
        if self.loop:
            t = self.times[0] + (t % self.period)
        index = max(int(np.searchsorted(self.times, t, side='right')) - 1, 0)
        return {station: (self.positions[index, k], self.quaternions[index, k])
                for k, station in enumerate(self.stations)}


def _forward_fill(frames: list[dict[int, Pose]], stations: Sequence[int]) -> tuple[np.ndarray,
                                                                                   np.ndarray]:
    """Dense (frames, stations) arrays; a station missing from a frame keeps its last pose."""
    positions = np.zeros((len(frames), len(stations), 3))
    quaternions = np.tile([0.0, 0.0, 0.0, 1.0], (len(frames), len(stations), 1))
    last: dict[int, Pose] = {}
    for i, frame in enumerate(frames):
        last.update(frame)
        for k, station in enumerate(stations):
            if station in last:
                positions[i, k], quaternions[i, k] = last[station]
    return positions, quaternions


def load_plhm_text(path: str | Path, loop: bool = True) -> RecordedMotion:
    """A text recording, one station per line: ``station, x, y, z, az, el, roll, time``.

    Positions in centimetres, Euler angles in degrees (Z-Y-X), time in milliseconds: the
    format of the real recordings in ``shared/data/liberty_recordings``. Lines with the
    same time form one frame. Malformed lines (a recording cut off mid-line) are skipped and
    counted in ``malformed_lines``.
    """
    rows, malformed = [], 0
    with open(path, encoding='utf-8', errors='replace') as stream:
        for line in stream:
            fields = line.split(',')
            try:
                row = [float(f) for f in fields[:8]]
            except ValueError:
                row = []
            if len(row) == 8 and all(math.isfinite(v) for v in row):
                rows.append(row)
            elif line.strip():
                malformed += 1  # e.g. a recording cut off mid-line
    if not rows:
        raise ValueError(f'{path}: no lines of the form "station, x, y, z, az, el, roll, '
                         f'time" ({malformed} malformed)')
    raw = np.asarray(rows)
    stations = tuple(sorted({int(s) for s in raw[:, 0]}))
    quaternions = euler_zyx_to_quaternion(*np.radians(raw[:, 4:7]).T)
    frames: list[dict[int, Pose]] = []
    times: list[float] = []
    for row, q in zip(raw, quaternions):
        time_s = row[7] / 1000.0
        if not times or time_s != times[-1]:
            times.append(time_s)
            frames.append({})
        frames[-1][int(row[0])] = (row[1:4] * 0.01, q)
    positions, quats = _forward_fill(frames, stations)
    times_arr = np.asarray(times) - times[0]
    return RecordedMotion(stations, times_arr, positions, quats, loop, malformed)


def load_pose_bag(path: str | Path, station_by_name: Mapping[str, int],
                  loop: bool = True) -> RecordedMotion:
    """Poses from a rosbag2 bag (MCAP or sqlite3) holding ``polhemus/<name>/pose`` topics.

    Messages with the same header stamp form one tracker frame, as the driver publishes.
    """
    from rosbags.typesys import Stores, get_typestore

    wanted = {station_pose_topic(name): station for name, station in station_by_name.items()}
    by_stamp: dict[int, dict[int, Pose]] = {}
    store = get_typestore(Stores.ROS2_JAZZY)
    with BagSource(Path(path)) as source:   # BagError (a ValueError) for an unusable bag
        topics = {name for name in source.topics if name in wanted}
        if not topics:
            raise ValueError(f'{path}: no topics polhemus/<name>/pose for names '
                             f'{sorted(station_by_name)}; topics are {sorted(source.topics)}')
        for topic, _, rawdata in source.messages(topics):
            msg = store.deserialize_cdr(rawdata, source.topics[topic].msgtype)
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            p, o = msg.pose.position, msg.pose.orientation
            by_stamp.setdefault(stamp, {})[wanted[topic]] = (
                np.array([p.x, p.y, p.z]), np.array([o.x, o.y, o.z, o.w]))
    stamps = sorted(by_stamp)
    stations = tuple(sorted({s for frame in by_stamp.values() for s in frame}))
    positions, quats = _forward_fill([by_stamp[s] for s in stamps], stations)
    times = (np.asarray(stamps, dtype=np.int64) - stamps[0]) * 1e-9
    return RecordedMotion(stations, times, positions, quats, loop)


def open_motion_source(spec: str, station_by_name: Mapping[str, int],
                       stations: Sequence[int]) -> MotionSource:
    """``builtin``, a ``.txt`` recording, or a bag folder / ``.mcap`` / ``.db3`` file."""
    if spec == 'builtin':
        return BuiltinMotion(stations)
    path = Path(spec)
    if not path.exists():
        raise FileNotFoundError(f'motion source {spec!r}: no such file or folder '
                                f'(use "builtin", a .txt recording or a bag)')
    if path.suffix == '.txt':
        return load_plhm_text(path)
    return load_pose_bag(path, station_by_name)
