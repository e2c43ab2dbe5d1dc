"""Known exploration motions for tests: fingertips on a sphere fixed to a moving object.

``sphere_session`` returns tracker frames (stamp, {name: (position, quaternion)}) in the
tracker frame, the way the driver publishes them: all stations of a frame share a stamp.
``write_pose_bag`` stores such frames as a rosbag2 MCAP bag of PoseStamped messages.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from inhand_common.ros_names import station_pose_topic
from inhand_common.rotations import (
    euler_zyx_to_quaternion,
    matrix_to_quaternion,
    quaternion_multiply,
    rotate_vectors,
)
from inhand_mapping.pose_cdr import encode_pose_stamped

FINGERS = ('thumb', 'index', 'middle')


def sphere_surface_points(count: int, radius: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(count, 3))
    return radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def fibonacci_sphere(count: int, radius: float) -> np.ndarray:
    """``count`` near-uniform points on a sphere of ``radius`` about the origin (a
    Fibonacci lattice: evenly spaced, unlike random draws)."""
    i = np.arange(count) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / count)
    azimuth = math.pi * (1.0 + math.sqrt(5.0)) * i
    return radius * np.stack([np.cos(azimuth) * np.sin(polar),
                              np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1)


def spot_tour(spots: np.ndarray) -> np.ndarray:
    """The spots in the order a finger slides through them: a nearest-neighbour tour from
    the first, so each leg is a short arc (1-3 cm for 40 spots on a 4 cm sphere)."""
    order = [0]
    left = set(range(1, len(spots)))
    while left:
        here = spots[order[-1]]
        nearest = min(left, key=lambda i: float(np.sum((spots[i] - here) ** 2)))
        order.append(nearest)
        left.remove(nearest)
    return spots[np.asarray(order)]


def fingertip_on_sphere(frame: int, finger: int, tour: np.ndarray, rate: float = 240.0,
                        leg: float = 0.6) -> np.ndarray:
    """Where ``finger`` is in tracker frame ``frame``: sliding along the sphere from one
    spot of ``tour`` to the next, ``leg`` seconds per arc (1.5-5 cm/s). The fingers start a
    third of the tour apart, so their paths overlap as the session goes on."""
    per_leg = max(1, int(round(leg * rate)))
    start = finger * len(tour) // 3
    k = frame // per_leg + start
    a, b = tour[k % len(tour)], tour[(k + 1) % len(tour)]
    s = (frame % per_leg) / per_leg
    radius = np.linalg.norm(a)
    cos = np.clip(np.dot(a, b) / (radius * np.linalg.norm(b)), -1.0, 1.0)
    angle = np.arccos(cos)
    if angle < 1e-9:
        return a.copy()
    return (np.sin((1 - s) * angle) * a + np.sin(s * angle) * b) / np.sin(angle)


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
                   leg: float = 0.6):
    """Frames of fingertips sliding over a sphere fixed to the object, from spot to spot
    of ``surface_points`` spots (``fingertip_on_sphere``); the fingers' paths overlap, so
    cells are touched by several fingers (the map needs independent touches or slow
    passes: see touch_paths.py). Returns (frames, sphere centre in the object frame).
    """
    centre = np.asarray(centre_in_object, dtype=float)
    tour = spot_tour(sphere_surface_points(surface_points, radius, seed))
    frames = []
    for k in range(int(seconds * rate)):
        t = start + k / rate
        obj_p, obj_q = object_motion(t - start, moving)
        frame = {'object': (obj_p, obj_q)}
        for f, name in enumerate(FINGERS):
            local = centre + fingertip_on_sphere(k, f, tour, rate, leg)
            frame[name] = (obj_p + rotate_vectors(obj_q, local), np.array([0.0, 0.0, 0.0, 1.0]))
        frames.append((t, frame))
    return frames, centre


def on_the_nail(frames, centre_in_object: np.ndarray, offset: np.ndarray, pad_radius: float,
                roll_deg: float = 20.0):
    """The same contacts made by real fingers: each fingertip sensor on the nail, ``offset``
    (sensor frame, m) from its pad centre, the pad ``pad_radius`` round, its nail facing out
    of the sphere (centred at ``centre_in_object``) and the finger rolled ``roll_deg`` about
    its x axis. The frames carry the sensors' poses (what the driver would publish)."""
    rolled = euler_zyx_to_quaternion(0.0, 0.0, np.radians(roll_deg))
    out = []
    for t, frame in frames:
        obj_p, obj_q = frame['object']
        centre = obj_p + rotate_vectors(obj_q, centre_in_object)
        nail = dict(frame)
        for name in FINGERS:
            contact = frame[name][0]
            outward = (contact - centre) / np.linalg.norm(contact - centre)
            side = np.cross(outward, [1.0, 0.0, 0.0] if abs(outward[0]) < 0.9 else [0.0, 1.0, 0.0])
            side /= np.linalg.norm(side)
            axes = np.stack([np.cross(side, outward), side, outward], axis=1)
            q = quaternion_multiply(matrix_to_quaternion(axes), rolled)
            pad_centre = contact + pad_radius * outward
            nail[name] = (pad_centre - rotate_vectors(q, offset), q)
        out.append((t, nail))
    return out


def stamp_parts(t: float) -> tuple[int, int]:
    ns = int(round(t * 1e9))
    return ns // 1_000_000_000, ns % 1_000_000_000


def write_pose_bag(path: Path, frames, frame_id: str = 'polhemus_source',
                   diagnostics: bool = False) -> Path:
    """The frames as PoseStamped messages; ``diagnostics`` adds an empty DiagnosticArray
    on /diagnostics every second, as a bag recorded from a live run holds."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    msgtype = 'geometry_msgs/msg/PoseStamped'
    names = list(dict.fromkeys(name for _, frame in frames for name in frame))
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {name: writer.add_connection('/' + station_pose_topic(name), msgtype,
                                                   typestore=store) for name in names}
        if diagnostics:
            array = store.types['diagnostic_msgs/msg/DiagnosticArray']
            header, stamp = store.types['std_msgs/msg/Header'], store.types[
                'builtin_interfaces/msg/Time']
            topic = writer.add_connection('/diagnostics', array.__msgtype__, typestore=store)
            for t in np.arange(frames[0][0], frames[-1][0], 1.0):
                sec, nanosec = stamp_parts(float(t))
                message = array(header=header(stamp=stamp(sec=sec, nanosec=nanosec),
                                              frame_id=''), status=[])
                writer.write(topic, sec * 1_000_000_000 + nanosec,
                             bytes(store.serialize_cdr(message, array.__msgtype__)))
        for t, frame in frames:
            sec, nanosec = stamp_parts(t)
            for name, (p, q) in frame.items():
                writer.write(connections[name], sec * 1_000_000_000 + nanosec,
                             encode_pose_stamped(sec, nanosec, frame_id, (*p, *q)))
    return path
