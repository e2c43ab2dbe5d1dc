"""The global map from the local maps of touch and vision (paper eqs. 8-12).

Both local maps live on the same grid as log-odds: touch with the grid's ``prior``, vision
with a prior of 1/2 (log-odds 0 where it says nothing). Three ways to make the global map,
parameter ``fusion``:

* ``none``: the touch map alone (what the map was before vision).
* ``product`` (eqs. 8-9): ``P(O | Z_vis Z_touch) = alpha P(Z_vis | O) P(Z_touch | O) P(O)``;
  in log-odds the sensors' evidence adds: ``L = L_touch + L_vision`` (the vision map's
  prior is 1/2, so its log-odds are its evidence), clamped to the touch map's clamps.
* ``entropy`` (eqs. 10-12): each sensor's confidence is the entropy of its map (binary
  entropy per cell, :mod:`inhand_mapping.entropy`), the weights ``w_s = 1 - H_s / sum H``
  (eq. 11) and the global map the weighted sum of the local probabilities (eq. 12). The
  paper sums each entropy over the whole map (``entropy_radius`` 0: one weight per sensor);
  ``entropy_radius`` r > 0 sums it over the (2r + 1)^3 cells around each cell instead, so a
  sensor is trusted where it is confident (one weight per sensor and cell).

A weighted sum of probabilities cannot reach beyond its inputs: a cell only touch saw
(vision 1/2) ends between the two, below the occupied threshold unless touch's weight is
large (0.97 and 0.5 at equal weights: 0.735). Measured on the bundled sessions, eq. 12 as
written keeps about half of the map whatever the entropy's reach (F@5mm 0.49-0.50 on the
cats, touch alone 0.93-0.94). ``entropy_pooling``:

* ``linear``: eq. 12 as written, ``P = sum_s w_s P_s``;
* ``log`` (log-linear pooling, a weighted product of the sensors' beliefs): ``L = sum_s
  (w_s / max_s w_s) L_s`` in log-odds: the more confident sensor keeps its whole evidence,
  the other is discounted by the ratio of their weights, and a sensor that says nothing
  (L = 0) changes nothing, as in the product form.

The defaults (:data:`ENTROPY_RADIUS`, :data:`ENTROPY_POOLING`) are the entropy form that
measured best: local entropies (r = 1) pooled in log-odds (``bench_fusion.py``: F within
0.02 of the product form on 11 sessions, eq. 12 as written 0.4-0.8 below it). A user who
picks ``entropy`` gets the entropy fusion that works; the paper's eq. 12 as written is
radius 0 with linear pooling, still selectable.

The entropy form runs as compiled loops (numba): the entropy straight from the log-odds; the
local sums are a separable box filter.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple, TypeAlias

import numba
import numpy as np
from numpy.typing import NDArray

from inhand_mapping.entropy import entropy_weights

__all__ = ['ENTROPY_POOLING', 'ENTROPY_RADIUS', 'FUSIONS', 'POOLINGS', 'Fused', 'fuse',
           'fuse_entropy', 'fuse_product']

Fusion: TypeAlias = Literal['none', 'product', 'entropy']
FUSIONS: tuple[Fusion, ...] = ('none', 'product', 'entropy')
Grid: TypeAlias = NDArray[np.float64]


class Fused(NamedTuple):
    """The global map's log-odds and, for the entropy form, the weights it used."""

    log_odds: Grid
    touch_weight: Grid | float | None = None
    vision_weight: Grid | float | None = None


def fuse_product(touch: Grid, vision: Grid, clamp: tuple[float, float]) -> Fused:
    """Eq. 9 in log-odds: ``touch + vision`` (vision relative to its prior of 1/2),
    clamped to ``clamp`` (log-odds)."""
    fused: Grid = np.clip(touch + vision, clamp[0], clamp[1])
    return Fused(fused)


POOLINGS = ('linear', 'log')
ENTROPY_RADIUS = 1          # the defaults: the best entropy form (module doc)
ENTROPY_POOLING = 'log'
_LN2 = math.log(2.0)


@numba.njit(cache=True, inline='always')
def _sigmoid(x: float) -> float:
    if x >= 0.0:
        return 1.0 / (1.0 + math.exp(-x))
    e = math.exp(x)
    return e / (1.0 + e)


@numba.njit(cache=True, inline='always')
def _entropy_bits(log_odds: float) -> float:
    """Binary entropy (bits) of the probability with these log-odds, without forming p:
    H = log(1 + e^-|L|) + |L| sigmoid(-|L|), in nats, over ln 2."""
    a = abs(log_odds)
    return (math.log1p(math.exp(-a)) + a * _sigmoid(-a)) / _LN2


@numba.njit(cache=True)
def _entropies(touch: Grid, vision: Grid, h_touch: NDArray[np.float32],
               h_vision: NDArray[np.float32]) -> tuple[float, float]:
    """Each cell's entropy (bits) in both maps, and the totals. Most cells hold their map's
    prior (never observed): a run of equal values reuses the last entropy."""
    totals = np.zeros(2)
    for source, out, slot in ((touch.ravel(), h_touch.ravel(), 0),
                              (vision.ravel(), h_vision.ravel(), 1)):
        last_value, last_entropy = np.nan, 0.0
        total = 0.0
        for k in range(source.size):
            value = source[k]
            if value != last_value:
                last_value, last_entropy = value, _entropy_bits(value)
            out[k] = last_entropy
            total += last_entropy
        totals[slot] = total
    return totals[0], totals[1]


