"""Registration of fingertips into the object frame (eq. 1 done properly).

The core check is physical: a fingertip glued to a rigid object at a fixed offset (in the
object sensor's frame) must register to that same offset whatever the object does. The
tracker-frame positions are built here with rotation matrices, p = t_o + R_o @ offset, so
the registrar's own quaternion path (conjugate + rotate_vectors) is checked against them.
"""

import math

import numpy as np
import pytest

from inhand_common.rotations import euler_zyx_to_quaternion, quaternion_multiply, quaternion_to_matrix, slerp
from inhand_mapping.registration import Registrar, RegistrationStats

RATE = 240.0
OFFSETS = np.array([[0.03, -0.01, 0.02], [-0.015, 0.025, 0.0], [0.0, 0.0, -0.04]])


def axis_angle_quaternion(axis, angle):
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    angle = np.asarray(angle, dtype=float)[..., None]
    return np.concatenate([axis * np.sin(angle / 2), np.cos(angle / 2)], axis=-1)


def wobbly_motion(t):
    """A motion that is anything but linear: curved path, rotation about all three axes."""
    t = np.asarray(t, dtype=float)
    pos = np.stack([0.2 + 0.1 * np.sin(1.3 * t), -0.05 + 0.08 * np.cos(0.7 * t),
                    0.15 + 0.03 * t * t], axis=-1)
    q = euler_zyx_to_quaternion(2.0 * np.sin(0.9 * t), 1.2 * np.sin(1.7 * t), 3.0 * t)
    return pos, q


Q0 = euler_zyx_to_quaternion(0.4, -0.3, 1.1)
AXIS = np.array([1.0, -2.0, 0.5])
OMEGA = 2.5  # rad/s about AXIS (in the source frame)
VELOCITY = np.array([0.12, -0.05, 0.08])


def screw_motion(t):
    """Linear position and constant angular velocity about a fixed tilted axis: on this
    motion linear interpolation and slerp between any two poses are exact."""
    t = np.asarray(t, dtype=float)
    pos = np.array([0.3, 0.1, -0.2]) + t[..., None] * VELOCITY
    q = quaternion_multiply(axis_angle_quaternion(AXIS, OMEGA * t), Q0)
    return pos, q


def fingertips_on_object(motion, t, offset):
    pos, q = motion(t)
    return pos + np.einsum('...ij,...j->...i', quaternion_to_matrix(q), offset)


def feed_objects(reg, times, motion):
    pos, q = motion(times)
    for k, tk in enumerate(times):
        reg.add_object_pose(float(tk), pos[k], q[k])


def balanced(stats: RegistrationStats) -> bool:
    return stats.received == (stats.registered + stats.dropped_gap + stats.dropped_invalid
                              + stats.dropped_before_object + stats.dropped_old_stream
                              + stats.pending)


def test_exact_stamps_register_fixed_offsets_on_a_wobbly_object():
    times = np.arange(480) / RATE
    pos, q = wobbly_motion(times)
    reg = Registrar()
    got = []
    # Interleaved as a live node sees it: a tracker frame's object pose and fingertips,
    # sometimes the fingertips first.
    for k, tk in enumerate(times):
        tips = np.stack([fingertips_on_object(wobbly_motion, tk, o) for o in OFFSETS])
        if k % 3 == 0:
            reg.add_fingertips(np.full(3, tk), tips, np.array([1, 2, 3]))
            reg.add_object_pose(tk, pos[k], q[k])
        else:
            reg.add_object_pose(tk, pos[k], q[k])
            reg.add_fingertips(np.full(3, tk), tips, np.array([1, 2, 3]))
        if k % 50 == 0:
            got.append(reg.drain())
    got.append(reg.finish())
    points = np.concatenate([g[0] for g in got])
    stamps = np.concatenate([g[1] for g in got])
    fingers = np.concatenate([g[2] for g in got])
    assert points.shape == (3 * len(times), 3)
    assert np.all(np.diff(stamps) >= 0)
    np.testing.assert_array_equal(np.unique(stamps), times)
    np.testing.assert_allclose(points, OFFSETS[fingers - 1], atol=1e-9, rtol=0)
    # The registration undid a large motion: the raw tracker positions are far from it.
    assert np.ptp(fingertips_on_object(wobbly_motion, times, OFFSETS[0]), axis=0).max() > 0.1
    assert reg.stats.registered == 3 * len(times) and reg.stats.pending == 0
    assert balanced(reg.stats)


