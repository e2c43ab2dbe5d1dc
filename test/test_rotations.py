"""Euler Z-Y-X (Polhemus azimuth, elevation, roll), quaternions (x, y, z, w), matrices."""

import math

import numpy as np
import pytest

from inhand_common import rotations as R

C45 = math.cos(math.pi / 4)
S45 = math.sin(math.pi / 4)
HALF_PI = math.pi / 2


def same_rotation(q1, q2, atol=1e-9):
    """q and -q are one rotation: compare up to sign, elementwise over a stack."""
    q1 = np.asarray(q1, dtype=float)
    q2 = np.asarray(q2, dtype=float)
    direct = np.all(np.abs(q1 - q2) <= atol, axis=-1)
    flipped = np.all(np.abs(q1 + q2) <= atol, axis=-1)
    return bool(np.all(direct | flipped))


def random_quaternions(rng, shape):
    q = rng.normal(size=tuple(shape) + (4,))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def random_euler(rng, shape, margin=1e-3):
    az = rng.uniform(-math.pi, math.pi, shape)
    el = rng.uniform(-HALF_PI + margin, HALF_PI - margin, shape)
    roll = rng.uniform(-math.pi, math.pi, shape)
    return az, el, roll


def hand_rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def hand_ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def hand_rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


# ----------------------------------------------------------------------------- known cases

@pytest.mark.parametrize('angles, matrix, quat', [
    ((HALF_PI, 0.0, 0.0), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], (0.0, 0.0, S45, C45)),
    ((0.0, HALF_PI, 0.0), [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], (0.0, S45, 0.0, C45)),
    ((0.0, 0.0, HALF_PI), [[1, 0, 0], [0, 0, -1], [0, 1, 0]], (S45, 0.0, 0.0, C45)),
    ((math.pi, 0.0, 0.0), [[-1, 0, 0], [0, -1, 0], [0, 0, 1]], (0.0, 0.0, 1.0, 0.0)),
    ((0.0, 0.0, -HALF_PI), [[1, 0, 0], [0, 0, 1], [0, -1, 0]], (-S45, 0.0, 0.0, C45)),
    ((0.0, 0.0, 0.0), np.eye(3), (0.0, 0.0, 0.0, 1.0)),
])
def test_single_axis_cases_by_hand(angles, matrix, quat):
    np.testing.assert_allclose(R.euler_zyx_to_matrix(*angles), matrix, atol=1e-15)
    q = R.euler_zyx_to_quaternion(*angles)
    assert q.shape == (4,)
    assert same_rotation(q, quat, atol=1e-15)
    np.testing.assert_allclose(R.quaternion_to_matrix(quat), matrix, atol=1e-15)
    assert same_rotation(R.matrix_to_quaternion(np.array(matrix, dtype=float)), quat, atol=1e-15)


def test_azimuth_90_takes_sensor_x_to_source_y():
    q = R.euler_zyx_to_quaternion(HALF_PI, 0.0, 0.0)
    np.testing.assert_allclose(R.rotate_vectors(q, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0],
                               atol=1e-15)
    # Elevation 90 tips x down onto -z (z points down in the source frame: x -> -z).
    q = R.euler_zyx_to_quaternion(0.0, HALF_PI, 0.0)
    np.testing.assert_allclose(R.rotate_vectors(q, [1.0, 0.0, 0.0]), [0.0, 0.0, -1.0],
                               atol=1e-15)


def test_euler_order_is_z_then_y_then_x():
    az, el, roll = 0.7, -0.4, 2.1
    by_hand = hand_rz(az) @ hand_ry(el) @ hand_rx(roll)
    np.testing.assert_allclose(R.euler_zyx_to_matrix(az, el, roll), by_hand, atol=1e-15)
    np.testing.assert_allclose(R.quaternion_to_matrix(R.euler_zyx_to_quaternion(az, el, roll)),
                               by_hand, atol=1e-15)
    np.testing.assert_allclose(R.matrix_to_euler_zyx(by_hand), [az, el, roll], atol=1e-14)
    # The other order gives a different matrix: the test can tell them apart.
    assert not np.allclose(by_hand, hand_rx(roll) @ hand_ry(el) @ hand_rz(az), atol=1e-3)


# ----------------------------------------------------------------------------- round trips

