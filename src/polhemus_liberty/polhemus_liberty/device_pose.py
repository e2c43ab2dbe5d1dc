"""Device units and angles <-> SI poses (metres, quaternion x, y, z, w).

The driver turns a decoded :class:`~polhemus_liberty.protocol.StationRecord` into a pose;
the emulator turns a pose into a record carrying every quantity an output list may ask for.
Keeping both directions here means the unit and angle conventions live in one place.
"""

from __future__ import annotations

import numpy as np

from inhand_common.rotations import (
    euler_zyx_to_quaternion,
    matrix_to_quaternion,
    quaternion_canonical,
    quaternion_normalize,
    quaternion_to_euler_zyx,
    quaternion_to_matrix,
)
from polhemus_liberty.protocol import NO_ERROR, StationRecord

__all__ = ['METRES_PER_UNIT', 'pose_to_record', 'record_to_pose']

METRES_PER_UNIT = {'cm': 0.01, 'inch': 0.0254}


def record_to_pose(record: StationRecord, units: str) -> tuple[np.ndarray, np.ndarray] | None:
    """Position (m) and unit quaternion (x, y, z, w) of a record; None if it lacks either.

    Orientation preference: quaternion (exact), then Euler (singular at elevation +-90),
    then the direction-cosine matrix (its element order is not confirmed by the
    protocol notes; row-major R is assumed).
    """
    if record.position is None:
        return None
    position = np.asarray(record.position, dtype=float) * METRES_PER_UNIT[units]
    try:
        if record.quaternion_wxyz is not None:
            w, x, y, z = record.quaternion_wxyz
            quaternion = quaternion_normalize([x, y, z, w])
        elif record.euler_deg is not None:
            quaternion = euler_zyx_to_quaternion(*np.radians(record.euler_deg))
        elif record.direction_cosines is not None:
            quaternion = matrix_to_quaternion(np.reshape(record.direction_cosines, (3, 3)))
        else:
            return None
    except ValueError:  # a zero quaternion from a corrupted record
        return None
    if not (np.all(np.isfinite(position)) and np.all(np.isfinite(quaternion))):
        return None
    return position, quaternion


def pose_to_record(station: int, position_m, quaternion_xyzw, units: str, *,
                   command: str = 'C', frame_count: int = 0, timestamp_ms: int = 0,
                   distortion: int = 0) -> StationRecord:
    """A record holding every quantity of the pose, for any output list to pick from."""
    position = np.asarray(position_m, dtype=float) / METRES_PER_UNIT[units]
    q = quaternion_canonical(quaternion_normalize(quaternion_xyzw))
    euler = np.degrees(quaternion_to_euler_zyx(q))
    matrix = quaternion_to_matrix(q)
    return StationRecord(
        station=station, command=command, error=NO_ERROR,
        position=tuple(float(v) for v in position),
        euler_deg=tuple(float(v) for v in euler),
        direction_cosines=tuple(float(v) for v in matrix.reshape(9)),
        quaternion_wxyz=(float(q[3]), float(q[0]), float(q[1]), float(q[2])),
        timestamp_ms=int(timestamp_ms) & 0xFFFFFFFF,
        frame_count=int(frame_count) & 0xFFFFFFFF,
        stylus=0, distortion=int(distortion), external_sync=0,
    )
