"""Entropy of occupancy maps (paper eq. 10) and the entropy weights of eq. 11.

Eq. 10 sums ``-P log P`` over the cells of a map. A cell's full uncertainty is the binary
entropy ``-(p log p + (1 - p) log(1 - p))``: 1 bit at p = 0.5 (nothing known), 0 at 0 or 1.
Both are here; the fusion weights use the binary form so that a map that is sure a cell is
empty counts as confident too. Logarithms are base 2 (bits).
"""

from __future__ import annotations

import numpy as np

__all__ = ['cell_entropy', 'entropy_weights', 'eq10_entropy', 'map_entropy']


def _xlog2x(p: np.ndarray) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    with np.errstate(divide='ignore', invalid='ignore'):
        return np.where(p > 0.0, p * np.log2(np.where(p > 0.0, p, 1.0)), 0.0)


def cell_entropy(p) -> np.ndarray:
    """Binary entropy of each cell's occupancy probability, in bits (0 log 0 = 0)."""
    p = np.asarray(p, dtype=float)
    return -(_xlog2x(p) + _xlog2x(1.0 - p))


def map_entropy(p) -> float:
    """Sum of the cells' binary entropies (bits)."""
    return float(cell_entropy(p).sum())


def eq10_entropy(p) -> float:
    """The paper's eq. 10 literally: ``-sum_i P_i log2 P_i`` over the cells (bits)."""
    return float(-_xlog2x(p).sum())


def entropy_weights(entropies) -> np.ndarray:
    """Eq. 11: ``w_s = 1 - H_s / sum_k H_k`` for each sensor's map entropy ``H_s``.

    The less uncertain map gets the larger weight. With two sensors the weights sum to 1;
    with S sensors they sum to S - 1, so they are normalised to sum to 1 for use as
    ``P(w)`` in eq. 12. All-zero entropies (every map certain) give equal weights.
    """
    h = np.asarray(entropies, dtype=float)
    total = h.sum()
    if total <= 0.0:
        return np.full(h.shape, 1.0 / h.size)
    w = 1.0 - h / total
    return w / w.sum() if w.sum() > 0 else np.full(h.shape, 1.0 / h.size)