@pytest.mark.parametrize('seed', range(5))
def test_euler_quaternion_matrix_round_trips_on_stacks(seed):
    rng = np.random.default_rng(seed)
    shape = (7, 11)
    az, el, roll = random_euler(rng, shape)
    q = R.euler_zyx_to_quaternion(az, el, roll)
    m = R.euler_zyx_to_matrix(az, el, roll)
    assert q.shape == shape + (4,)
    assert m.shape == shape + (3, 3)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-14)
    # Proper rotations.
    np.testing.assert_allclose(m @ np.swapaxes(m, -1, -2), np.broadcast_to(np.eye(3), m.shape),
                               atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(m), 1.0, atol=1e-14)
    # Both paths give one matrix.
    np.testing.assert_allclose(R.quaternion_to_matrix(q), m, atol=1e-14)
    # Back to Euler from either.
    expected = np.stack([az, el, roll], axis=-1)
    np.testing.assert_allclose(R.matrix_to_euler_zyx(m), expected, atol=1e-9)
    np.testing.assert_allclose(R.quaternion_to_euler_zyx(q), expected, atol=1e-9)
    # Matrix -> quaternion gives the same rotation, canonical w >= 0.
    q_back = R.matrix_to_quaternion(m)
    assert q_back.shape == shape + (4,)
    assert same_rotation(q_back, q, atol=1e-12)
    assert np.all(q_back[..., 3] >= 0.0)


@pytest.mark.parametrize('seed', range(5))
def test_random_quaternions_round_trip(seed):
    rng = np.random.default_rng(100 + seed)
    q = random_quaternions(rng, (500,))
    m = R.quaternion_to_matrix(q)
    assert same_rotation(R.matrix_to_quaternion(m), q, atol=1e-12)
    euler = R.quaternion_to_euler_zyx(q)
    assert np.all(np.abs(euler[..., 1]) <= HALF_PI)
    assert same_rotation(R.euler_zyx_to_quaternion(*np.moveaxis(euler, -1, 0)), q, atol=1e-9)
    np.testing.assert_allclose(R.euler_zyx_to_matrix(*np.moveaxis(euler, -1, 0)), m,
                               atol=1e-9)


def test_quaternion_to_matrix_normalises_first():
    q = np.array([0.0, 0.0, S45, C45])
    np.testing.assert_allclose(R.quaternion_to_matrix(3.5 * q), R.quaternion_to_matrix(q),
                               atol=1e-15)


# ----------------------------------------------------------------------------- gimbal

@pytest.mark.parametrize('elevation', [HALF_PI, -HALF_PI])
def test_gimbal_matrix_round_trip_is_exact(elevation):
    rng = np.random.default_rng(7)
    az = rng.uniform(-math.pi, math.pi, 200)
    roll = rng.uniform(-math.pi, math.pi, 200)
    m = R.euler_zyx_to_matrix(az, elevation, roll)
    euler = R.matrix_to_euler_zyx(m)
    assert np.all(np.isfinite(euler))
    np.testing.assert_allclose(euler[..., 1], elevation, atol=1e-12)
    np.testing.assert_allclose(euler[..., 2], 0.0, atol=0.0)  # the documented split
    np.testing.assert_allclose(R.euler_zyx_to_matrix(*np.moveaxis(euler, -1, 0)), m,
                               atol=1e-12)
    # At +90 only az - roll matters, at -90 only az + roll.
    combined = az - roll if elevation > 0 else az + roll
    np.testing.assert_allclose(np.cos(euler[..., 0]), np.cos(combined), atol=1e-12)
    np.testing.assert_allclose(np.sin(euler[..., 0]), np.sin(combined), atol=1e-12)


@pytest.mark.parametrize('elevation', [HALF_PI, -HALF_PI])
def test_gimbal_through_quaternion_stays_the_same_rotation(elevation):
    rng = np.random.default_rng(8)
    az = rng.uniform(-math.pi, math.pi, 200)
    roll = rng.uniform(-math.pi, math.pi, 200)
    q = R.euler_zyx_to_quaternion(az, elevation, roll)
    euler = R.quaternion_to_euler_zyx(q)
    assert np.all(np.isfinite(euler))
    # Quaternion rounding puts sin(elevation) a few ulp under 1, which arcsin amplifies to
    # ~1e-8 rad; still far below any sensor noise.
    np.testing.assert_allclose(R.euler_zyx_to_matrix(*np.moveaxis(euler, -1, 0)),
                               R.quaternion_to_matrix(q), atol=1e-7)


@pytest.mark.parametrize('offset', [1e-3, 1e-5, 1e-7, 1e-9])
@pytest.mark.parametrize('sign', [1.0, -1.0])
def test_near_gimbal_matrix_round_trip(offset, sign):
    rng = np.random.default_rng(9)
    az = rng.uniform(-math.pi, math.pi, 100)
    roll = rng.uniform(-math.pi, math.pi, 100)
    m = R.euler_zyx_to_matrix(az, sign * (HALF_PI - offset), roll)
    euler = R.matrix_to_euler_zyx(m)
    # Within ~1.4e-6 rad of +-90 the gimbal split (roll = 0) is used, which costs an error
    # of the order of the offset; further out the general formula is exact.
    atol = 3.0 * offset if offset < 2e-6 else 1e-10
    np.testing.assert_allclose(R.euler_zyx_to_matrix(*np.moveaxis(euler, -1, 0)), m,
                               atol=atol)


