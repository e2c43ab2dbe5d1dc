"""Pivot calibration: a finger's tip offset from its sensor's poses while the pad pivots.

The finger's pad rests in a small dimple (or on one fixed point of the table) and the hand
turns the finger about it, tilting it 30-60 degrees in several directions. The pad centre
``b`` (tracker frame) then stays put while the sensor moves, so for every pose
``(R_i, p_i)``::

    R_i o + p_i = b        i.e.     [R_i  -I] [o; b] = -p_i

with ``o`` the tip offset (sensor frame, tip_offsets.py): 3 equations per pose, 6 unknowns,
solved by linear least squares (the standard pivot calibration of tracked tools).

What makes a pivot poor, and is refused with one sentence saying what to do:

* **too little rotation**: with the finger turned by a few degrees, ``o`` and ``b`` trade
  off against each other and noise decides. The rotation is the largest angle between two
  of the poses; under ``min_rotation_deg`` (15) the pivot is refused.
* **rotation about one axis only**: the offset's component along that axis cannot be seen.
  The least squares give each unknown a standard error (``sigma^2 (A^T A)^-1``); an offset
  axis with a standard error over ``max_uncertainty`` (1 mm) is refused.
* **the pad slipped, or it was not a pivot**: the residual (RMS distance between each
  pose's predicted pad centre and ``b``) over ``max_residual`` (3 mm; 1 mm of tracker noise
  per axis gives about 1.7).

Which poses are the pivot: a finger's stream also holds it resting while the others pivot
(a still pose fits any offset, with its own pivot point, and would pull the solution) and
coming to the dimple and leaving it. :func:`pivot_window` keeps the longest stretch where
the finger keeps turning (over ``TURNING_DEG`` within +-``TURNING_WINDOW`` s, with pauses
under ``TURNING_PAUSE`` s bridged). Within it, poses that still do not pivot are left out
robustly: after a first solution, poses whose pad prediction is further
from ``b`` than ``OUTLIER_FACTOR`` times the median (and at least ``OUTLIER_FLOOR``) are
dropped and the system solved again, a few times; the share kept is reported and under
``MIN_KEPT`` the pivot is refused.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from inhand_common.rotations import quaternion_normalize, quaternion_to_matrix

__all__ = ['MIN_KEPT', 'MIN_POSES', 'PivotLimits', 'PivotResult', 'pivot_window', 'solve_pivot']

MIN_POSES = 30          # fewer poses than this are not a pivot (one second at 30 Hz)
MIN_KEPT = 0.5          # at least this share of the poses must be the pivot itself
OUTLIER_FACTOR = 3.0    # a pose further than this many median residuals from b is not pivoting
OUTLIER_FLOOR = 0.003   # m: ... and further than this
ROUNDS = 5              # robust re-solves
ROTATION_SAMPLE = 400   # poses compared pairwise for the rotation range
TURNING_DEG = 5.0       # a finger turning this much within +-TURNING_WINDOW is pivoting
TURNING_WINDOW = 0.5    # s
TURNING_PAUSE = 1.0     # s: a shorter still moment inside a pivot does not end it


@dataclass(frozen=True)
class PivotLimits:
    """When a pivot is refused (see the module docstring)."""

    min_rotation_deg: float = 15.0
    max_residual: float = 0.003     # m, RMS
    max_uncertainty: float = 0.001  # m, standard error of each offset axis


@dataclass(frozen=True)
class PivotResult:
    """One finger's pivot: the offset (sensor frame), the pivot point (tracker frame), how
    well they fit, and why the pivot is refused (``problem``, None when accepted)."""

    offset: np.ndarray          # (3,) m, sensor frame
    pivot: np.ndarray           # (3,) m, tracker frame
    residual: float             # m, RMS over the poses kept
    uncertainty: np.ndarray     # (3,) m, standard error of each offset axis
    rotation_deg: float         # largest angle between two poses kept
    poses: int                  # poses given
    kept: int                   # poses used (the pivot itself)
    problem: str | None

    @property
    def accepted(self) -> bool:
        return self.problem is None

    def summary(self, name: str) -> str:
        """One line for a person at the bench."""
        o = ', '.join(f'{1000 * v:+.1f}' for v in self.offset)
        line = (f'{name}: offset [{o}] mm, residual {1000 * self.residual:.2f} mm RMS, '
                f'turned {self.rotation_deg:.0f} deg, {self.kept} of {self.poses} poses')
        return line + (f': REFUSED, {self.problem}' if self.problem else '')


def _rotation_range_deg(quaternions: np.ndarray) -> float:
    """The largest angle between two of the orientations (at most ROTATION_SAMPLE of them,
    evenly spaced, compared pairwise)."""
    step = max(1, len(quaternions) // ROTATION_SAMPLE)
    q = quaternions[::step]
    dots = np.clip(np.abs(q @ q.T), 0.0, 1.0)
    return math.degrees(2.0 * math.acos(float(dots.min())))


def pivot_window(times: ArrayLike, quaternions: ArrayLike) -> np.ndarray:
    """Which poses (times (N,) s, ascending; quaternions (N, 4)) form the finger's pivot: the
    longest stretch of time where it keeps turning (module docstring). All False when it
    never turns."""
    t = np.asarray(times, dtype=float).reshape(-1)
    q = quaternion_normalize(np.asarray(quaternions, dtype=float).reshape(-1, 4))
    if len(t) < 2:
        return np.zeros(len(t), dtype=bool)
    before = np.clip(np.searchsorted(t, t - TURNING_WINDOW), 0, len(t) - 1)
    after = np.clip(np.searchsorted(t, t + TURNING_WINDOW, side='right') - 1, 0, len(t) - 1)
    dots = np.clip(np.abs(np.sum(q[before] * q[after], axis=1)), 0.0, 1.0)
    turning = np.degrees(2.0 * np.arccos(dots)) > TURNING_DEG
    if not turning.any():
        return turning
    # Runs of turning poses; runs separated by a pause under TURNING_PAUSE are one.
    index = np.flatnonzero(turning)
    breaks = np.flatnonzero(np.diff(t[index]) > TURNING_PAUSE)
    starts = np.concatenate([[0], breaks + 1])
    ends = np.concatenate([breaks, [len(index) - 1]])
    longest = int(np.argmax(t[index[ends]] - t[index[starts]]))
    window = np.zeros(len(t), dtype=bool)
    window[index[starts[longest]]:index[ends[longest]] + 1] = True
    return window


def _system(rotations: np.ndarray) -> np.ndarray:
    """The matrix A of [R_i -I][o; b] = -p_i, (3N, 6)."""
    a = np.empty((len(rotations), 3, 6))
    a[:, :, :3] = rotations
    a[:, :, 3:] = -np.eye(3)
    return a.reshape(-1, 6)


def _pad_distances(rotations: np.ndarray, positions: np.ndarray, solution: np.ndarray
                   ) -> np.ndarray:
    """Each pose's distance from its pad centre R_i o + p_i to the pivot point b."""
    pads = np.einsum('nij,j->ni', rotations, solution[:3]) + positions
    return np.linalg.norm(pads - solution[3:], axis=1)


