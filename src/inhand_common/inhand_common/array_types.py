"""Array aliases that say what an array holds: its dtype in the type, its shape in the name.

numpy's typing carries the dtype but not the shape, so the shape goes into the alias's name and
its comment; mypy then catches a float array passed where indices are expected, and a reader
sees the shape at the signature.
"""

from __future__ import annotations

from typing import TypeAlias

import numpy as np
from numpy.typing import NDArray

__all__ = ['Bools', 'CellFloats', 'CellHits', 'Counts', 'FingerIds', 'Floats', 'Indices',
           'Matrices', 'Matrix3', 'Points', 'Quaternions', 'Records', 'Rows', 'StationIds',
           'Times', 'Vector3', 'Weights']

Floats: TypeAlias = NDArray[np.float64]        # any shape, float64
Bools: TypeAlias = NDArray[np.bool_]           # any shape, a mask
Indices: TypeAlias = NDArray[np.int64]         # (N,) or (N, 3) integer cell indices
Rows: TypeAlias = NDArray[np.intp]             # (N,) positions into another array (argsort, searchsorted)
Counts: TypeAlias = NDArray[np.intp]           # (N,) how many of something each entry has
Points: TypeAlias = NDArray[np.float64]        # (N, 3) positions (m)
Vector3: TypeAlias = NDArray[np.float64]       # (3,) one position or direction
Times: TypeAlias = NDArray[np.float64]         # (N,) times (s)
Weights: TypeAlias = NDArray[np.float64]       # (N,) per-sample weights in [0, 1]
Quaternions: TypeAlias = NDArray[np.float64]   # (N, 4) or (4,) unit quaternions x, y, z, w
Matrix3: TypeAlias = NDArray[np.float64]       # (3, 3) rotation matrix
Matrices: TypeAlias = NDArray[np.float64]      # (N, 3, 3) rotation matrices
FingerIds: TypeAlias = NDArray[np.int64]       # (N,) finger ids as the map counts them (>= 0)
StationIds: TypeAlias = NDArray[np.int32]      # (N,) finger ids (tracker stations) of registration
CellFloats: TypeAlias = NDArray[np.float64]    # (n, n, n) or flat (n^3,) one value per grid cell
CellHits: TypeAlias = NDArray[np.uint32]       # (n, n, n) or flat (n^3,) hit count per grid cell
Records: TypeAlias = NDArray[np.void]          # (N,) structured rows (one field per column)
