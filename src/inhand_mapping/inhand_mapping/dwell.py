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

The speed is measured over one period (over a single 240 Hz step, 1 mm of tracker noise
would look like 0.3 m/s), both ways: from the finger's sample one period earlier to this
one, and from this one to the finger's sample one period later, and the faster counts. A
sample taken just after the finger lifted off the surface, or just before it touches down,
is in the air between a slow part and a fast part of the motion; looking back only, the
first sample of a lift-off would still see the slow slide before it and count fully. A
direction with no sample one to two periods away (the start, the end, a gap) gives no
speed.

Looking ahead means a sample can only be weighed once the finger's next period has arrived:
``push`` holds each finger's newest samples back and returns the ones whose weights are
settled, in the order they were pushed; ``flush`` releases the rest at the end of a stream.
A finger's sample is settled when that finger has a sample one period later, or when any
finger is more than two periods past it (the stream is in time order, so nothing that
could still arrive would be close enough to count). The result does not depend on how the
stream is cut into pushes. Plain numpy.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import TypeAlias

import numpy as np
from numpy.typing import ArrayLike

from inhand_common.array_types import Bools, FingerIds, Floats, Points, Rows, Times, Weights

__all__ = ['DwellWeights', 'WeightedSamples']

# What selects samples: a slice, a mask or integer positions.
Selection: TypeAlias = slice | Bools | Rows


@dataclass(frozen=True, slots=True)
class WeightedSamples:
    """Samples released by ``DwellWeights`` with their weights, in the order pushed.

    Iterating gives the four arrays in field order (``points, times, fingers, weights =
    samples``). A dataclass rather than a NamedTuple: ``count`` would shadow ``tuple.count``.
    """

    points: Points      # (N, 3)
    times: Times        # (N,)
    fingers: FingerIds  # (N,) int64
    weights: Weights    # (N,) in [0, 1]

    def __iter__(self) -> Iterator[Floats | FingerIds]:
        return iter((self.points, self.times, self.fingers, self.weights))

    @classmethod
    def empty(cls) -> WeightedSamples:
        return cls(np.empty((0, 3)), np.empty(0), np.empty(0, np.int64), np.empty(0))

    @property
    def count(self) -> int:
        return len(self.times)

    def part(self, index: Selection) -> WeightedSamples:
        return WeightedSamples(self.points[index], self.times[index], self.fingers[index],
                               self.weights[index])

    @classmethod
    def joined(cls, parts: Iterable[WeightedSamples]) -> WeightedSamples:
        parts = [part for part in parts if part.count]
        if not parts:
            return cls.empty()
        return cls(np.concatenate([part.points for part in parts]),
                   np.concatenate([part.times for part in parts]),
                   np.concatenate([part.fingers for part in parts]),
                   np.concatenate([part.weights for part in parts]))


def _usable(points: Points, times: Times) -> Bools:
    """Samples with a finite time and position: the only ones that are a finger's
    neighbours."""
    usable: Bools = np.isfinite(times) & np.all(np.isfinite(points), axis=1)
    return usable


