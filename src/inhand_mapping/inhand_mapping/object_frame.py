"""The object-centric frame (paper III.D): centre of mass and principal axes of the map.

The centre of mass is the probability-weighted mean of the cells above the threshold:
first moments over the zeroth, as the paper describes. The second central moments give
the principal axes (the paper points at moment invariants): their directions do not depend
on the frame the map was built in, which makes them a natural object-attached frame.
The ``object_centric`` frame of the interface contract is the ``object`` frame moved to
the centre of mass, axes unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from inhand_common.array_types import Matrix3, Points, Vector3

__all__ = ['ObjectFrame', 'object_frame']


@dataclass(frozen=True)
class ObjectFrame:
    centre_of_mass: Vector3     # (3,) map frame, metres
    principal_axes: Matrix3     # (3, 3) columns: unit axes, largest spread first, right-handed
    principal_extents: Vector3  # (3,) standard deviation (m) along each axis
    mass: float                    # sum of the probabilities (zeroth moment)
    cells: int                     # cells above the threshold

    def to_object_centric(self, points: ArrayLike) -> Points:
        """Map-frame points expressed in ``object_centric`` (origin at the centre of mass)."""
        centric: Points = np.asarray(points, dtype=float) - self.centre_of_mass
        return centric


def object_frame(centres: ArrayLike, probabilities: ArrayLike, threshold: float
                 ) -> ObjectFrame | None:
    """The frame of the cells whose probability exceeds ``threshold``; None if there are none."""
    all_centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    all_weights = np.asarray(probabilities, dtype=float).reshape(-1)
    keep = all_weights > threshold
    if not keep.any():
        return None
    occupied, weights = all_centres[keep], all_weights[keep]
    mass = float(weights.sum())
    centre = weights @ occupied / mass
    spread = occupied - centre
    covariance = (spread * weights[:, None]).T @ spread / mass
    variances, axes = np.linalg.eigh(covariance)
    order = np.argsort(variances)[::-1]
    variances, axes = variances[order], axes[:, order]
    # Fix the sign of each axis (eigenvectors come with an arbitrary sign) so the frame is
    # reproducible: first two point towards positive map coordinates, third makes it
    # right-handed.
    for k in range(2):
        if axes[np.argmax(np.abs(axes[:, k])), k] < 0:
            axes[:, k] = -axes[:, k]
    axes[:, 2] = np.cross(axes[:, 0], axes[:, 1])
    return ObjectFrame(centre_of_mass=centre, principal_axes=axes,
                       principal_extents=np.sqrt(np.maximum(variances, 0.0)), mass=mass,
                       cells=int(keep.sum()))
