"""Compiled inner loop of the vision map (numba), used only by vision_model.py.

:func:`select_cells` is :func:`~inhand_stereo.vision_model.observe_grid`'s geometry in one
pass over the grid's cells: each centre into the rectified left camera, the nearest
pixel's depth (and object mask and spread), the ranges along the ray through the centre,
whether the cell is updated (module doc of vision_model.py) and its update by the model:
the same arithmetic as ``VisionModel.log_odds`` (numpy, the reference the tests compare
with), one cell at a time without temporaries.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TypeVar, cast

import numba
import numpy as np
from numpy.typing import NDArray

__all__ = ['select_cells']

MIN_DEPTH = 1e-3
_Function = TypeVar('_Function', bound=Callable[..., object])
Floats = NDArray[np.float64]


def _compiled(function: _Function) -> _Function:
    """``numba.njit(cache=True, nogil=True)`` keeping the Python signature for mypy."""
    return cast(_Function, numba.njit(cache=True, nogil=True)(function))


_SQRT2 = math.sqrt(2.0)
_SQRT2PI = math.sqrt(2.0 * math.pi)


def _inlined(function: _Function) -> _Function:
    return cast(_Function, numba.njit(cache=True, nogil=True, inline='always')(function))


@_inlined
def _phi(x: float) -> float:
    return 0.5 * math.erfc(-x / _SQRT2)


@_inlined
def model_log_odds(delta: float, measured_range: float, spread: float, model: Floats) -> float:
    """The vision model's clamped log-odds update (VisionModel.log_odds, one cell);
    ``model`` = [epsilon, tau, sigma_min, zeta, stereo noise (0/1), mean update (0/1),
    p_free, p_occupied, logit(p_free), logit(p_occupied)]."""
    epsilon, tau, sigma_min, zeta = model[0], model[1], model[2], model[3]
    growth = measured_range * measured_range if model[4] > 0.5 else measured_range
    sigma_s = max(sigma_min + zeta * growth, spread)
    mu = min(max(0.5 + delta / epsilon, 0.0), 1.0)
    outside = max(abs(delta) - epsilon / 2.0, 0.0)
    sigma = max(sigma_s / epsilon * math.exp(-outside / tau), 1e-9)
    if (mu == 0.0 or mu == 1.0) and sigma < 0.5 / 9.0:
        # a confident belief at 0 or 1 (most of the free space in front): P(O) is within
        # Phi(-9) ~ 1e-19 of it, far inside the clamps, whichever reading
        return float(model[8] if mu == 0.0 else model[9])
    if model[5] > 0.5:     # the mean of the belief truncated to [0, 1]
        a, b = (0.0 - mu) / sigma, (1.0 - mu) / sigma
        mass = max(_phi(b) - _phi(a), 1e-300)
        p = mu + sigma * (math.exp(-0.5 * a * a) - math.exp(-0.5 * b * b)) / _SQRT2PI / mass
        p = min(max(p, 0.0), 1.0)
    else:                  # its mass above 1/2
        p = _phi((mu - 0.5) / sigma)
    p = min(max(p, model[6]), model[7])
    return math.log(p / (1.0 - p))


@_compiled
def select_cells(centres: Floats, matrix: Floats, offset: Floats, P: Floats,
                 surface: NDArray[np.float32], mask: NDArray[np.bool_], resolution: float,
                 band_behind: float, free_limit: float, model: Floats
                 ) -> tuple[NDArray[np.intp], Floats, Floats, Floats]:
    """(cells, log-odds update, delta to the far side, measured range) of the cells an
    exposure updates. ``surface`` (H, W, 2): each pixel's depth and spread side by side,
    so the one cache line a cell's pixel costs brings both (the pixels a grid's cells
    land on are scattered over the image); ``mask`` of shape (0, 0) when not given."""
    count = centres.shape[0]
    height, width = surface.shape[0], surface.shape[1]
    has_mask = mask.shape[0] > 0
    cells = np.empty(count, dtype=np.intp)
    deltas = np.empty(count)
    ranges = np.empty(count)
    updates = np.empty(count)
    kept = 0
    half = resolution / 2.0
    for k in range(count):
        x = matrix[0, 0] * centres[k, 0] + matrix[0, 1] * centres[k, 1] + \
            matrix[0, 2] * centres[k, 2] + offset[0]
        y = matrix[1, 0] * centres[k, 0] + matrix[1, 1] * centres[k, 1] + \
            matrix[1, 2] * centres[k, 2] + offset[1]
        z = matrix[2, 0] * centres[k, 0] + matrix[2, 1] * centres[k, 1] + \
            matrix[2, 2] * centres[k, 2] + offset[2]
        w = P[2, 0] * x + P[2, 1] * y + P[2, 2] * z + P[2, 3]
        if not (z > MIN_DEPTH and w > 0.0):
            continue
        # pixel centres at integer coordinates (ROS): the nearest pixel
        u = np.rint((P[0, 0] * x + P[0, 1] * y + P[0, 2] * z + P[0, 3]) / w)
        v = np.rint((P[1, 0] * x + P[1, 1] * y + P[1, 2] * z + P[1, 3]) / w)
        if not (0 <= u < width and 0 <= v < height):
            continue
        row, column = int(v), int(u)
        measured = float(surface[row, column, 0])
        if not (math.isfinite(measured) and measured > 0.0):
            continue
        pixel_spread = float(surface[row, column, 1])
        if not math.isfinite(pixel_spread):
            continue
        cell_range = math.sqrt(x * x + y * y + z * z)
        measured_range = measured * cell_range / z
        behind = cell_range - measured_range          # > 0: the centre is behind the surface
        far_side = behind + half
        on_object = mask[row, column] if has_mask else True
        if on_object:
            if behind > band_behind:
                continue
        elif far_side > free_limit:
            continue
        cells[kept] = k
        deltas[kept] = far_side
        ranges[kept] = measured_range
        updates[kept] = model_log_odds(far_side, measured_range, pixel_spread * cell_range / z,
                                       model)
        kept += 1
    return cells[:kept], updates[:kept], deltas[:kept], ranges[:kept]
