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

Plain numpy (scipy's box filter for the local sums); a full 70^3 grid fuses in a few ms.
"""

from __future__ import annotations

from typing import Literal, NamedTuple, TypeAlias

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter  # type: ignore[import-untyped]

from inhand_mapping.entropy import cell_entropy

__all__ = ['FUSIONS', 'POOLINGS', 'Fused', 'fuse', 'fuse_entropy', 'fuse_product']

Fusion: TypeAlias = Literal['none', 'product', 'entropy']
FUSIONS: tuple[Fusion, ...] = ('none', 'product', 'entropy')
Grid: TypeAlias = NDArray[np.float64]


class Fused(NamedTuple):
    """The global map's log-odds and, for the entropy form, the weights it used."""

    log_odds: Grid
    touch_weight: Grid | float | None = None
    vision_weight: Grid | float | None = None


def _probability(log_odds: Grid) -> Grid:
    p: Grid = 1.0 / (1.0 + np.exp(-log_odds))
    return p


def _log_odds(p: Grid, clamp: tuple[float, float]) -> Grid:
    low, high = clamp
    q = np.clip(p, 1.0 / (1.0 + np.exp(-low)), 1.0 / (1.0 + np.exp(-high)))
    log_odds: Grid = np.log(q / (1.0 - q))
    return log_odds


def fuse_product(touch: Grid, vision: Grid, clamp: tuple[float, float]) -> Fused:
    """Eq. 9 in log-odds: ``touch + vision`` (vision relative to its prior of 1/2),
    clamped to ``clamp`` (log-odds)."""
    fused: Grid = np.clip(touch + vision, clamp[0], clamp[1])
    return Fused(fused)


POOLINGS = ('linear', 'log')


def _pool(w_touch: Grid | float, w_vision: Grid | float, touch: Grid, vision: Grid,
          p_touch: Grid, p_vision: Grid, pooling: str, clamp: tuple[float, float]) -> Grid:
    if pooling == 'linear':                                        # eq. 12
        return _log_odds(w_touch * p_touch + w_vision * p_vision, clamp)
    strongest = np.maximum(w_touch, w_vision)
    pooled: Grid = np.clip((w_touch * touch + w_vision * vision) / strongest, *clamp)
    return pooled


def fuse_entropy(touch: Grid, vision: Grid, clamp: tuple[float, float],
                 radius: int = 0, pooling: str = 'linear') -> Fused:
    """Eqs. 10-12: the local maps weighted by ``1 - H_s / sum H``, the entropies over the
    whole map (``radius`` 0) or over the (2r+1)^3 cells around each cell, pooled by
    ``pooling`` (module doc)."""
    if radius < 0:
        raise ValueError(f'entropy radius must be >= 0, got {radius}')
    if pooling not in POOLINGS:
        raise ValueError(f"entropy pooling must be one of {', '.join(POOLINGS)}, got "
                         f'{pooling!r}')
    p_touch, p_vision = _probability(touch), _probability(vision)
    h_touch, h_vision = cell_entropy(p_touch), cell_entropy(p_vision)
    if radius == 0:
        total_touch, total_vision = float(h_touch.sum()), float(h_vision.sum())
        total = total_touch + total_vision
        w_touch = 0.5 if total <= 0 else 1.0 - total_touch / total
        w_vision = 1.0 - w_touch      # two sensors: the weights of eq. 11 sum to 1
        return Fused(_pool(w_touch, w_vision, touch, vision, p_touch, p_vision, pooling, clamp),
                     w_touch, w_vision)
    size = 2 * radius + 1
    # Means over the cube (the sums divided by its cell count: the ratio is the same);
    # outside the grid counts as unknown (1 bit).
    local_touch = uniform_filter(h_touch, size=size, mode='constant', cval=1.0)
    local_vision = uniform_filter(h_vision, size=size, mode='constant', cval=1.0)
    total_grid = local_touch + local_vision
    safe = np.where(total_grid > 1e-12, total_grid, 1.0)
    w_touch_grid: Grid = np.where(total_grid > 1e-12, 1.0 - local_touch / safe, 0.5)
    w_vision_grid: Grid = 1.0 - w_touch_grid
    return Fused(_pool(w_touch_grid, w_vision_grid, touch, vision, p_touch, p_vision, pooling,
                       clamp), w_touch_grid, w_vision_grid)


def fuse(fusion: str, touch: Grid, vision: Grid | None, clamp: tuple[float, float],
         entropy_radius: int = 0, entropy_pooling: str = 'linear') -> Fused:
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
