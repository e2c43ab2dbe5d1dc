"""Fast PoseStamped CDR codec against the two serialisers it must agree with.

References: rclpy.serialization (the bytes a raw subscription delivers and a publisher
accepts) and rosbags' typestore (the bytes in bags), both independent of the code under
test. frame_id lengths 0..20 walk the padding before the 8-byte aligned doubles through
every case.
"""

import struct

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore

from inhand_mapping.pose_cdr import decode_pose_stamped, decode_pose_stamped_many, encode_pose_stamped

STORE = get_typestore(Stores.ROS2_JAZZY)
RB_POSE_STAMPED = STORE.types['geometry_msgs/msg/PoseStamped']
ALPHABET = np.array(list('abcdefghijklmnopqrstuvwxyz_/0123456789'))


def random_fields(rng, name_length):
    sec = int(rng.integers(-2**31, 2**31))
    nanosec = int(rng.integers(0, 10**9))
    frame_id = ''.join(rng.choice(ALPHABET, name_length))
    pose = tuple(float(v) for v in rng.normal(scale=10.0, size=7))
    return sec, nanosec, frame_id, pose


def rclpy_message(sec, nanosec, frame_id, pose):
    msg = PoseStamped()
    msg.header.stamp.sec = sec
    msg.header.stamp.nanosec = nanosec
    msg.header.frame_id = frame_id
    p, o = msg.pose.position, msg.pose.orientation
    p.x, p.y, p.z, o.x, o.y, o.z, o.w = pose
    return msg


def rosbags_message(sec, nanosec, frame_id, pose):
    types = STORE.types
    return RB_POSE_STAMPED(
        header=types['std_msgs/msg/Header'](
            stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec),
            frame_id=frame_id),
        pose=types['geometry_msgs/msg/Pose'](
            position=types['geometry_msgs/msg/Point'](x=pose[0], y=pose[1], z=pose[2]),
            orientation=types['geometry_msgs/msg/Quaternion'](
                x=pose[3], y=pose[4], z=pose[5], w=pose[6])))


def zero_padding(raw):
    """The buffer with the padding before the doubles zeroed. rclpy's serialize_message
    leaves those bytes uninitialised (seen here: 0x2b, 0x1b3c52 ...), so only the rest can
    be compared byte for byte; encode_pose_stamped writes zeros, as rosbags does."""
    raw = bytearray(raw)
    end = 16 + struct.unpack_from('<I', raw, 12)[0]
    pad = (-(end - 4)) % 8
    raw[end:end + pad] = bytes(pad)
    return bytes(raw)


def fields_of(msg):
    p, o = msg.pose.position, msg.pose.orientation
    return (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id,
            (p.x, p.y, p.z, o.x, o.y, o.z, o.w))


@pytest.mark.parametrize('name_length', range(21))
def test_matches_rclpy_both_ways_for_every_alignment(name_length):
    rng = np.random.default_rng(name_length)
    for _ in range(20):
        fields = random_fields(rng, name_length)
        reference = serialize_message(rclpy_message(*fields))
        assert decode_pose_stamped(reference) == fields
        encoded = encode_pose_stamped(*fields)
        assert len(encoded) == len(reference)
        assert encoded == zero_padding(reference)
        assert fields_of(deserialize_message(encoded, PoseStamped)) == fields


@pytest.mark.parametrize('little_endian', [True, False])
def test_decodes_rosbags_serialisation_in_both_byte_orders(little_endian):
    rng = np.random.default_rng(7)
    for name_length in range(21):
        fields = random_fields(rng, name_length)
        raw = STORE.serialize_cdr(rosbags_message(*fields), RB_POSE_STAMPED.__msgtype__,
                                  little_endian=little_endian)
        assert raw[:2] == (b'\x00\x01' if little_endian else b'\x00\x00')
        assert decode_pose_stamped(raw) == fields  # memoryview in, as rosbags gives it
        if little_endian:
            assert encode_pose_stamped(*fields) == bytes(raw)
        decoded = STORE.deserialize_cdr(encode_pose_stamped(*fields), RB_POSE_STAMPED.__msgtype__)
        assert decoded.header.frame_id == fields[2] and decoded.pose.orientation.w == fields[3][6]


def test_special_values_and_non_ascii_frame_ids_round_trip_like_rclpy():
    pose = (float('nan'), float('inf'), -0.0, 5e-324, -1.7976931348623157e308, 0.0, 1.0)
    for frame_id in ('', 'ä', 'object_µ', '物体'):
        reference = serialize_message(rclpy_message(-1, 999_999_999, frame_id, pose))
        assert encode_pose_stamped(-1, 999_999_999, frame_id, pose) == zero_padding(reference)
        sec, nanosec, name, got = decode_pose_stamped(reference)
        assert (sec, nanosec, name) == (-1, 999_999_999, frame_id)
        assert struct.pack('<7d', *got) == struct.pack('<7d', *pose)  # bit for bit