def test_interpolated_stamps_register_exactly_on_a_screw_motion():
    obj_times = np.arange(241) / RATE
    tip_times = 0.0003 + np.arange(997) / 1000.0  # 1 kHz, never on an object stamp
    reg = Registrar(max_gap=0.01)
    feed_objects(reg, obj_times, screw_motion)
    for finger, offset in enumerate(OFFSETS):
        reg.add_fingertips(tip_times, fingertips_on_object(screw_motion, tip_times, offset),
                           np.full(tip_times.size, finger))
    points, stamps, fingers = reg.drain()
    assert not np.isin(tip_times, obj_times).any()
    assert points.shape == (3 * tip_times.size, 3)
    np.testing.assert_allclose(points, OFFSETS[fingers], atol=1e-9, rtol=0)
    assert np.all(np.diff(stamps) >= 0)
    # Interpolation mattered: pairing each fingertip with the previous object pose instead
    # would be off by far more than the tolerance.
    prev = np.floor(tip_times * RATE) / RATE
    pos, q = screw_motion(prev)
    tips = fingertips_on_object(screw_motion, tip_times, OFFSETS[0])
    naive = np.einsum('nji,nj->ni', quaternion_to_matrix(q), tips - pos)
    assert np.abs(naive - OFFSETS[0]).max() > 1e-4


def test_exact_stamp_uses_that_pose_and_not_a_blend():
    reg = Registrar(max_gap=0.05)
    t1 = 1.0 + 4 / RATE
    q_a = euler_zyx_to_quaternion(0.0, 0.0, 0.0)
    q_b = euler_zyx_to_quaternion(0.8, -0.4, 0.3)
    reg.add_object_pose(1.0, [0.0, 0.0, 0.0], q_a)
    reg.add_object_pose(t1, [0.1, 0.2, 0.3], q_b)
    reg.add_object_pose(t1 + 0.02, [0.5, 0.5, 0.5], q_a)
    tip = np.array([0.15, 0.1, 0.4])
    reg.add_fingertips(np.array([t1]), tip[None], np.array([7]))
    points, stamps, fingers = reg.drain()
    expected = quaternion_to_matrix(q_b).T @ (tip - np.array([0.1, 0.2, 0.3]))
    np.testing.assert_allclose(points[0], expected, atol=1e-12, rtol=0)
    assert stamps.tolist() == [t1] and fingers.tolist() == [7]