# ----------------------------------------------------------------------------- near 180 degrees

@pytest.mark.parametrize('angle', [math.pi, math.pi - 1e-6, math.pi - 1e-12, -math.pi])
def test_matrix_to_quaternion_near_half_turn(angle):
    rng = np.random.default_rng(11)
    axes = rng.normal(size=(300, 3))
    axes = np.concatenate([np.eye(3), -np.eye(3), [[1, 1, 0], [0, 1, -1], [1, 1, 1]], axes])
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    q = np.concatenate([axes * math.sin(angle / 2), np.full((len(axes), 1), math.cos(angle / 2))],
                       axis=-1)
    # Rodrigues, written out independently of the module.
    k = np.zeros((len(axes), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axes[:, 2], axes[:, 1], -axes[:, 0]
    k = k - np.swapaxes(k, -1, -2)
    m = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)
    q_back = R.matrix_to_quaternion(m)
    assert np.all(np.isfinite(q_back))
    np.testing.assert_allclose(np.linalg.norm(q_back, axis=-1), 1.0, atol=1e-14)
    assert same_rotation(q_back, q, atol=1e-12)
    np.testing.assert_allclose(R.quaternion_to_matrix(q_back), m, atol=1e-13)


def test_half_turn_about_x_by_hand():
    m = np.diag([1.0, -1.0, -1.0])
    assert same_rotation(R.matrix_to_quaternion(m), [1.0, 0.0, 0.0, 0.0], atol=0.0)
    m = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # about (1, 1, 0)
    assert same_rotation(R.matrix_to_quaternion(m), [S45, S45, 0.0, 0.0], atol=1e-15)


# ----------------------------------------------------------------------------- products

def test_rotate_vectors_matches_matrix_product():
    rng = np.random.default_rng(21)
    q = random_quaternions(rng, (50,))
    v = rng.normal(size=(50, 3))
    m = R.quaternion_to_matrix(q)
    expected = np.einsum('nij,nj->ni', m, v)
    np.testing.assert_allclose(R.rotate_vectors(q, v), expected, atol=1e-13)
    # One rotation, many vectors (broadcast), and an unnormalised quaternion.
    many = rng.normal(size=(20, 3))
    np.testing.assert_allclose(R.rotate_vectors(2.0 * q[0], many), many @ m[0].T, atol=1e-13)
    # Lengths are kept.
    np.testing.assert_allclose(np.linalg.norm(R.rotate_vectors(q, v), axis=-1),
                               np.linalg.norm(v, axis=-1), atol=1e-13)


def test_quaternion_multiply_is_associative_and_matches_matrices():
    rng = np.random.default_rng(22)
    a, b, c = (random_quaternions(rng, (100,)) for _ in range(3))
    left = R.quaternion_multiply(R.quaternion_multiply(a, b), c)
    right = R.quaternion_multiply(a, R.quaternion_multiply(b, c))
    np.testing.assert_allclose(left, right, atol=1e-14)
    np.testing.assert_allclose(R.quaternion_to_matrix(R.quaternion_multiply(a, b)),
                               R.quaternion_to_matrix(a) @ R.quaternion_to_matrix(b), atol=1e-13)
    # Not commutative in general.
    assert not np.allclose(R.quaternion_multiply(a, b), R.quaternion_multiply(b, a), atol=1e-3)
    # Apply q2 first, then q1.
    v = rng.normal(size=(100, 3))
    np.testing.assert_allclose(R.rotate_vectors(R.quaternion_multiply(a, b), v),
                               R.rotate_vectors(a, R.rotate_vectors(b, v)), atol=1e-13)


def test_quaternion_multiply_identity_and_conjugate():
    rng = np.random.default_rng(23)
    q = random_quaternions(rng, (30,))
    identity = np.array([0.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(R.quaternion_multiply(q, identity), q, atol=1e-15)
    np.testing.assert_allclose(R.quaternion_multiply(identity, q), q, atol=1e-15)
    np.testing.assert_allclose(R.quaternion_multiply(q, R.quaternion_conjugate(q)),
                               np.broadcast_to(identity, q.shape), atol=1e-14)


def test_zyx_product_of_single_axis_quaternions():
    az, el, roll = 0.3, -1.1, 2.5
    qz = np.array([0.0, 0.0, math.sin(az / 2), math.cos(az / 2)])
    qy = np.array([0.0, math.sin(el / 2), 0.0, math.cos(el / 2)])
    qx = np.array([math.sin(roll / 2), 0.0, 0.0, math.cos(roll / 2)])
    product = R.quaternion_multiply(R.quaternion_multiply(qz, qy), qx)
    np.testing.assert_allclose(R.euler_zyx_to_quaternion(az, el, roll), product, atol=1e-15)


def test_quaternion_canonical():
    q = np.array([[0.1, 0.2, 0.3, -0.9], [0.1, 0.2, 0.3, 0.9]])
    out = R.quaternion_canonical(q)
    np.testing.assert_allclose(out[0], -q[0])
    np.testing.assert_allclose(out[1], q[1])


# ----------------------------------------------------------------------------- slerp

def z_rotation(angle):
    return np.array([0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2)])


def test_slerp_endpoints():
    rng = np.random.default_rng(31)
    q0 = random_quaternions(rng, (40,))
    q1 = random_quaternions(rng, (40,))
    assert same_rotation(R.slerp(q0, q1, 0.0), q0, atol=1e-12)
    assert same_rotation(R.slerp(q0, q1, 1.0), q1, atol=1e-12)


def test_slerp_midpoint_of_quarter_turn_is_eighth_turn():
    identity = z_rotation(0.0)
    quarter = z_rotation(HALF_PI)
    assert same_rotation(R.slerp(identity, quarter, 0.5), z_rotation(math.pi / 4), atol=1e-15)
    assert same_rotation(R.slerp(identity, quarter, 0.25), z_rotation(math.pi / 8), atol=1e-15)
    # The same end rotation given with the other sign: still the short way, still 45 deg.
    assert same_rotation(R.slerp(identity, -quarter, 0.5), z_rotation(math.pi / 4), atol=1e-15)


def test_slerp_fractions_as_a_stack_move_at_constant_rate():
    q0 = z_rotation(0.2)
    q1 = z_rotation(1.4)
    t = np.linspace(0.0, 1.0, 9)
    out = R.slerp(q0, q1, t)
    assert out.shape == (9, 4)
    for ti, qi in zip(t, out):
        assert same_rotation(qi, z_rotation(0.2 + 1.2 * ti), atol=1e-14)


def test_slerp_short_way_round_when_q1_is_minus_q0():
    rng = np.random.default_rng(32)
    q0 = random_quaternions(rng, (20,))
    for t in (0.0, 0.3, 0.5, 1.0):
        out = R.slerp(q0, -q0, t)
        assert np.all(np.isfinite(out))
        assert same_rotation(out, q0, atol=1e-12)


def test_slerp_takes_the_short_arc_for_opposite_hemispheres():
    # 350 deg about z is -10 deg: the midpoint from 0 is -5 deg, not 175 deg.
    out = R.slerp(z_rotation(0.0), z_rotation(math.radians(350.0)), 0.5)
    assert same_rotation(out, z_rotation(math.radians(-5.0)), atol=1e-14)


def test_slerp_nearly_equal_quaternions():
    q0 = z_rotation(0.5)
    q1 = z_rotation(0.5 + 1e-9)
    out = R.slerp(q0, q1, 0.5)
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(np.linalg.norm(out), 1.0, atol=1e-15)
    assert same_rotation(out, z_rotation(0.5 + 0.5e-9), atol=1e-12)


# ----------------------------------------------------------------------------- normalise

@pytest.mark.parametrize('bad', [
    [0.0, 0.0, 0.0, 0.0],
    [math.nan, 0.0, 0.0, 1.0],
    [math.inf, 0.0, 0.0, 1.0],
    [[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0]],
    [[0.0, 0.0, 0.0, 1.0], [0.0, math.nan, 0.0, 1.0]],
    [1e-14, 0.0, 0.0, 0.0],
])
def test_quaternion_normalize_refuses_zero_and_non_finite(bad):
    with pytest.raises(ValueError):
        R.quaternion_normalize(bad)


def test_quaternion_normalize_scales_to_unit():
    out = R.quaternion_normalize([[0.0, 0.0, 3.0, 4.0], [2.0, 0.0, 0.0, 0.0]])
    np.testing.assert_allclose(out, [[0.0, 0.0, 0.6, 0.8], [1.0, 0.0, 0.0, 0.0]], atol=1e-15)


def test_functions_refuse_a_zero_quaternion():
    with pytest.raises(ValueError):
        R.quaternion_to_matrix([0.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError):
        R.rotate_vectors([0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    with pytest.raises(ValueError):
        R.slerp([0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], 0.5)
