"""The regions of a map: the most explored cells (the cells with the most hits) and the first
touched ones. Plain numpy, no ROS and no drawing: the map pictures (``regions.png``,
``map_figures.draw_regions``) and the live view (``inhand_view``) share the definition.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ['regions']

Mask = NDArray[np.bool_]


def regions(hits: ArrayLike, first_touch: ArrayLike, top_fraction: float = 0.1,
            first_fraction: float = 0.1) -> tuple[Mask, Mask, float, float]:
    """(most explored mask, first touched mask, hit count cut, first-touch cut in seconds).

    Most explored: hit cells whose hit count reaches the top ``top_fraction`` (hits at or
    above the (1 - top_fraction) quantile of the hit cells' counts). First touched: the
    ``first_fraction`` of hit cells touched earliest (first_touch at or below that quantile).
    """
    counts = np.asarray(hits)
    times = np.asarray(first_touch, dtype=float)
    hit = counts > 0
    most = np.zeros(len(counts), dtype=bool)
    first = np.zeros(len(counts), dtype=bool)
    hit_cut = first_cut = float('nan')
    if hit.any():
        hit_cut = float(np.quantile(counts[hit], 1.0 - top_fraction, method='higher'))
        most = hit & (counts >= hit_cut)
    touched = np.isfinite(times)
    if touched.any():
        first_cut = float(np.quantile(times[touched], first_fraction, method='lower'))
        first = touched & (times <= first_cut)
    return most, first, hit_cut, first_cut
