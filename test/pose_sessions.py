"""Known exploration motions for tests: fingertips on a sphere fixed to a moving object.

``sphere_session`` returns tracker frames (stamp, {name: (position, quaternion)}) in the
tracker frame, the way the driver publishes them: all stations of a frame share a stamp.
``write_pose_bag`` stores such frames as a rosbag2 MCAP bag of PoseStamped messages.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from inhand_common.ros_names import station_pose_topic
from inhand_common.rotations import euler_zyx_to_quaternion, rotate_vectors
from inhand_mapping.pose_cdr import encode_pose_stamped

FINGERS = ('thumb', 'index', 'middle')


def sphere_surface_points(count: int, radius: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(count, 3))
    return radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def touched_spot(frame: int, finger: int, spots: int, rate: float = 240.0,
                 dwell: float = 0.2) -> int:
    """Which spot ``finger`` touches in tracker frame ``frame`` of a sphere session."""
    per_spot = max(1, int(round(dwell * rate)))
    return ((frame // per_spot) * 7 + finger * 53) % spots


def object_motion(t: float, moving: bool):
    """Object sensor pose: 25 cm in front of the source; swaying and drifting if moving."""
    if not moving:
        return np.array([0.25, 0.0, 0.05]), np.array([0.0, 0.0, 0.0, 1.0])
    position = np.array([0.25 + 0.03 * np.sin(0.7 * t), 0.02 * np.sin(1.1 * t), 0.05])
    return position, euler_zyx_to_quaternion(0.6 * np.sin(0.5 * t), 0.3 * np.sin(0.3 * t),
                                             0.2 * t)


def sphere_session(seconds: float = 4.0, rate: float = 240.0, radius: float = 0.04,
                   centre_in_object=(0.0, 0.01, -0.02), surface_points: int = 150,
                   moving: bool = True, start: float = 1000.0, seed: int = 0,
                   dwell: float = 0.2):
    """Frames of fingertips visiting ``surface_points`` spots of a sphere fixed to the object.

    Each fingertip rests ``dwell`` seconds on a spot, then jumps to another; the fingers
    take the spots in different orders, so spots are touched by several fingers and again
    later (the map needs independent touches: see occupancy.py). Returns (frames, sphere
    centre in the object frame).
    """
    spots = sphere_surface_points(surface_points, radius, seed) + np.asarray(centre_in_object)
    frames = []
    for k in range(int(seconds * rate)):
        t = start + k / rate
        obj_p, obj_q = object_motion(t - start, moving)
        frame = {'object': (obj_p, obj_q)}
        for f, name in enumerate(FINGERS):
            local = spots[touched_spot(k, f, len(spots), rate, dwell)]
            frame[name] = (obj_p + rotate_vectors(obj_q, local), np.array([0.0, 0.0, 0.0, 1.0]))
        frames.append((t, frame))
    return frames, np.asarray(centre_in_object, dtype=float)


def stamp_parts(t: float) -> tuple[int, int]:
    ns = int(round(t * 1e9))
    return ns // 1_000_000_000, ns % 1_000_000_000


def write_pose_bag(path: Path, frames, frame_id: str = 'polhemus_source') -> Path:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    msgtype = 'geometry_msgs/msg/PoseStamped'
    names = list(frames[0][1])
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {name: writer.add_connection('/' + station_pose_topic(name), msgtype,
                                                   typestore=store) for name in names}
        for t, frame in frames:
            sec, nanosec = stamp_parts(t)
            for name, (p, q) in frame.items():
                writer.write(connections[name], sec * 1_000_000_000 + nanosec,
                             encode_pose_stamped(sec, nanosec, frame_id, (*p, *q)))
    return path
