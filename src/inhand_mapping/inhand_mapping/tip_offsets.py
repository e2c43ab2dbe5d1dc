"""From the fingertip sensor to the finger pad: the tip offset.

On a real bench the Liberty sensor is taped on the fingernail (or the back of the
fingertip), not at the point that touches the object. The finger pad's centre is a fixed
point of the sensor's own frame, about a centimetre from it: the *tip offset* ``o``
(metres, sensor frame, one per finger). With the sensor at ``p`` and orientation ``q``
(quaternion x, y, z, w, the driver's pose in the tracker frame), the pad centre is::

    pad = p + R(q) o

Both ``p`` and ``q`` are the sensor's pose at the same stamp (one tracker frame), so no
interpolation is involved: the offset is applied per sample, before the sample is
registered into the object frame (registration.py). The driver keeps publishing the raw
sensor poses, so bags stay raw and a wrong offset is fixed by replaying with another.

How to measure ``o``: pivot calibration (pivot_calibration.py, ``calibrate_fingertips``).

The pad is round: a ball of radius ``r`` (``pad_radius``) whose centre stays one radius off
the surface it touches. The point registered is the contact, one radius from the pad
centre towards the surface::

    contact = pad + r R(q) u,     u = o / |o|   (u = -z when o = 0)

``u`` is the direction from the sensor on the nail to the pad centre, in the sensor's frame:
the way the pad faces. The surface normal is not measured, and a finger rolled or pitched
by an angle ``a`` off the normal would put the contact ``r (1 - cos a)`` too far out along
the normal (0.4 mm for a 7 mm pad at 20 degrees, 2 mm at 45) and ``r sin a`` along the
surface. So the registrar uses ``u`` only where the pads have not yet traced the surface
around a point: elsewhere the direction is the normal of the sheet of pad centres before
it (pad_normals.py).

The parameter is a flat list (ROS 2 parameters have no nested lists): ``x, y, z`` per finger
in the order of ``finger_names``, or one ``x, y, z`` for every finger.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from inhand_common.array_types import Bools, Points, StationIds
from inhand_common.rotations import rotate_vectors

__all__ = ['MAX_PAD_RADIUS', 'MAX_TIP_OFFSET', 'TipOffsets', 'tip_offsets_problem']

MAX_TIP_OFFSET = 0.1   # m: a pad further than this from its sensor is not a fingertip
MAX_PAD_RADIUS = 0.02  # m: a pad this round is not a fingertip


def tip_offsets_problem(values: Sequence[float], finger_names: Sequence[str]) -> str | None:
    """Why the flat ``tip_offsets`` parameter does not fit ``finger_names`` (None when it does)."""
    fingers = len(finger_names)
    if len(values) in (3, 3 * fingers):
        return None
    return (f"parameter 'tip_offsets' has {len(values)} numbers: allowed is 3 (one x, y, z for "
            f'every finger) or {3 * fingers} (x, y, z for each of {", ".join(finger_names)})')


class TipOffsets:
    """Per-finger offsets of the pad centre in the sensor frame: ``offsets`` (F, 3), metres;
    and the pad's radius ``pad_radius`` (m, every finger)."""

    def __init__(self, offsets: ArrayLike, pad_radius: float = 0.0):
        table = np.asarray(offsets, dtype=float).reshape(-1, 3)
        if not np.isfinite(table).all():
            raise ValueError('tip offsets must be finite numbers of metres')
        if not 0.0 <= pad_radius <= MAX_PAD_RADIUS:
            raise ValueError(f'pad radius {pad_radius} m: allowed is [0, {MAX_PAD_RADIUS}]')
        self.offsets: Points = table
        self.pad_radius = float(pad_radius)
        # Where each pad faces, in its sensor's frame: from the sensor towards the pad.
        lengths = np.linalg.norm(table, axis=1, keepdims=True)
        self.facing: Points = np.where(lengths > 0.0, table / np.maximum(lengths, 1e-12),
                                       np.array([[0.0, 0.0, -1.0]]))

    @classmethod
    def from_parameter(cls, values: Sequence[float], fingers: int, pad_radius: float = 0.0
                       ) -> TipOffsets:
        """From the flat parameter: 3 values for every finger, or 3 per finger."""
        flat = np.asarray(values, dtype=float).ravel()
        if flat.size == 3:
            flat = np.tile(flat, fingers)
        if flat.size != 3 * fingers:
            raise ValueError(f'tip offsets: {flat.size} numbers for {fingers} fingers')
        return cls(flat.reshape(fingers, 3), pad_radius)

    @property
    def zero(self) -> bool:
        """True when every contact is at its sensor (the map is the raw positions')."""
        return not self.offsets.any() and self.pad_radius == 0.0

    def as_parameter(self) -> list[float]:
        """The flat parameter value."""
        return [float(v) for v in self.offsets.ravel()]

    def pads(self, positions: Points, quaternions: ArrayLike, fingers: StationIds
             ) -> tuple[Points, Points, Bools]:
        """The pad centres and the unit directions the pads face (both (N, 3), the frame of
        ``positions``) of sensor poses (N, 3) + (N, 4) of ``fingers`` (N,), and which rows
        are valid: a finger beyond the table, or a non-finite or zero quaternion, cannot be
        moved to its pad (its row is returned unchanged, facing zero, flagged False)."""
        q = np.asarray(quaternions, dtype=float).reshape(-1, 4)
        known = (fingers >= 0) & (fingers < len(self.offsets))
        norms = np.linalg.norm(q, axis=1)
        valid = known & np.isfinite(norms) & (norms > 1e-9)
        centres = np.array(positions, dtype=float, copy=True)
        facing = np.zeros_like(centres)
        if valid.any():
            mine = fingers[valid]
            centres[valid] += rotate_vectors(q[valid], self.offsets[mine])
            facing[valid] = rotate_vectors(q[valid], self.facing[mine])
        return centres, facing, valid
