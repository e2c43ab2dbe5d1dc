"""Rotations: Polhemus Euler Z-Y-X angles, unit quaternions and rotation matrices.

Conventions used everywhere in the workspace:

* Quaternions are ``(x, y, z, w)`` like ``geometry_msgs/Quaternion``. The Liberty sends
  ``(w, x, y, z)``; only the codec deals with that order.
* Euler angles are the Liberty's azimuth, elevation, roll in **radians**, applied as
  ``R = Rz(azimuth) @ Ry(elevation) @ Rx(roll)`` (intrinsic Z, then new Y, then new X).
  The device reports degrees; convert at the edge with ``numpy.radians``.
* A rotation maps vectors expressed in the rotated (sensor) frame into the reference
  (source) frame: ``p_source = R @ p_sensor``.

Every function accepts a single rotation or a stack (leading dimensions broadcast), so the
registration and simulation hot paths stay vectorised.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from inhand_common.array_types import Floats, Matrices, Quaternions

__all__ = [
    'euler_zyx_to_matrix',
    'euler_zyx_to_quaternion',
    'matrix_to_euler_zyx',
    'matrix_to_quaternion',
    'quaternion_canonical',
    'quaternion_conjugate',
    'quaternion_multiply',
    'quaternion_normalize',
    'quaternion_to_euler_zyx',
    'quaternion_to_matrix',
    'rotate_vectors',
    'slerp',
]


def _stack_last(*parts: ArrayLike) -> Floats:
    return np.stack(np.broadcast_arrays(*parts), axis=-1)


def euler_zyx_to_quaternion(azimuth: ArrayLike, elevation: ArrayLike, roll: ArrayLike
                            ) -> Quaternions:
    """Quaternion ``(x, y, z, w)`` of ``Rz(azimuth) Ry(elevation) Rx(roll)`` (radians)."""
    ha, he, hr = (np.asarray(a, dtype=float) * 0.5 for a in (azimuth, elevation, roll))
    ca, sa = np.cos(ha), np.sin(ha)
    ce, se = np.cos(he), np.sin(he)
    cr, sr = np.cos(hr), np.sin(hr)
    # Product qz(a) * qy(e) * qx(r), written out.
    w = ca * ce * cr + sa * se * sr
    x = ca * ce * sr - sa * se * cr
    y = ca * se * cr + sa * ce * sr
    z = sa * ce * cr - ca * se * sr
    return _stack_last(x, y, z, w)


def euler_zyx_to_matrix(azimuth: ArrayLike, elevation: ArrayLike, roll: ArrayLike) -> Matrices:
    """Rotation matrix ``Rz(azimuth) @ Ry(elevation) @ Rx(roll)`` (radians), shape (..., 3, 3)."""
    a, e, r = (np.asarray(v, dtype=float) for v in (azimuth, elevation, roll))
    ca, sa, ce, se, cr, sr = np.cos(a), np.sin(a), np.cos(e), np.sin(e), np.cos(r), np.sin(r)
    rows = [
        [ca * ce, ca * se * sr - sa * cr, ca * se * cr + sa * sr],
        [sa * ce, sa * se * sr + ca * cr, sa * se * cr - ca * sr],
        [-se, ce * sr, ce * cr],
    ]
    return np.stack([_stack_last(*row) for row in rows], axis=-2)


def matrix_to_euler_zyx(matrix: ArrayLike) -> Floats:
    """Azimuth, elevation, roll (radians) of a rotation matrix, stacked on the last axis.

    At elevation +-90 degrees azimuth and roll are not separable; the split chosen there
    (roll = 0) is one of the infinitely many valid ones.
    """
    m = np.asarray(matrix, dtype=float)
    sin_el = np.clip(-m[..., 2, 0], -1.0, 1.0)
    elevation = np.arcsin(sin_el)
    gimbal = np.abs(sin_el) > 1.0 - 1e-12
    azimuth = np.where(gimbal, np.arctan2(-m[..., 0, 1], m[..., 1, 1]),
                       np.arctan2(m[..., 1, 0], m[..., 0, 0]))
    roll = np.where(gimbal, 0.0, np.arctan2(m[..., 2, 1], m[..., 2, 2]))
    return _stack_last(azimuth, elevation, roll)


def quaternion_normalize(q: ArrayLike) -> Quaternions:
    """Unit quaternion; raises ValueError on a zero or non-finite quaternion."""
    quaternion = np.asarray(q, dtype=float)
    norm = np.linalg.norm(quaternion, axis=-1, keepdims=True)
    if not np.all(np.isfinite(norm)) or np.any(norm < 1e-12):
        raise ValueError('quaternion with zero or non-finite norm')
    unit: Quaternions = quaternion / norm
    return unit


def quaternion_canonical(q: ArrayLike) -> Quaternions:
    """The same rotation with ``w >= 0`` (q and -q are one rotation)."""
    quaternion = np.asarray(q, dtype=float)
    canonical: Quaternions = np.where(quaternion[..., 3:4] < 0.0, -quaternion, quaternion)
    return canonical


def quaternion_conjugate(q: ArrayLike) -> Quaternions:
    """Inverse of a unit quaternion."""
    inverse: Quaternions = np.asarray(q, dtype=float) * np.array([-1.0, -1.0, -1.0, 1.0])
    return inverse


def quaternion_multiply(q1: ArrayLike, q2: ArrayLike) -> Quaternions:
    """Hamilton product ``q1 * q2`` (apply q2 first, then q1)."""
    x1, y1, z1, w1 = np.moveaxis(np.asarray(q1, dtype=float), -1, 0)
    x2, y2, z2, w2 = np.moveaxis(np.asarray(q2, dtype=float), -1, 0)
    return _stack_last(
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
    )


def quaternion_to_matrix(q: ArrayLike) -> Matrices:
    """Rotation matrix of a quaternion ``(x, y, z, w)`` (normalised first), shape (..., 3, 3)."""
    x, y, z, w = np.moveaxis(quaternion_normalize(q), -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([_stack_last(*row) for row in rows], axis=-2)


def matrix_to_quaternion(matrix: ArrayLike) -> Quaternions:
    """Quaternion ``(x, y, z, w)`` with ``w >= 0`` of a rotation matrix.

    Shepperd's method: picks the largest of w, x, y, z to divide by, so it stays accurate
    for every rotation (the trace-only formula loses precision near 180 degrees).
    """
    m = np.asarray(matrix, dtype=float)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    candidates = np.stack([
        1.0 + m00 - m11 - m22,  # 4x^2
        1.0 - m00 + m11 - m22,  # 4y^2
        1.0 - m00 - m11 + m22,  # 4z^2
        1.0 + m00 + m11 + m22,  # 4w^2
    ], axis=-1)
    best = np.argmax(candidates, axis=-1)
    s = 2.0 * np.sqrt(np.maximum(np.take_along_axis(candidates, best[..., None], -1)[..., 0],
                                 1e-300))
    d21, d12 = m[..., 2, 1], m[..., 1, 2]
    d02, d20 = m[..., 0, 2], m[..., 2, 0]
    d10, d01 = m[..., 1, 0], m[..., 0, 1]
    by_x = _stack_last(0.25 * s, (d01 + d10) / s, (d02 + d20) / s, (d21 - d12) / s)
    by_y = _stack_last((d01 + d10) / s, 0.25 * s, (d12 + d21) / s, (d02 - d20) / s)
    by_z = _stack_last((d02 + d20) / s, (d12 + d21) / s, 0.25 * s, (d10 - d01) / s)
    by_w = _stack_last((d21 - d12) / s, (d02 - d20) / s, (d10 - d01) / s, 0.25 * s)
    q = np.choose(best[..., None], [by_x, by_y, by_z, by_w])
    return quaternion_canonical(quaternion_normalize(q))


def quaternion_to_euler_zyx(q: ArrayLike) -> Floats:
    """Azimuth, elevation, roll (radians) of a quaternion ``(x, y, z, w)``."""
    return matrix_to_euler_zyx(quaternion_to_matrix(q))


def rotate_vectors(q: ArrayLike, v: ArrayLike) -> Floats:
    """Rotate vectors ``v`` (..., 3) by quaternions ``q`` (..., 4): ``R(q) @ v``."""
    unit = quaternion_normalize(q)
    vectors = np.asarray(v, dtype=float)
    u = unit[..., :3]
    w = unit[..., 3:4]
    # v' = v + 2 w (u x v) + 2 u x (u x v): no matrix built, cheap for large stacks.
    uv = np.cross(u, vectors)
    rotated: Floats = vectors + 2.0 * (w * uv + np.cross(u, uv))
    return rotated


def slerp(q0: ArrayLike, q1: ArrayLike, fraction: ArrayLike) -> Quaternions:
    """Spherical linear interpolation from ``q0`` (fraction 0) to ``q1`` (fraction 1).

    Takes the short way round (flips ``q1`` when the dot product is negative) and falls
    back to normalised linear interpolation when the two are nearly equal.
    """
    start = quaternion_normalize(q0)
    end = quaternion_normalize(q1)
    t = np.asarray(fraction, dtype=float)[..., None]
    dot = np.sum(start * end, axis=-1, keepdims=True)
    end = np.where(dot < 0.0, -end, end)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-6
    safe = np.where(near, 1.0, sin_theta)
    w0 = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    w1 = np.where(near, t, np.sin(t * theta) / safe)
    return quaternion_normalize(w0 * start + w1 * end)
