"""Fast CDR decoding and encoding of ``geometry_msgs/msg/PoseStamped``.

rclpy hands raw subscriptions the serialized message, and bags (rosbags, rosbag2) store the
same bytes. Deserialising through rclpy costs a Python message object per pose, which is
the bottleneck of the tracker hot path; the layout of a PoseStamped is fixed, so ``struct``
reads it directly, and a batch of equally long messages (one frame_id) is read by numpy
without a Python loop at all.

Layout (OMG CDR, as Fast DDS and rosbags write it)::

    0   encapsulation: 2-byte representation id, big-endian (0x0000 CDR_BE, 0x0001 CDR_LE),
        then 2 option bytes. Everything after it is the payload; alignment is counted from
        the payload's start (byte 4 of the buffer).
    +0  int32   header.stamp.sec
    +4  uint32  header.stamp.nanosec
    +8  uint32  length of header.frame_id in bytes, including its terminating NUL
    +12 bytes   frame_id, NUL-terminated
    ... padding to a multiple of 8 (payload-relative)
        float64 x 7: position x, y, z, orientation x, y, z, w

Both byte orders are decoded; :func:`encode_pose_stamped` writes little-endian, as ROS 2
does on x86 and ARM.
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Iterable, Sequence

import numpy as np

from inhand_common.cdr import CDR_BE, CDR_LE, ENCAPSULATION, byte_order, decode_string

__all__ = [
    'CDR_BE',
    'CDR_LE',
    'decode_pose_stamped',
    'decode_pose_stamped_many',
    'encode_pose_stamped',
]

_LE_HEAD = struct.Struct('<iII')
_BE_HEAD = struct.Struct('>iII')
_LE_POSE = struct.Struct('<7d')
_BE_POSE = struct.Struct('>7d')
_LE_ENCAP = b'\x00\x01\x00\x00'
_HEAD_SIZE = 12  # sec, nanosec, string length
_POSE_SIZE = 56

Pose7 = tuple[float, float, float, float, float, float, float]


def _pose_offset(string_length: int) -> int:
    """Buffer offset of the 7 doubles for a frame_id field of ``string_length`` bytes."""
    payload = _HEAD_SIZE + string_length
    return ENCAPSULATION + ((payload + 7) & ~7)


def _frame_id(field) -> str:
    return decode_string(bytes(field), 'frame_id', 'PoseStamped')


def _structs(data) -> tuple[struct.Struct, struct.Struct]:
    if byte_order(data, 'PoseStamped') == '<':
        return _LE_HEAD, _LE_POSE
    return _BE_HEAD, _BE_POSE


def decode_pose_stamped(data) -> tuple[int, int, str, Pose7]:
    """Decode one serialized PoseStamped: ``(sec, nanosec, frame_id, (px, py, pz, qx, qy, qz, qw))``.

    ``data`` is anything that supports the buffer protocol (bytes, memoryview, bytearray).
    Raises ValueError on an unknown encapsulation, a truncated or malformed buffer.
    """
    head, pose = _structs(data)
    size = len(data)
    if size < ENCAPSULATION + _HEAD_SIZE:
        raise ValueError(f'PoseStamped CDR truncated: {size} bytes, header needs '
                         f'{ENCAPSULATION + _HEAD_SIZE}')
    sec, nanosec, length = head.unpack_from(data, ENCAPSULATION)
    start = ENCAPSULATION + _HEAD_SIZE
    offset = _pose_offset(length)
    end = offset + _POSE_SIZE
    if size < end:
        raise ValueError(f'PoseStamped CDR truncated: {size} bytes, frame_id of length '
                         f'{length} needs {end}')
    if size - end > 3:
        raise ValueError(f'PoseStamped CDR malformed: {size - end} bytes after the pose '
                         f'(message is {end} bytes)')
    frame_id = decode_string(bytes(data[start:start + length]), 'frame_id', 'PoseStamped')
    return sec, nanosec, frame_id, pose.unpack_from(data, offset)


def decode_pose_stamped_many(messages: Sequence | Iterable
                             ) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Decode many PoseStamped: ``(stamps_ns int64 (N,), frame_ids [N], poses float64 (N, 7))``.

    ``stamps_ns = sec * 1_000_000_000 + nanosec``. When every message is little-endian with
    the same length (the usual case: one topic, one frame_id) the batch is decoded by numpy
    in one go; otherwise message by message. Raises ValueError naming the first bad message.
    """
    messages = messages if isinstance(messages, (list, tuple)) else list(messages)
    n = len(messages)
    if n == 0:
        return np.empty(0, dtype=np.int64), [], np.empty((0, 7))
    lengths = set(map(len, messages))
    first_len = len(messages[0])
    if len(lengths) == 1 and first_len >= ENCAPSULATION + _HEAD_SIZE:
        batch = _decode_uniform(messages, first_len)
        if batch is not None:
            return batch
    stamps = np.empty(n, dtype=np.int64)
    poses = np.empty((n, 7))
    frame_ids: list[str] = []
    append = frame_ids.append
    for i, message in enumerate(messages):
        try:
            sec, nanosec, frame_id, pose = decode_pose_stamped(message)
        except ValueError as err:
            raise ValueError(f'message {i}: {err}') from None
        stamps[i] = sec * 1_000_000_000 + nanosec
        append(frame_id)
        poses[i] = pose
    return stamps, frame_ids, poses