def test_many_matches_one_by_one_on_the_numpy_and_the_loop_paths():
    rng = np.random.default_rng(5)
    same = [encode_pose_stamped(*random_fields(rng, 0)[:2], 'polhemus_source',
                                random_fields(rng, 0)[3]) for _ in range(500)]
    names = [encode_pose_stamped(*random_fields(rng, 6)) for _ in range(300)]  # equal lengths
    mixed = [serialize_message(rclpy_message(*random_fields(rng, int(n))))
             for n in rng.integers(0, 21, 300)]
    big_endian = [STORE.serialize_cdr(rosbags_message(*random_fields(rng, 4)),
                                      RB_POSE_STAMPED.__msgtype__, little_endian=False)
                  for _ in range(50)]
    for batch in (same, names, mixed, big_endian, [memoryview(m) for m in same[:10]]):
        stamps, frame_ids, poses = decode_pose_stamped_many(batch)
        assert stamps.dtype == np.int64 and poses.shape == (len(batch), 7)
        for i, message in enumerate(batch):
            sec, nanosec, frame_id, pose = decode_pose_stamped(message)
            assert stamps[i] == sec * 1_000_000_000 + nanosec
            assert frame_ids[i] == frame_id
            assert tuple(poses[i]) == pose
    stamps, frame_ids, poses = decode_pose_stamped_many(iter(same[:3]))  # any iterable
    assert len(frame_ids) == 3 and set(frame_ids) == {'polhemus_source'}
    stamps, frame_ids, poses = decode_pose_stamped_many([])
    assert stamps.shape == (0,) and frame_ids == [] and poses.shape == (0, 7)


def test_stamps_in_nanoseconds_cover_the_int32_range():
    raw = [encode_pose_stamped(2**31 - 1, 999_999_999, 'a', (0.0,) * 7),
           encode_pose_stamped(-2**31, 0, 'a', (0.0,) * 7)]
    stamps, _, _ = decode_pose_stamped_many(raw)
    assert stamps.tolist() == [(2**31 - 1) * 10**9 + 999_999_999, -2**31 * 10**9]


def test_truncated_and_malformed_buffers_are_refused():
    good = encode_pose_stamped(3, 4, 'object', (1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0))
    for size in range(len(good)):
        with pytest.raises(ValueError, match='truncated'):
            decode_pose_stamped(good[:size])
    with pytest.raises(ValueError, match='encapsulation 0x0007'):
        decode_pose_stamped(b'\x00\x07' + good[2:])
    no_nul = bytearray(good)
    no_nul[16 + len('object')] = ord('x')  # the NUL after 'object'
    with pytest.raises(ValueError, match='NUL'):
        decode_pose_stamped(bytes(no_nul))
    huge = bytearray(good)
    huge[12:16] = struct.pack('<I', 2**32 - 1)
    with pytest.raises(ValueError, match='truncated'):
        decode_pose_stamped(bytes(huge))
    with pytest.raises(ValueError, match='after the pose'):
        decode_pose_stamped(good + bytes(8))
    bad_utf8 = bytearray(good)
    bad_utf8[16] = 0xff
    with pytest.raises(ValueError, match='UTF-8'):
        decode_pose_stamped(bytes(bad_utf8))
    # Up to 3 bytes of trailing padding are CDR-legal and ignored.
    assert decode_pose_stamped(good + bytes(3))[:3] == (3, 4, 'object')
    # A batch names the offending message, whichever path it takes.
    with pytest.raises(ValueError, match=r'message 2: .*truncated'):
        decode_pose_stamped_many([good, good, good[:-1]])
    with pytest.raises(ValueError, match=r'message 1: .*NUL'):
        decode_pose_stamped_many([good, bytes(no_nul), good])
    with pytest.raises(ValueError, match=r'message 2: .*encapsulation 0x0300'):
        decode_pose_stamped_many([good, good, b'\x03\x00' + good[2:]])


def test_encode_refuses_what_cannot_be_a_pose_stamped():
    with pytest.raises(ValueError, match='int32'):
        encode_pose_stamped(2**31, 0, 'a', (0.0,) * 7)
    with pytest.raises(ValueError, match='uint32'):
        encode_pose_stamped(0, -1, 'a', (0.0,) * 7)
    with pytest.raises(ValueError, match='NUL'):
        encode_pose_stamped(0, 0, 'a\x00b', (0.0,) * 7)
    with pytest.raises(ValueError, match='7 values'):
        encode_pose_stamped(0, 0, 'a', (0.0,) * 6)


def test_batched_decode_equals_one_at_a_time_on_a_long_stream():
    rng = np.random.default_rng(9)
    secs = rng.integers(0, 2**31, 20000).tolist()
    poses = rng.normal(size=(20000, 7)).tolist()
    raw = [encode_pose_stamped(sec, 500, 'polhemus_source', pose)
           for sec, pose in zip(secs, poses)]
    stamps, frame_ids, decoded = decode_pose_stamped_many(raw)
    assert np.array_equal(stamps, np.array(secs, dtype=np.int64) * 1_000_000_000 + 500)
    assert set(frame_ids) == {'polhemus_source'}
    assert np.array_equal(decoded, np.array(poses))
    for k in (0, 1234, 19999):
        assert decode_pose_stamped(raw[k])[3] == tuple(poses[k])