def _box_mean(values: NDArray[np.float32], radius: int, outside: float
              ) -> NDArray[np.float32]:
    """Mean over the (2r+1)^3 cube around each cell (cells beyond the grid count as
    ``outside``): a separable box filter (float32: entropies need no more, and it halves
    the memory the three passes sweep)."""
    from scipy import ndimage  # type: ignore[import-untyped]
    mean: NDArray[np.float32] = ndimage.uniform_filter(values, 2 * radius + 1,
                                                       mode='constant', cval=outside)
    return mean


@numba.njit(cache=True)
def _pool(touch: Grid, vision: Grid, w_touch: Grid, log: bool, low: float, high: float
          ) -> Grid:
    """Eq. 12 (linear: sum of probabilities) or the log-linear pool, clamped, as log-odds;
    ``w_touch`` per cell (the vision weight is 1 - w_touch: two sensors). Most cells hold
    both maps' priors: a run of equal inputs reuses the last result."""
    fused = np.empty_like(touch)
    flat_t, flat_v, flat_w, out = touch.ravel(), vision.ravel(), w_touch.ravel(), fused.ravel()
    p_low, p_high = _sigmoid(low), _sigmoid(high)
    last_t, last_v, last_w, last = np.nan, np.nan, np.nan, 0.0
    for k in range(flat_t.size):
        wt = flat_w[k]
        if flat_t[k] == last_t and flat_v[k] == last_v and wt == last_w:
            out[k] = last
            continue
        last_t, last_v, last_w = flat_t[k], flat_v[k], wt
        wv = 1.0 - wt
        if log:
            value = (wt * flat_t[k] + wv * flat_v[k]) / max(wt, wv)
            out[k] = min(max(value, low), high)
        elif flat_v[k] == 0.0 and wt == 1.0:
            out[k] = min(max(flat_t[k], low), high)
        else:
            p = wt * _sigmoid(flat_t[k]) + wv * _sigmoid(flat_v[k])
            p = min(max(p, p_low), p_high)
            out[k] = math.log(p / (1.0 - p))
        last = out[k]
    return fused


def fuse_entropy(touch: Grid, vision: Grid, clamp: tuple[float, float],
                 radius: int = ENTROPY_RADIUS, pooling: str = ENTROPY_POOLING) -> Fused:
    """Eqs. 10-12: the local maps weighted by ``1 - H_s / sum H``, the entropies over the
    whole map (``radius`` 0) or over the (2r+1)^3 cells around each cell, pooled by
    ``pooling`` (module doc)."""
    if radius < 0:
        raise ValueError(f'entropy radius must be >= 0, got {radius}')
    if pooling not in POOLINGS:
        raise ValueError(f"entropy pooling must be one of {', '.join(POOLINGS)}, got "
                         f'{pooling!r}')
    touch = np.ascontiguousarray(touch, dtype=np.float64)
    vision = np.ascontiguousarray(vision, dtype=np.float64)
    h_touch = np.empty(touch.shape, dtype=np.float32)
    h_vision = np.empty(vision.shape, dtype=np.float32)
    total_touch, total_vision = _entropies(touch, vision, h_touch, h_vision)
    if radius == 0:
        weight = float(entropy_weights([total_touch, total_vision])[0])      # eq. 11
        w_touch: Grid = np.full_like(touch, weight)
    else:
        # outside the grid counts as unknown (1 bit) for both sensors
        local_touch = _box_mean(h_touch, radius, 1.0)
        local_vision = _box_mean(h_vision, radius, 1.0)
        total_grid = local_touch + local_vision
        w_touch = np.where(total_grid > 1e-12,
                           1.0 - local_touch / np.where(total_grid > 1e-12, total_grid, 1.0),
                           0.5).astype(np.float64)
    fused = _pool(touch, vision, w_touch, pooling == 'log', clamp[0], clamp[1])
    if radius == 0:
        return Fused(fused, float(w_touch.flat[0]), 1.0 - float(w_touch.flat[0]))
    return Fused(fused, w_touch, 1.0 - w_touch)


def fuse(fusion: str, touch: Grid, vision: Grid | None, clamp: tuple[float, float],
         entropy_radius: int = ENTROPY_RADIUS, entropy_pooling: str = ENTROPY_POOLING
         ) -> Fused:
    """The global map's log-odds by ``fusion`` (module doc). ``touch`` holds the touch map's
    log-odds (its prior included), ``vision`` the vision map's (prior 1/2: log-odds 0), or
    None when there is no vision map yet (the touch map then is the global map); ``clamp``
    the touch map's clamps in log-odds."""
    if fusion not in FUSIONS:
        raise ValueError(f"fusion must be one of {', '.join(FUSIONS)}, got {fusion!r}")
    if fusion == 'none' or vision is None:
        return Fused(touch)
    if fusion == 'product':
        # eq. 9 with the prior once: the touch map's log-odds already hold it
        return fuse_product(touch, vision, clamp)
    # eq. 12 mixes the posteriors: the touch map's probabilities with its prior in them
    return fuse_entropy(touch, vision, clamp, entropy_radius, entropy_pooling)
