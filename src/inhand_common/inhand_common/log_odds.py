"""Probability and log-odds, each from the other (the occupancy maps' two forms of a cell)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from inhand_common.array_types import Floats


def logit(p: ArrayLike) -> Floats:
    p = np.asarray(p, dtype=float)
    return np.log(p / (1.0 - p))


def probability(log_odds: ArrayLike) -> Floats:
    p: Floats = 1.0 / (1.0 + np.exp(-np.asarray(log_odds, dtype=float)))
    return p