class DwellWeights:
    """Weight in [0, 1] of each fingertip sample (see the module docstring).

    ``period`` (s) is the time worth one measurement; ``cell`` (m) the cell edge. Samples
    are expected in time order; a time going back by more than a period (a bag replayed in
    a loop, a reset) ends the stream: what is held back is released as at its end, and the
    new stream starts afresh. Samples with a non-finite time or position are passed on with
    weight 1 (the map rejects them) and are no finger's neighbours.
    """

    def __init__(self, period: float, cell: float):
        if not (period > 0 and cell > 0):
            raise ValueError(f'period {period} s and cell {cell} m must be positive')
        self.period = float(period)
        self.cell = float(cell)
        # Stamps near 1.7e9 s carry ~0.2 us of rounding: "one period later" allows for it.
        self._slack = 1e-3 * self.period
        self.reset()

    def reset(self) -> None:
        """Forget everything, including the samples held back."""
        self._held = WeightedSamples.empty()
        # Per finger: the newest released samples (times, points), two periods' worth, as
        # the earlier neighbours of the samples still held back.
        self._history: dict[int, tuple[Times, Points]] = {}
        self._latest = -np.inf   # newest usable time pushed

    @property
    def pending(self) -> int:
        """Samples held back until their finger's next period arrives."""
        return self._held.count

    def push(self, points: ArrayLike, times: ArrayLike, fingers: ArrayLike) -> WeightedSamples:
        """Take samples (in time order); return those whose weights are now settled."""
        positions: Points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        stamps: Times = np.asarray(times, dtype=np.float64).reshape(-1)
        finger_ids: FingerIds = np.asarray(fingers).reshape(-1).astype(np.int64)
        usable = _usable(positions, stamps)
        released = []
        while len(stamps):
            # Newest usable time before each sample; a time falling back more than a period
            # below it starts a new stream there.
            newest = np.maximum.accumulate(np.where(usable, stamps, -np.inf))
            before = np.maximum(self._latest, np.concatenate([[-np.inf], newest[:-1]]))
            restart = np.flatnonzero(usable & (stamps < before - self.period))
            cut = restart[0] if len(restart) else len(stamps)
            self._hold(positions[:cut], stamps[:cut], finger_ids[:cut])
            if cut == len(stamps):
                released.append(self._release(everything=False))
                break
            released.append(self._release(everything=True))
            self.reset()
            positions, stamps = positions[cut:], stamps[cut:]
            finger_ids, usable = finger_ids[cut:], usable[cut:]
        return WeightedSamples.joined(released)

    def flush(self) -> WeightedSamples:
        """Release every sample held back (the end of the stream)."""
        return self._release(everything=True)

    # ------------------------------------------------------------------ internals
    def _hold(self, points: Points, times: Times, fingers: FingerIds) -> None:
        # Held samples carry weight 1 until released: what unusable ones keep.
        self._held = WeightedSamples.joined(
            [self._held, WeightedSamples(points, times, fingers, np.ones(len(times)))])
        usable = _usable(points, times)
        if usable.any():
            self._latest = max(self._latest, float(times[usable].max()))

    def _release(self, everything: bool) -> WeightedSamples:
        held = self._held
        usable = _usable(held.points, held.times)
        count = held.count if everything else self._settled_prefix(usable)
        if count == 0:
            return WeightedSamples.empty()
        out = held.part(slice(None, count))
        for finger in np.unique(out.fingers[usable[:count]]):
            mine = np.flatnonzero(usable & (held.fingers == finger))
            releasing = mine < count
            out.weights[mine[releasing]] = self._finger_weights(
                int(finger), held.times[mine], held.points[mine], releasing)
        self._held = held.part(slice(count, None))
        return out

    def _settled_prefix(self, usable: Bools) -> int:
        """How many held samples, from the oldest, have every neighbour that can count."""
        held, period = self._held, self.period
        settled = ~usable | (held.times + 2.0 * period + self._slack < self._latest)
        for finger in np.unique(held.fingers[usable]):
            mine = usable & (held.fingers == finger)
            newest = held.times[mine].max()
            settled |= mine & (held.times + period - self._slack <= newest)
        return len(settled) if settled.all() else int(np.argmin(settled))

    def _finger_weights(self, finger: int, times: Times, points: Points, releasing: Bools
                        ) -> Weights:
        """Weights of the ``releasing`` ones of a finger's held samples (the others are their
        later neighbours); the finger's history updated."""
        period, slack = self.period, self._slack
        history_t, history_p = self._history.get(finger, (np.empty(0), np.empty((0, 3))))
        all_t = np.concatenate([history_t, times])
        all_p = np.concatenate([history_p, points])
        order = np.argsort(all_t, kind='stable')
        all_t, all_p = all_t[order], all_p[order]
        k = np.argsort(order, kind='stable')[len(history_t):][releasing]  # in all_*
        dt = np.full(len(k), period)
        has_previous = k > 0
        dt[has_previous] = np.clip(all_t[k[has_previous]] - all_t[k[has_previous] - 1],
                                   0.0, period)
        earlier = np.searchsorted(all_t, all_t[k] - period + slack, side='right') - 1
        later = np.searchsorted(all_t, all_t[k] + period - slack, side='left')
        speed = np.maximum(self._speed(all_t, all_p, k, earlier),
                           self._speed(all_t, all_p, k, later))
        with np.errstate(divide='ignore'):
            crossing = np.where(speed > 0, self.cell / speed, np.inf)
        released_t, released_p = np.concatenate([history_t, times[releasing]]), \
            np.concatenate([history_p, points[releasing]])
        if len(released_t):
            keep = released_t >= released_t.max() - 2.0 * period - slack
            self._history[finger] = (released_t[keep], released_p[keep])
        weights: Weights = np.minimum(dt, crossing) / period
        return weights

    def _speed(self, all_t: Times, all_p: Points, k: Rows, other: Rows) -> Floats:
        """Speed between samples ``k`` and ``other`` (indices into all_*), 0 where ``other``
        is missing or more than two periods away."""
        speed = np.zeros(len(k))
        inside = (other >= 0) & (other < len(all_t))
        other = np.clip(other, 0, len(all_t) - 1)
        baseline = np.abs(all_t[other] - all_t[k])
        found = inside & (baseline <= 2.0 * self.period + self._slack) & (baseline > 0)
        speed[found] = (np.linalg.norm(all_p[other[found]] - all_p[k[found]], axis=1)
                        / baseline[found])
        return speed
