"""Left and right images of one exposure, paired by exact stamp.

A stereo camera (or a bag of one) stamps both images of an exposure identically; they arrive
as two messages in either order, and over best-effort transport one may never come. The
buffer keeps the newest few unpaired images per side and releases a pair as soon as both
halves of one stamp are there; a half whose partner does not come within ``depth`` newer
exposures is dropped and counted.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Generic, TypeVar

__all__ = ['SIDES', 'PairBuffer']

SIDES = ('left', 'right')
Item = TypeVar('Item')


class PairBuffer(Generic[Item]):
    """Pairs items of the two sides by stamp (int nanoseconds)."""

    def __init__(self, depth: int = 4):
        if depth < 1:
            raise ValueError(f'depth must be at least 1, got {depth}')
        self.depth = depth
        self._waiting: dict[str, OrderedDict[int, Item]] = {side: OrderedDict() for side in SIDES}
        self.paired = 0
        self.dropped = 0   # halves whose partner never came

    def add(self, side: str, stamp_ns: int, item: Item) -> tuple[int, Item, Item] | None:
        """Offer one half; returns (stamp, left, right) when it completes a pair."""
        if side not in SIDES:
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        other = self._waiting['right' if side == 'left' else 'left']
        partner = other.pop(stamp_ns, None)
        if partner is not None:
            # Older halves of the other side will not be completed now: exposures come in
            # order, so their partners were lost.
            for stale in [s for s in other if s < stamp_ns]:
                del other[stale]
                self.dropped += 1
            self.paired += 1
            return (stamp_ns, item, partner) if side == 'left' else (stamp_ns, partner, item)
        mine = self._waiting[side]
        mine[stamp_ns] = item
        while len(mine) > self.depth:
            mine.popitem(last=False)
            self.dropped += 1
        return None

    @property
    def waiting(self) -> int:
        return sum(len(items) for items in self._waiting.values())
