"""How much evidence one fingertip sample carries: the time it stands for, in measurements.

The paper updates a cell once per measurement at 15 Hz. Samples of one fingertip are not
independent measurements, though: at 240 Hz a finger resting in a cell for a second gives
240 "measurements" of one contact, and a finger flying through a cell between strokes at
0.3 m/s is sampled there as often as one sliding over the surface at 3 cm/s. So evidence
is counted in time: a sample stands for the time the fingertip spent where it was sampled,

    dwell = min(dt, cell / speed),

``dt`` the time since the finger's previous sample (at most one ``period``) and
``cell / speed`` the time the finger needs to cross a cell at its current speed. Its weight
is ``dwell / period``, ``period = 1 / evidence_rate``: with the default rate of 15 Hz a
sample at the paper's rate taken while sliding counts as one measurement, as in the paper;
at 240 Hz one sample counts 1/16; a sample taken while the finger moves ten times faster
than it needs to cross a cell in one period counts 1/10. The same motion therefore gives
the same evidence at any tracker rate.

The speed is measured over one period (the displacement from the finger's sample one
period earlier): over a single 240 Hz step, 1 mm of tracker noise would look like 0.3 m/s.
A finger with no sample one to two periods back (the first samples, or after a gap) has
no speed yet and is not limited by it.

Plain numpy; the per-finger tail of the last two periods is kept between calls, so the
weights do not depend on how the stream is cut into batches.
"""

from __future__ import annotations

import numpy as np

__all__ = ['DwellWeights']


class DwellWeights:
    """Weight in [0, 1] of each fingertip sample (see the module docstring).

    ``period`` (s) is the time worth one measurement; ``cell`` (m) the cell edge.
    Samples of a finger are expected in time order; a finger whose time goes back by more
    than a period (a bag replayed in a loop, a reset) starts afresh.
    """

    def __init__(self, period: float, cell: float):
        if not (period > 0 and cell > 0):
            raise ValueError(f'period {period} s and cell {cell} m must be positive')
        self.period = float(period)
        self.cell = float(cell)
        self._tails: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def reset(self) -> None:
        self._tails.clear()

    def weights(self, points, times, fingers) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        times = np.asarray(times, dtype=np.float64).reshape(-1)
        fingers = np.asarray(fingers).reshape(-1)
        out = np.ones(len(times))
        usable = np.isfinite(times) & np.all(np.isfinite(points), axis=1)
        for finger in np.unique(fingers[usable]):
            index = np.flatnonzero(usable & (fingers == finger))
            index = index[np.argsort(times[index], kind='stable')]
            out[index] = self._finger_weights(int(finger), points[index], times[index])
        return out

    def _finger_weights(self, finger: int, points: np.ndarray, times: np.ndarray):
        period = self.period
        tail_t, tail_p = self._tails.get(finger, (np.empty(0), np.empty((0, 3))))
        if len(tail_t) and times[0] < tail_t[-1] - period:
            tail_t, tail_p = np.empty(0), np.empty((0, 3))   # time went back: start afresh
        all_t = np.concatenate([tail_t, times])
        all_p = np.concatenate([tail_p, points])
        k = len(tail_t) + np.arange(len(times))              # this batch within all_*
        dt = np.full(len(times), period)
        has_previous = k > 0
        dt[has_previous] = np.clip(all_t[k[has_previous]] - all_t[k[has_previous] - 1],
                                   0.0, period)
        # The finger's sample one period back (at most two periods back) gives its speed.
        # (A little slack: stamps near 1.7e9 s carry ~0.2 us of rounding.)
        slack = 1e-3 * period
        back = np.searchsorted(all_t, all_t[k] - period + slack, side='right') - 1
        found = back >= 0
        baseline = np.where(found, all_t[k] - all_t[np.maximum(back, 0)], np.inf)
        found &= baseline <= 2.0 * period + slack
        crossing = np.full(len(times), np.inf)
        if found.any():
            moved = np.linalg.norm(all_p[k[found]] - all_p[back[found]], axis=1)
            speed = moved / baseline[found]
            with np.errstate(divide='ignore'):
                crossing[found] = np.where(speed > 0, self.cell / speed, np.inf)
        keep = all_t >= all_t[-1] - 2.0 * period - slack
        self._tails[finger] = (all_t[keep], all_p[keep])
        return np.minimum(dt, crossing) / period