def solve_pivot(positions: ArrayLike, quaternions: ArrayLike,
                limits: PivotLimits = PivotLimits()) -> PivotResult:
    """The tip offset and pivot point of one finger's poses during a pivot: ``positions``
    (N, 3) m and ``quaternions`` (N, 4) x, y, z, w, the sensor's poses in the tracker frame.
    Never raises for a poor pivot: the result says why it is refused."""
    p = np.asarray(positions, dtype=float).reshape(-1, 3)
    q = np.asarray(quaternions, dtype=float).reshape(-1, 4)
    if len(p) != len(q):
        raise ValueError(f'{len(p)} positions but {len(q)} quaternions')
    finite = np.isfinite(p).all(axis=1) & np.isfinite(q).all(axis=1) \
        & (np.linalg.norm(q, axis=1) > 1e-9)
    p, q = p[finite], quaternion_normalize(q[finite])
    given = int(finite.size)
    if len(p) < MIN_POSES:
        nan3 = np.full(3, math.nan)
        return PivotResult(nan3, nan3, math.nan, nan3, 0.0, given, len(p),
                           f'{len(p)} valid poses, at least {MIN_POSES} needed: pivot for '
                           'a few seconds')
    rotations = quaternion_to_matrix(q)
    kept = np.ones(len(p), dtype=bool)
    for _ in range(ROUNDS):
        solution, *_ = np.linalg.lstsq(_system(rotations[kept]), -p[kept].reshape(-1), rcond=None)
        distance = _pad_distances(rotations, p, solution)
        bound = max(OUTLIER_FACTOR * float(np.median(distance[kept])), OUTLIER_FLOOR)
        agree = distance <= bound
        if np.array_equal(agree, kept) or np.count_nonzero(agree) < MIN_POSES:
            break
        kept = agree
    else:
        solution, *_ = np.linalg.lstsq(_system(rotations[kept]), -p[kept].reshape(-1), rcond=None)
        distance = _pad_distances(rotations, p, solution)
    offset, pivot = solution[:3], solution[3:]
    residuals = distance[kept]
    residual = float(np.sqrt(np.mean(residuals ** 2)))
    n_kept = int(np.count_nonzero(kept))
    # Noise variance per equation from the fit (3 per pose, 6 unknowns); the unknowns'
    # covariance is that times (A^T A)^-1.
    variance = float(np.sum(residuals ** 2)) / max(3 * n_kept - 6, 1)
    a = _system(rotations[kept])
    uncertainty = np.sqrt(np.maximum(np.diag(np.linalg.pinv(a.T @ a))[:3] * variance, 0.0))
    rotation = _rotation_range_deg(q[kept])
    problem = None
    if n_kept < MIN_KEPT * len(p):
        problem = (f'only {n_kept} of {len(p)} poses agree on one pivot point: keep the pad '
                   'in the dimple while turning the finger')
    elif rotation < limits.min_rotation_deg:
        problem = (f'the finger turned {rotation:.0f} deg, at least '
                   f'{limits.min_rotation_deg:.0f} needed: tilt it 30-60 deg in several '
                   'directions')
    elif residual > limits.max_residual:
        problem = (f'residual {1000 * residual:.1f} mm RMS over {1000 * limits.max_residual:.1f}:'
                   ' the pad slipped or was not resting on one point')
    elif uncertainty.max() > limits.max_uncertainty:
        axis = 'xyz'[int(np.argmax(uncertainty))]
        problem = (f'the offset along the sensor {axis} axis is uncertain by '
                   f'{1000 * uncertainty.max():.1f} mm (over '
                   f'{1000 * limits.max_uncertainty:.1f}): tilt the finger about more than '
                   'one axis')
    return PivotResult(offset=offset, pivot=pivot, residual=residual, uncertainty=uncertainty,
                       rotation_deg=rotation, poses=given, kept=n_kept, problem=problem)