def test_fingertip_waits_for_a_late_object_pose():
    reg = Registrar()
    reg.add_object_pose(0.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    reg.add_fingertips(np.array([1 / RATE]), np.array([[1.0, 2.0, 3.0]]), np.array([1]))
    points, _, _ = reg.drain()
    assert points.shape == (0, 3)
    assert reg.stats.pending == 1 and reg.stats.registered == 0
    reg.add_object_pose(1 / RATE, [1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    points, stamps, _ = reg.drain()
    np.testing.assert_allclose(points, [[0.0, 2.0, 3.0]], atol=1e-12)
    assert stamps.tolist() == [1 / RATE]
    assert reg.stats.pending == 0 and reg.stats.registered == 1
    assert balanced(reg.stats)


def test_never_extrapolates_across_a_gap_or_past_the_last_pose():
    identity = [0.0, 0.0, 0.0, 1.0]
    reg = Registrar(max_gap=0.05)
    reg.add_object_pose(0.0, [0.0, 0.0, 0.0], identity)
    reg.add_object_pose(0.05, [0.05, 0.0, 0.0], identity)  # gap == max_gap: interpolated
    reg.add_object_pose(0.15, [0.15, 0.0, 0.0], identity)  # gap 0.1 > max_gap
    reg.add_fingertips(np.array([0.025, 0.1, 0.12, 0.2, 0.3]), np.zeros((5, 3)),
                       np.zeros(5, dtype=int))
    points, stamps, fingers = reg.drain()
    assert stamps.tolist() == [0.025]
    np.testing.assert_allclose(points, [[-0.025, 0.0, 0.0]], atol=1e-12)
    assert reg.stats.dropped_gap == 2  # 0.1 and 0.12 fall in the long gap
    assert reg.stats.pending == 2  # 0.2 and 0.3 wait for a later object pose
    points, stamps, _ = reg.finish()
    assert points.shape == (0, 3) and stamps.size == 0
    assert reg.stats.dropped_gap == 4 and reg.stats.pending == 0
    assert balanced(reg.stats)


def test_fingertips_before_the_first_object_pose_are_dropped():
    identity = [0.0, 0.0, 0.0, 1.0]
    reg = Registrar()
    # Arriving before any object pose, they wait; once it comes the early ones are dropped.
    reg.add_fingertips(np.array([0.98, 0.99, 1.0]), np.ones((3, 3)), np.array([3, 3, 3]))
    assert reg.drain()[0].shape == (0, 3) and reg.stats.pending == 3
    reg.add_object_pose(1.0, [0.0, 0.0, 0.0], identity)
    points, stamps, fingers = reg.drain()
    assert stamps.tolist() == [1.0] and fingers.tolist() == [3]
    assert reg.stats.dropped_before_object == 2
    # Arriving later than the first pose but stamped before it: dropped too.
    reg.add_fingertips(np.array([0.5]), np.ones((1, 3)), np.array([1]))
    assert reg.drain()[0].shape == (0, 3)
    assert reg.stats.dropped_before_object == 3 and reg.stats.dropped_gap == 0
    assert balanced(reg.stats)


def test_finish_without_any_object_pose_drops_everything_as_before_object():
    reg = Registrar()
    reg.add_fingertips(np.array([0.0, 0.1]), np.zeros((2, 3)), np.array([1, 1]))
    points, _, _ = reg.finish()
    assert points.shape == (0, 3)
    assert reg.stats.dropped_before_object == 2 and reg.stats.pending == 0
    assert reg.first_object_pose is None


def test_nan_and_inf_are_rejected_and_counted():
    reg = Registrar()
    reg.add_object_pose(0.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    reg.add_object_pose(0.004, [np.nan, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    reg.add_object_pose(0.004, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0])
    reg.add_object_pose(0.004, [0.0, 0.0, 0.0], [np.inf, 0.0, 0.0, 1.0])
    assert reg.stats.object_invalid == 3 and reg.stats.object_poses == 1
    positions = np.array([[1.0, 0, 0], [np.nan, 0, 0], [0, np.inf, 0], [2.0, 0, 0], [3.0, 0, 0]])
    reg.add_fingertips(np.array([0.0, 0.0, 0.0, np.nan, 0.0]), positions, np.arange(5))
    assert reg.stats.dropped_invalid == 3
    points, _, fingers = reg.drain()
    assert fingers.tolist() == [0, 4]
    assert np.isfinite(points).all()
    assert balanced(reg.stats)


def test_static_mode_passes_points_through_in_the_tracker_frame():
    reg = Registrar(mode='static')
    position, quaternion = reg.first_object_pose
    np.testing.assert_array_equal(position, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(quaternion, [0.0, 0.0, 0.0, 1.0])
    reg.add_object_pose(0.0, [1.0, 1.0, 1.0], euler_zyx_to_quaternion(1.0, 0.0, 0.0))  # ignored
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(6, 3))
    pts[2, 1] = np.nan
    reg.add_fingertips(np.array([0.3, 0.1, 0.2, 0.4, 0.0, 0.5]), pts, np.array([1, 2, 3, 1, 2, 3]))
    points, stamps, fingers = reg.finish()
    assert stamps.tolist() == [0.0, 0.1, 0.3, 0.4, 0.5]
    np.testing.assert_array_equal(points, pts[[4, 1, 0, 3, 5]])
    assert fingers.tolist() == [2, 2, 1, 1, 3]
    assert reg.stats.dropped_invalid == 1 and reg.stats.registered == 5
    assert balanced(reg.stats)


def test_out_of_order_and_duplicate_object_poses_are_ignored():
    identity = [0.0, 0.0, 0.0, 1.0]
    reg = Registrar()
    reg.add_object_pose(0.0, [0.0, 0.0, 0.0], identity)
    reg.add_object_pose(0.01, [0.01, 0.0, 0.0], identity)
    reg.add_object_pose(0.005, [9.0, 9.0, 9.0], identity)  # older: ignored
    reg.add_object_pose(0.01, [7.0, 7.0, 7.0], identity)  # duplicate stamp: ignored
    assert reg.stats.object_out_of_order == 2 and reg.stats.object_poses == 2
    reg.add_fingertips(np.array([0.005, 0.01]), np.zeros((2, 3)), np.array([1, 1]))
    points, _, _ = reg.drain()
    np.testing.assert_allclose(points, [[-0.005, 0.0, 0.0], [-0.01, 0.0, 0.0]], atol=1e-12)


def test_first_object_pose_is_the_map_frame_in_the_tracker_frame():
    reg = Registrar()
    assert reg.first_object_pose is None
    q = np.array([0.0, 0.0, 2.0, 2.0])  # not normalised on input
    reg.add_object_pose(5.0, [0.1, 0.2, 0.3], q)
    reg.add_object_pose(5.01, [0.4, 0.5, 0.6], [0.0, 0.0, 0.0, 1.0])
    position, quaternion = reg.first_object_pose
    np.testing.assert_allclose(position, [0.1, 0.2, 0.3])
    np.testing.assert_allclose(quaternion, q / np.linalg.norm(q), atol=1e-15)
    # A texture point measured in the tracker frame maps into the map frame with it.
    world = np.array([0.1, 0.5, 0.3])
    in_map = quaternion_to_matrix(quaternion).T @ (world - position)
    np.testing.assert_allclose(in_map, [0.3, 0.0, 0.0], atol=1e-12)


def test_late_fingertips_register_within_max_pending_and_history_stays_bounded():
    reg = Registrar(max_pending=1.0)
    obj_times = np.arange(int(20 * RATE)) / RATE
    feed_objects(reg, obj_times, screw_motion)
    assert reg.drain()[0].shape == (0, 3)
    # Fingertips arriving 0.5 s late still register; 2 s late the poses are forgotten.
    late = np.array([obj_times[-1] - 0.5, obj_times[-1] - 2.0])
    tips = fingertips_on_object(screw_motion, late, OFFSETS[1])
    reg.add_fingertips(late, tips, np.array([2, 2]))
    points, stamps, _ = reg.drain()
    assert stamps.tolist() == [late[0]]
    np.testing.assert_allclose(points, OFFSETS[1][None], atol=1e-9)
    assert reg.stats.dropped_gap == 1
    # History kept: about max_pending seconds of poses, not the 20 s fed.
    assert reg._n_obj <= int(1.0 * RATE) + 2


def test_stalled_object_stream_does_not_grow_the_buffer():
    reg = Registrar(max_pending=0.5)
    reg.add_object_pose(0.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    for k in range(1, 1201):  # 5 s of fingertips, no more object poses; wall = sensor pace
        reg.add_fingertips(np.full(3, k / RATE), np.zeros((3, 3)), np.array([1, 2, 3]),
                           now=k / RATE)
        if k % 24 == 0:
            reg.drain(now=k / RATE)
    assert reg.stats.pending <= 3 * (0.5 * RATE + 24 + 1)
    assert reg.stats.dropped_gap >= 3 * (1200 - 0.5 * RATE - 24)
    assert balanced(reg.stats)


def test_output_is_time_ordered_across_calls_and_fingers_broadcast():
    identity = [0.0, 0.0, 0.0, 1.0]
    reg = Registrar()
    for k in range(5):
        reg.add_object_pose(k * 0.01, [0.0, 0.0, 0.0], identity)
    reg.add_fingertips(0.03, np.array([[3.0, 0, 0], [3.5, 0, 0]]), 2)  # scalar t and finger
    reg.add_fingertips(np.array([0.01, 0.02]), np.array([[1.0, 0, 0], [2.0, 0, 0]]), [1, 1])
    reg.add_fingertips(0.0, [0.5, 0.0, 0.0], 3)  # one position as (3,)
    points, stamps, fingers = reg.finish()
    assert stamps.tolist() == [0.0, 0.01, 0.02, 0.03, 0.03]
    assert points[:, 0].tolist() == [0.5, 1.0, 2.0, 3.0, 3.5]
    assert fingers.tolist() == [3, 1, 1, 2, 2]


def reference_registration(obj_t, obj_p, obj_q, t, p, max_gap):
    """One fingertip at a time, written for clarity: None when it cannot be registered."""
    out = []
    for ti, pi in zip(t, p):
        if ti < obj_t[0] or ti > obj_t[-1]:
            out.append(None)
            continue
        k = int(np.flatnonzero(obj_t >= ti)[0])
        if obj_t[k] == ti:
            q, pos = obj_q[k], obj_p[k]
        elif obj_t[k] - obj_t[k - 1] <= max_gap:
            frac = (ti - obj_t[k - 1]) / (obj_t[k] - obj_t[k - 1])
            q = slerp(obj_q[k - 1], obj_q[k], frac)
            pos = obj_p[k - 1] + frac * (obj_p[k] - obj_p[k - 1])
        else:
            out.append(None)
            continue
        out.append(quaternion_to_matrix(q).T @ (pi - pos))
    return out


def test_random_streams_match_a_point_by_point_reference():
    rng = np.random.default_rng(11)
    steps = np.where(rng.random(400) < 0.03, rng.uniform(0.06, 0.2, 400), 1 / RATE)
    obj_t = 2.0 + np.cumsum(steps)
    obj_p = np.cumsum(rng.normal(scale=0.002, size=(obj_t.size, 3)), axis=0)
    obj_q = np.cumsum(rng.normal(scale=0.05, size=(obj_t.size, 4)), axis=0) + [0, 0, 0, 1]
    obj_q /= np.linalg.norm(obj_q, axis=1, keepdims=True)
    obj_q[::7] *= -1  # sign flips: the same rotations, slerp must take the short way
    # Fingertips: 1-4 stations on object stamps, others anywhere (before, gaps, after).
    on_stamp = np.repeat(rng.choice(obj_t, 300), rng.integers(1, 5, 300))
    anywhere = rng.uniform(obj_t[0] - 0.1, obj_t[-1] + 0.1, 600)
    t = rng.permutation(np.concatenate([on_stamp, anywhere]))
    p = rng.normal(scale=0.1, size=(t.size, 3))
    fingers = rng.integers(0, 4, t.size)

    reg = Registrar(max_gap=0.05, max_pending=100.0)
    for k in range(obj_t.size):
        reg.add_object_pose(obj_t[k], obj_p[k], obj_q[k])
    for chunk in np.array_split(np.arange(t.size), 7):  # unsorted, in several calls
        reg.add_fingertips(t[chunk], p[chunk], fingers[chunk])
    got = [reg.drain(), reg.finish()]
    points = np.concatenate([g[0] for g in got])
    stamps = np.concatenate([g[1] for g in got])
    got_fingers = np.concatenate([g[2] for g in got])

    expected = reference_registration(obj_t, obj_p, obj_q, t, p, 0.05)
    keep = np.array([e is not None for e in expected])
    order = np.lexsort((fingers, t))  # the output order: by time, then finger
    order = order[keep[order]]
    assert 300 < order.size < t.size  # the case mix is real: some resolve, some do not
    np.testing.assert_array_equal(stamps, t[order])
    np.testing.assert_array_equal(got_fingers, fingers[order])
    np.testing.assert_allclose(points, np.array([expected[i] for i in order]), atol=1e-12)
    s = reg.stats
    assert s.registered == order.size
    assert s.dropped_before_object == np.count_nonzero(t < obj_t[0])
    assert s.dropped_gap == t.size - order.size - s.dropped_before_object
    assert balanced(s) and s.pending == 0


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match='mode'):
        Registrar(mode='moving')
    with pytest.raises(ValueError, match='max_gap'):
        Registrar(max_gap=0.0)
    with pytest.raises(ValueError, match='max_pending'):
        Registrar(max_pending=math.nan)
    with pytest.raises(ValueError, match=r'\(N, 3\)'):
        Registrar().add_fingertips(np.zeros(2), np.zeros((2, 2)), np.zeros(2, dtype=int))
    with pytest.raises(ValueError, match='integers'):
        Registrar().add_fingertips(np.zeros(2), np.zeros((2, 3)), np.zeros(2))


def test_a_long_stream_registers_exactly():
    """200,000 fingertips (half on object stamps, half between) against 240 Hz object poses."""
    n_frames = 100_000 // 3 + 1
    obj_times = np.arange(n_frames) / RATE
    pos, q = screw_motion(obj_times)
    tip_times = np.concatenate([obj_times, obj_times[:-1] + 0.5 / RATE])
    tip_times = np.repeat(tip_times, 3)[:200_000]
    tips = fingertips_on_object(screw_motion, tip_times, OFFSETS[0])
    reg = Registrar()
    # Fingertips first (as a bag tool might): the object history is then kept for them.
    reg.add_fingertips(tip_times, tips, np.zeros(tip_times.size, dtype=int))
    for k in range(n_frames):
        reg.add_object_pose(obj_times[k], pos[k], q[k])
    points, _, _ = reg.drain()
    assert points.shape == (200_000, 3)
    np.testing.assert_allclose(points, np.broadcast_to(OFFSETS[0], points.shape), atol=1e-9)


def test_points_are_released_in_time_order_up_to_the_slowest_finger_stream():
    """Topics are delivered independently: one finger's stream may run ahead. Nothing is
    released past the oldest newest-stamp of the streams, so the output stays in time
    order across drains, which the occupancy windows rely on."""
    identity = [0.0, 0.0, 0.0, 1.0]
    reg = Registrar()
    for k in range(101):
        reg.add_object_pose(k * 0.01, [0.0, 0.0, 0.0], identity)
    times = np.arange(100) * 0.01
    reg.add_fingertips(times, np.zeros((100, 3)), 1)            # thumb: the whole second
    reg.add_fingertips(times[:30], np.zeros((30, 3)), 2)        # index: lagging behind
    _, first, _ = reg.drain()
    assert first.max() <= times[29] and first.size == 60
    reg.add_fingertips(times[30:], np.zeros((70, 3)), 2)        # index catches up
    _, second, _ = reg.drain()
    released = np.concatenate([first, second])
    assert released.size == 200 and np.all(np.diff(released) >= 0)


def test_a_silent_finger_stream_stops_holding_the_others_back():
    identity = [0.0, 0.0, 0.0, 1.0]
    reg = Registrar(max_pending=0.5)
    for k in range(101):
        reg.add_object_pose(k * 0.01, [0.0, 0.0, 0.0], identity)
    reg.add_fingertips(np.array([0.0]), np.zeros((1, 3)), 2, now=0.0)   # index, then silent
    reg.add_fingertips(np.arange(50) * 0.01, np.zeros((50, 3)), 1, now=0.1)
    assert reg.drain(now=0.2)[1].size == 2     # held at index's last stamp (0.0)
    assert reg.drain(now=0.7)[1].size == 49    # index silent for 0.7 s > max_pending
    assert balanced(reg.stats)


def test_an_expected_finger_not_heard_yet_holds_the_object_history_at_start_up():
    """A fast replay can deliver seconds of object poses and of some fingers before the
    first message of another finger. That finger's first seconds still register: its
    object poses are kept until it is heard, for max_pending seconds from the first data;
    without knowing it is expected, they are trimmed and its points dropped."""
    identity = [0.0, 0.0, 0.0, 1.0]
    results = {}
    for expected in ((), (1, 2)):
        reg = Registrar(max_pending=2.0, fingers=expected)
        assert reg.drain(now=0.0)[1].size == 0     # the node drains before data comes
        # 20 s of object poses in one batch, before any fingertip (the buffer makes room
        # on the way, which trims what it thinks nobody needs)
        for k in range(2001):
            reg.add_object_pose(k * 0.01, [0.0, 0.0, 0.0], identity)
        times = np.arange(2000) * 0.01
        reg.add_fingertips(times, np.zeros((2000, 3)), 1, now=0.1)
        first = reg.drain(now=0.1)[1].size
        reg.add_fingertips(times, np.zeros((2000, 3)), 2, now=0.15)    # finger 2, late
        second = reg.drain(now=0.15)[1].size
        results[expected] = (first, second, reg.stats.dropped_gap)
        assert balanced(reg.stats)
    assert results[(1, 2)] == (0, 4000, 0)
    first, second, dropped = results[()]
    assert dropped > 1000               # not expected: trimmed on the way, points lost
    # A finger that is expected but never tracked holds things up for max_pending only.
    reg = Registrar(max_pending=0.5, fingers=(1, 2))
    for k in range(101):
        reg.add_object_pose(k * 0.01, [0.0, 0.0, 0.0], identity)
    reg.add_fingertips(np.arange(50) * 0.01, np.zeros((50, 3)), 1, now=0.0)
    assert reg.drain(now=0.1)[1].size == 0
    assert reg.drain(now=0.7)[1].size == 50
    # Without a clock (build_map, a bag read in time order) nothing is held for it.
    reg = Registrar(fingers=(1, 2))
    for k in range(101):
        reg.add_object_pose(k * 0.01, [0.0, 0.0, 0.0], identity)
    reg.add_fingertips(np.arange(50) * 0.01, np.zeros((50, 3)), 1)
    assert reg.drain()[1].size == 50


def test_object_pose_at_follows_the_fingertip_rules():
    """What the stereo node asks: the map frame's pose at a picture's stamp."""
    from inhand_common.rotations import quaternion_to_matrix
    reg = Registrar('tracked', max_gap=0.05)
    assert reg.object_pose_at(10.0).state == 'later'          # no pose yet
    q0, q1 = np.array([0.0, 0.0, 0.0, 1.0]), np.array([0.0, 0.0, math.sin(0.1), math.cos(0.1)])
    reg.add_object_pose(10.00, [0.1, 0.0, 0.0], q0)
    reg.add_object_pose(10.04, [0.2, 0.0, 0.0], q1)
    reg.add_object_pose(10.20, [0.3, 0.0, 0.0], q1)           # 0.16 s after: a gap
    exact = reg.object_pose_at(10.04)
    assert exact.state == 'resolved'
    assert np.allclose(exact.position, [0.2, 0, 0])
    assert np.allclose(exact.rotation, quaternion_to_matrix(q1))
    half = reg.object_pose_at(10.02)
    assert half.state == 'resolved' and np.allclose(half.position, [0.15, 0, 0])
    angle = math.atan2(half.rotation[1, 0], half.rotation[0, 0])
    assert math.isclose(angle, 0.1, abs_tol=1e-9)             # slerp: half of 0.2 rad
    assert reg.object_pose_at(10.10).state == 'gap'
    assert reg.object_pose_at(9.99).state == 'before_first'
    assert reg.object_pose_at(10.30).state == 'later'         # never extrapolated
    static = Registrar('static').object_pose_at(5.0)
    assert static.state == 'resolved' and np.allclose(static.rotation, np.eye(3))


def feed_in_batches(reg, times, motion, offset, fingers_first=False, batch=0.05):
    """What the node does: every 50 ms, the object poses then the fingertips received
    (or the other way round); returns the registered points."""
    out = []
    pos, q = motion(times)
    tips = fingertips_on_object(motion, times, offset)
    edges = np.arange(times[0], times[-1] + batch, batch)
    for start in edges:
        part = np.flatnonzero((times >= start) & (times < start + batch))
        if len(part) == 0:
            continue
        def objects(part=part):
            for k in part:
                reg.add_object_pose(float(times[k]), pos[k], q[k])
        def fingers(part=part):
            reg.add_fingertips(times[part], tips[part], 0, now=0.0)
        for step in ((fingers, objects) if fingers_first else (objects, fingers)):
            step()
        out.append(reg.drain(now=0.0))
    return out


@pytest.mark.parametrize('fingers_first', [False, True])
@pytest.mark.parametrize('shift', [0.0, -100.0])
def test_time_going_back_starts_a_new_stream_and_keeps_registering(fingers_first, shift):
    """A second replay into a running graph, a loop, a clock stepped back: the registrar
    used to drop everything after the jump as 'before the first object pose'. The second
    pass registers as the first did, in the same map frame."""
    offset = np.array([0.01, -0.02, 0.03])
    times = 1000.0 + np.arange(300) / 100.0            # 3 s at 100 Hz
    reg = Registrar('tracked', max_gap=0.05, max_pending=2.0, fingers=[0])
    first = feed_in_batches(reg, times, screw_motion, offset, fingers_first)
    later = times + shift
    second = feed_in_batches(reg, later, lambda t: screw_motion(t - shift), offset,
                             fingers_first)
    second.append(reg.finish())
    points = np.concatenate([r[0] for r in first + second])
    stats = reg.stats
    assert stats.restarts == 1
    assert stats.dropped_before_object == 0 and stats.dropped_gap == 0
    assert stats.registered == len(points) >= 2 * 300 - 6   # a batch in flight at most
    assert balanced(stats)
    # Every point is the same offset in the object frame, in both streams.
    assert np.allclose(points, offset, atol=1e-9)


def test_a_loop_of_five_passes_keeps_mapping():
    offset = np.array([0.0, 0.01, 0.0])
    times = 5.0 + np.arange(200) / 100.0
    reg = Registrar('tracked', max_gap=0.05, max_pending=2.0, fingers=[0])
    out = []
    for _ in range(5):
        out += feed_in_batches(reg, times, screw_motion, offset)
    out.append(reg.finish())
    assert reg.stats.restarts == 4
    assert reg.stats.registered >= 5 * 200 - 4 * 6
    assert balanced(reg.stats)


def test_static_mode_restarts_on_a_finger_going_back():
    reg = Registrar('static', fingers=[0, 1])
    t = np.arange(100) / 50.0
    for finger in (0, 1):
        reg.add_fingertips(t, np.zeros((100, 3)), finger, now=0.0)
    assert len(reg.drain(now=0.0)[0]) == 200
    for finger in (0, 1):
        reg.add_fingertips(t, np.ones((100, 3)), finger, now=0.0)
    points = np.concatenate([reg.drain(now=0.0)[0], reg.finish()[0]])
    assert reg.stats.restarts == 1 and len(points) == 200 and np.all(points == 1.0)
    assert balanced(reg.stats)