def _decode_uniform(messages, size: int):
    """Vectorised decode of equally long little-endian messages, or None to fall back."""
    raw = np.frombuffer(b''.join(messages), dtype=np.uint8).reshape(len(messages), size)
    if not np.all(raw[:, :ENCAPSULATION] == np.frombuffer(_LE_ENCAP, np.uint8)):
        return None  # other byte order or options: the per-message path says what is wrong
    head = np.ascontiguousarray(raw[:, ENCAPSULATION:ENCAPSULATION + _HEAD_SIZE])
    head = head.view('<u4')
    length = int(head[0, 2])
    if not np.all(head[:, 2] == length):
        return None
    offset = _pose_offset(length)
    end = offset + _POSE_SIZE
    if size < end or size - end > 3:
        return None
    start = ENCAPSULATION + _HEAD_SIZE
    if length:
        names = raw[:, start:start + length]
        if not np.all(names[:, -1] == 0):
            return None
        try:
            if np.all(names == names[0]):
                frame_ids = [_frame_id(names[0])] * len(messages)
            else:
                frame_ids = [_frame_id(row) for row in names]
        except ValueError:
            return None
    else:
        frame_ids = [''] * len(messages)
    sec = head[:, 0].view('<i4').astype(np.int64)
    stamps = sec * 1_000_000_000 + head[:, 1].astype(np.int64)
    poses = np.ascontiguousarray(raw[:, offset:end]).view('<f8').astype(np.float64)
    return stamps, frame_ids, poses


@functools.lru_cache(maxsize=64)
def _message_struct(string_length: int) -> struct.Struct:
    """Whole little-endian message after the encapsulation, for one frame_id length.

    ``s`` pads with NULs, so the frame_id's terminator comes for free; ``x`` is the zeroed
    alignment padding before the doubles.
    """
    pad = _pose_offset(string_length) - ENCAPSULATION - _HEAD_SIZE - string_length
    return struct.Struct(f'<iII{string_length}s{pad}x7d')


def encode_pose_stamped(sec: int, nanosec: int, frame_id: str, pose7) -> bytes:
    """Serialize a PoseStamped as little-endian CDR.

    Byte-identical to rosbags' ``serialize_cdr``; identical to rclpy's
    ``serialize_message`` except for the alignment padding, which rclpy leaves
    uninitialised and this writes as zeros.
    """
    name = frame_id.encode('utf-8')
    if b'\x00' in name:
        raise ValueError('frame_id must not contain NUL characters')
    values = tuple(pose7)
    if len(values) != 7:
        raise ValueError(f'pose7 must have 7 values (px, py, pz, qx, qy, qz, qw), '
                         f'got {len(values)}')
    length = len(name) + 1
    try:
        return _LE_ENCAP + _message_struct(length).pack(sec, nanosec, length, name, *values)
    except struct.error as err:
        raise ValueError(f'cannot encode PoseStamped (sec must fit int32, nanosec uint32, '
                         f'the pose 7 floats): {err}') from None


def stamp_seconds(stamps_ns) -> np.ndarray:
    """Float seconds of integer nanosecond stamps, computed as ``sec + nanosec * 1e-9``.

    Every place that turns stamps into seconds uses this one formula, so that a fingertip
    and the object pose of the same tracker frame get bit-identical times (registration
    pairs them by equality) whichever path decoded them.
    """
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    return (stamps_ns // 1_000_000_000).astype(np.float64) + \
        (stamps_ns % 1_000_000_000).astype(np.float64) * 1e-9
