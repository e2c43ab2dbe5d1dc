"""Compiled loops of the vision map (numba), used only by vision_model.py.

:func:`expose_grid` is :func:`~inhand_stereo.vision_model.observe_grid`'s geometry in one
pass over the grid's lines of cells: each centre into the rectified left camera, the nearest
pixel's depth (and object mask and spread), the ranges along the ray through the centre,
whether the cell is updated (module doc of vision_model.py) and its update by the model:
the same arithmetic as ``VisionModel.log_odds`` (numpy, the reference the tests compare
with), a line of cells at a time in a few scratch rows; optionally applied to the map in the same
pass. :func:`depth_surface` measures the depth's local spread for it
(``vision_model.depth_spread`` is the reference).

Why compiled and in one pass: an exposure touches every cell of the grid (343,000 at
70^3); as numpy expressions it made a dozen full-grid temporaries and ran at a quarter of
Open3D's ``UniformTSDFVolume.integrate`` on the same image and grid.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TypeVar, cast

import numba
import numpy as np
from numpy.typing import NDArray

__all__ = ['depth_surface', 'expose_grid']

MIN_DEPTH = 1e-3
_Function = TypeVar('_Function', bound=Callable[..., object])
Floats = NDArray[np.float64]


def _compiled(function: _Function) -> _Function:
    """``numba.njit(cache=True, nogil=True, error_model='numpy')`` keeping the Python
    signature for mypy. numpy's error model: a float division by zero gives inf or NaN
    instead of raising, so a division is not a branch and a loop with one is vectorised
    (expose_grid's projection: 4.0 -> 3.2 ms); none of these kernels divides by zero
    where it matters (w <= 0 is not seen either way)."""
    return cast(_Function, numba.njit(cache=True, nogil=True, error_model='numpy')(function))


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


# A confident free-space belief (mu = 0, sigma < 1/18: see model_log_odds) is most of the
# grid in front of a surface. exp(x) >= 1 + x + x^2/2 + x^3/6 for x >= 0 tells most of those
# cells without the exponential, and reciprocals save the divisions; the margin covers the
# rounding of both sides, so the answer is the one model_log_odds would give, to the bit.
_MARGIN = 1e-9
_CONFIDENT = (0.5 / 9.0) * (1.0 - _MARGIN)
_SIXTH = 1.0 / 6.0       # a product, not a division (the compiler keeps a division as it is)


@_inlined
def surely_confident_free(far_side: float, sigma_s: float, model: Floats, inv_epsilon: float,
                          inv_tau: float) -> bool:
    """True only if ``model_log_odds(far_side, ...)`` takes its confident branch at mu = 0
    (it may still when this is False)."""
    epsilon = model[0]
    in_front = far_side < -0.5 * epsilon * (1.0 + _MARGIN)    # then 0.5 + far_side / epsilon < 0
    x = (-far_side - 0.5 * epsilon) * inv_tau * (1.0 - _MARGIN)   # outside / tau, from below
    bound = 1.0 + x * (1.0 + x * (0.5 + x * _SIXTH))
    confident: bool = in_front & (sigma_s * inv_epsilon < _CONFIDENT * bound)
    return confident


@_compiled
def expose_grid(n: int, origin: Floats, resolution: float, matrix: Floats, offset: Floats,
                P: Floats, surface: NDArray[np.float32], band_behind: float, free_limit: float,
                model: Floats, log_odds: Floats,
                clamp_low: float, clamp_high: float, cells: NDArray[np.intp], updates: Floats,
                deltas: Floats, ranges: Floats) -> int:
    """The cells an exposure updates on the n^3 grid at ``origin`` (cells of edge
    ``resolution``, flat index (i n + j) n + k): their index, log-odds update, delta to the
    far side and measured range, written to the front of ``cells``, ``updates``,
    ``deltas`` and ``ranges`` (each n^3 long, or empty: not wanted). Returns how many.
    ``surface`` (H, W, 2): each pixel's depth and spread side by side (:func:`depth_surface`),
    so the one cache line a cell's pixel costs brings both and the object mask. ``log_odds``
    (n^3,), when not empty, gets the updates added and clamped to [clamp_low, clamp_high]
    in the same pass.

    The centres are ``GridSpec.cell_centres``' arithmetic and the camera coordinates the
    same sums in the same order (each axis' terms computed once per index), so the result
    is the numpy reference's to the bit."""
    height, width = surface.shape[0], surface.shape[1]
    apply = log_odds.shape[0] > 0
    want_cells, want_updates = cells.shape[0] > 0, updates.shape[0] > 0
    want_deltas, want_ranges = deltas.shape[0] > 0, ranges.shape[0] > 0
    lowest = model[8]
    inv_epsilon, inv_tau = 1.0 / model[0], 1.0 / model[1]
    half = resolution / 2.0
    noise_squared = model[4] > 0.5
    # terms[r, a, index]: matrix[r, a] times the centre's coordinate a at that index
    terms = np.empty((3, 3, n))
    for a in range(3):
        for index in range(n):
            centre = origin[a] + (index + 0.5) * resolution
            for r in range(3):
                terms[r, a, index] = matrix[r, a] * centre
    # one line of cells along k at a time, in passes over scratch rows: the projection
    # and the ranges, the pixels' reads, the model's cheap test, the rare full model, the
    # update; the passes without branches are vectorised by the compiler (as one loop with
    # a branch per test, the cells took twice as long)
    zs, cell_ranges = np.empty(n), np.empty(n)
    # each cell's pixel as an index into the flat surface: its depth there, its spread next
    pixels = np.empty(n, dtype=np.intp)
    flat = surface.reshape(-1)
    stored32, spread32 = np.empty(n, dtype=np.float32), np.empty(n, dtype=np.float32)
    seen = np.empty(n, dtype=np.bool_)
    measured_ranges, far_sides, spreads = np.empty(n), np.empty(n), np.empty(n)
    used, full = np.empty(n, dtype=np.bool_), np.empty(n, dtype=np.bool_)
    updates_line = np.empty(n)
    kept = 0
    for i in range(n):
        for j in range(n):
            ax = terms[0, 0, i] + terms[0, 1, j]
            ay = terms[1, 0, i] + terms[1, 1, j]
            az = terms[2, 0, i] + terms[2, 1, j]
            _project_line(ax, ay, az, terms, offset, P, flat, width, height, zs, cell_ranges, seen,
                          pixels, stored32, spread32)
            # the model's cheap test for every cell of the line, without branches (NaN where
            # unseen fails every test); the cells it does not settle are marked full
            any_full = False
            for k in range(n):
                stored = float(stored32[k]) if seen[k] else np.nan
                pixel_spread = float(spread32[k]) if seen[k] else np.nan
                z, cell_range = zs[k], cell_ranges[k]
                measured = abs(stored)
                measured_range = measured * cell_range / z
                behind = cell_range - measured_range      # > 0: the centre is behind the surface
                far_side = behind + half
                on_object = stored > 0.0
                spread = pixel_spread * cell_range / z
                growth = measured_range * measured_range if noise_squared else measured_range
                sigma_s = max(model[2] + model[3] * growth, spread)
                in_band = (on_object & (not behind > band_behind)) | \
                    ((not on_object) & (not far_side > free_limit))
                use = math.isfinite(stored) & math.isfinite(pixel_spread) & in_band
                confident = surely_confident_free(far_side, sigma_s, model, inv_epsilon, inv_tau)
                used[k] = use
                full[k] = use & (not confident)
                any_full |= use & (not confident)
                measured_ranges[k] = measured_range
                far_sides[k] = far_side
                spreads[k] = spread
                updates_line[k] = lowest
            if any_full:
                for k in range(n):
                    if full[k]:
                        updates_line[k] = model_log_odds(far_sides[k], measured_ranges[k],
                                                         spreads[k], model)
            line = (i * n + j) * n
            if apply:
                for k in range(n):
                    c = line + k
                    before = log_odds[c]
                    after = min(max(before + updates_line[k], clamp_low), clamp_high)
                    log_odds[c] = after if used[k] else before     # a select, not a branch
            if want_cells or want_updates or want_deltas or want_ranges:
                kept = _record_line(line, used, updates_line, far_sides, measured_ranges, kept,
                                    cells, updates, deltas, ranges)
            else:
                for k in range(n):
                    kept += used[k]
    return kept


@_inlined
def _project_line(ax: float, ay: float, az: float, terms: Floats, offset: Floats, P: Floats,
                  flat: NDArray[np.float32], width: int, height: int, zs: Floats,
                  cell_ranges: Floats, seen: NDArray[np.bool_], pixels: NDArray[np.intp],
                  stored: NDArray[np.float32], spread: NDArray[np.float32]) -> None:
    """A line of :func:`expose_grid`'s cells along k (``a*``: the i and j terms' sums): each
    centre's z and range, whether it is seen and on which pixel, and that pixel's stored
    depth and spread from ``flat`` (the surface, raveled; pixel 0's where unseen)."""
    for k in range(zs.shape[0]):
        x = ax + terms[0, 2, k] + offset[0]
        y = ay + terms[1, 2, k] + offset[1]
        z = az + terms[2, 2, k] + offset[2]
        w = P[2, 0] * x + P[2, 1] * y + P[2, 2] * z + P[2, 3]
        # pixel centres at integer coordinates (ROS): the nearest pixel
        u = np.rint((P[0, 0] * x + P[0, 1] * y + P[0, 2] * z + P[0, 3]) / w)
        v = np.rint((P[1, 0] * x + P[1, 1] * y + P[1, 2] * z + P[1, 3]) / w)
        # without branches (&, not and) so that the loop is vectorised
        inside = (z > MIN_DEPTH) & (w > 0.0) & (u >= 0.0) & (u < width) & \
            (v >= 0.0) & (v < height)
        seen[k] = inside
        pixels[k] = (int(v) * width + int(u)) * 2 if inside else 0
        zs[k] = z
        cell_ranges[k] = math.sqrt(x * x + y * y + z * z)
    # the reads on their own: a loop of loads only (the one that misses the cache), from
    # a precomputed flat index rather than the (H, W, 2) array's three
    for k in range(zs.shape[0]):
        stored[k] = flat[pixels[k]]
        spread[k] = flat[pixels[k] + 1]


@_inlined
def _record_line(line: int, used: NDArray[np.bool_], line_updates: Floats, far_sides: Floats,
                 measured_ranges: Floats, kept: int, cells: NDArray[np.intp], updates: Floats,
                 deltas: Floats, ranges: Floats) -> int:
    """The updated cells of a line (flat index of its first: ``line``) written to the
    wanted outputs of :func:`expose_grid` from ``kept`` on; returns the new count."""
    for k in range(used.shape[0]):
        if not used[k]:
            continue
        if cells.shape[0] > 0:
            cells[kept] = line + k
        if updates.shape[0] > 0:
            updates[kept] = line_updates[k]
        if deltas.shape[0] > 0:
            deltas[kept] = far_sides[k]
        if ranges.shape[0] > 0:
            ranges[kept] = measured_ranges[k]
        kept += 1
    return kept


@_compiled
def depth_surface(depth: NDArray[np.float32], mask: NDArray[np.bool_], window: int,
                  surface: NDArray[np.float32]) -> None:
    """``surface`` (H, W, 2) as :func:`expose_grid` reads it: in channel 0 the depth where
    it is finite and positive (NaN elsewhere), negated off the object (``mask`` (H, W), or
    (0, 0): all object), so a cell's one pixel read brings the mask too; in channel 1 the
    depth's local spread over a ``window`` square (odd; 0: no spread, zeros):
    ``vision_model.depth_spread``'s definition (the reference), a row at a time over a few
    padded row buffers (loops without branches, which the compiler vectorises) instead of
    five box filters and their full-image temporaries. The residuals in float32, the
    depth's own precision and the reference's (twice the lanes per vector: 1.62 -> 1.38 ms
    on a bundled pair), their running column sums in float64, which a row added and one
    taken away at each step would otherwise make drift (float32 sums: up to 2e-5 m off
    after 480 rows; these: 6e-8 m from the float64 version's spread). Both
    channels of a row are written in one pass when its spread is known: the interleaved
    stores of a row are contiguous, a channel written on its own is a scatter."""
    height, width = depth.shape
    has_mask = mask.shape[0] > 0
    row_spread = np.zeros(width, dtype=np.float32)
    if window == 0:
        for r in range(height):
            _write_row(depth, mask, has_mask, r, row_spread, surface)
        return
    half = window // 2
    need = window * window / 2.0          # at least half the window's pixels complete
    padded = width + 2 * half
    # rows r-1, r, r+1 (by r % 3) of the depth with 0 where there is none, and of 1 where
    # there is one; one column of zeros on each side (outside the image: no depth)
    filled = np.zeros((3, width + 2), dtype=np.float32)
    valid = np.zeros((3, width + 2), dtype=np.float32)
    three_sum = np.zeros(width + 2, dtype=np.float32)
    three_valid = np.zeros(width + 2, dtype=np.float32)
    # the last ``window`` rows (by r % window) of the complete flags (all nine neighbours
    # with a depth) and squared residuals from the 3x3 mean; their column sums with
    # ``half`` zeros on each side. The flags and their sums as integers: exact as the
    # float64 counts were, with twice the lanes per vector
    ring_count = np.zeros((window, width), dtype=np.int32)
    ring_square = np.zeros((window, width), dtype=np.float32)
    column_count = np.zeros(padded, dtype=np.int32)
    column_square = np.zeros(padded)
    row_count, row_square = np.zeros(width, dtype=np.int32), np.zeros(width)
    _load_row(depth, 0, filled[0], valid[0])
    for r in range(height + half):
        slot = r % window
        if r < height:                    # row r enters the window, row r - window leaves
            above, here, below = (r + 2) % 3, r % 3, (r + 1) % 3
            _load_row(depth, r + 1, filled[below], valid[below])
            for c in range(width + 2):
                three_sum[c] = filled[above, c] + filled[here, c] + filled[below, c]
                three_valid[c] = valid[above, c] + valid[here, c] + valid[below, c]
            for c in range(width):
                nine = three_valid[c] + three_valid[c + 1] + three_valid[c + 2]
                residual = filled[here, c + 1] - \
                    (three_sum[c] + three_sum[c + 1] + three_sum[c + 2]) / np.float32(9.0)
                complete = 1 if nine == np.float32(9.0) else 0
                square = np.float32(complete) * residual * residual
                # the leaving row's value out, then the entering one's in: the column sums'
                # order of operations, on which their rounding depends
                column_count[c + half] = column_count[c + half] - ring_count[slot, c] + complete
                column_square[c + half] = column_square[c + half] - ring_square[slot, c] + square
                ring_count[slot, c] = complete
                ring_square[slot, c] = square
        else:                             # past the last row: rows only leave
            for c in range(width):
                column_count[c + half] -= ring_count[slot, c]
                column_square[c + half] -= ring_square[slot, c]
                ring_count[slot, c] = 0
                ring_square[slot, c] = 0.0
        out = r - half                    # the row whose window is now complete
        if out < 0:
            continue
        row_count[:] = 0
        row_square[:] = 0.0
        for d in range(window):
            for c in range(width):
                row_count[c] += column_count[c + d]
                row_square[c] += column_square[c + d]
        for c in range(width):
            count = row_count[c]
            spread = math.sqrt(max(row_square[c], 0.0) / float(max(count, 1)))
            row_spread[c] = spread if count >= need else np.nan
        _write_row(depth, mask, has_mask, out, row_spread, surface)


@_inlined
def _load_row(depth: NDArray[np.float32], r: int, filled: NDArray[np.float32],
              valid: NDArray[np.float32]) -> None:
    """Row ``r`` of the depth into ``filled`` (0 where there is no depth) and ``valid`` (1
    where there is), from index 1; zeros if ``r`` is past the last row."""
    if r >= depth.shape[0]:
        filled[:] = 0.0
        valid[:] = 0.0
        return
    for c in range(depth.shape[1]):
        z = float(depth[r, c])
        ok = math.isfinite(z)
        filled[c + 1] = z if ok else 0.0
        valid[c + 1] = 1.0 if ok else 0.0


@_inlined
def _write_row(depth: NDArray[np.float32], mask: NDArray[np.bool_], has_mask: bool, r: int,
               spread: NDArray[np.float32], surface: NDArray[np.float32]) -> None:
    """Row ``r`` of ``surface``: the depth with the mask as its sign, and ``spread``."""
    for c in range(depth.shape[1]):
        z = depth[r, c]
        on_object = mask[r, c] if has_mask else True
        signed = z if on_object else -z
        surface[r, c, 0] = signed if math.isfinite(z) and z > 0.0 else np.float32(np.nan)
        surface[r, c, 1] = spread[c]
