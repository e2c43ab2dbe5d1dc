"""Stereo pairs between the camera and the work: the newest waits, the others are counted.

A camera sends pairs at its own rate (15-30 Hz), and a pair's work (disparity, points, the
vision map, the texture) can take longer than the time to the next one. The node's
callbacks only pair the images and hand complete pairs to :class:`NewestPair`; one worker
thread takes the newest pair when it is free. A pair replaced before the worker took it is
*skipped*, and counted: so every pair that arrives is processed, skipped or refused, and
the node's ``diagnostics`` say which (:func:`flow_report`), rather than the transport's
queues dropping the surplus without a word. The work itself releases the interpreter
(OpenCV, the compiled kernels), so the callbacks keep taking images meanwhile.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from typing import Generic, TypeVar

from inhand_common.health import WARN, Problems

__all__ = ['NewestPair', 'flow_report']

Pair = TypeVar('Pair')


class NewestPair(Generic[Pair]):
    """A one-pair slot between the callbacks (:meth:`offer`) and the worker (:meth:`take`);
    thread-safe."""

    def __init__(self) -> None:
        self._ready = threading.Condition()
        self._pair: Pair | None = None
        self._closed = False
        self.received = 0     # pairs offered
        self.skipped = 0      # pairs replaced by a newer one before the worker took them

    def offer(self, pair: Pair) -> None:
        with self._ready:
            self.received += 1
            if self._pair is not None:
                self.skipped += 1
            self._pair = pair
            self._ready.notify()

    def take(self, timeout: float) -> Pair | None:
        """The newest pair, waiting up to ``timeout`` s; None if none came or closed."""
        with self._ready:
            self._ready.wait_for(lambda: self._pair is not None or self._closed, timeout)
            pair, self._pair = self._pair, None
            return pair

    def close(self) -> None:
        """Wake the worker for good (:meth:`take` returns what is left, then None)."""
        with self._ready:
            self._closed = True
            self._ready.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed


def flow_report(counts: Mapping[str, int], increases: Mapping[str, int], elapsed: float,
                problems: Problems) -> tuple[str, dict[str, object]]:
    """The stereo node's diagnostics from its running totals ``counts`` (keys ``pairs
    received``, ``pairs processed``, ``pairs skipped``, ``pairs refused``, ``pairs without
    an object pose``, ``images unpaired``) and their ``increases`` over the last
    ``elapsed`` s: the OK message and the key values; a warning added to ``problems`` when
    pairs were skipped or images went unpaired in that time."""
    received, skipped = increases.get('pairs received', 0), increases.get('pairs skipped', 0)
    if skipped:
        problems.add(WARN, 'skipping pairs',
                     f'{skipped} of {received} stereo pairs in the last {elapsed:.1f} s '
                     'skipped: the work of a pair takes longer than the camera leaves it '
                     '(the newest pair is taken; lower the camera rate or the disparity '
                     'range)')
    unpaired = increases.get('images unpaired', 0)
    if unpaired:
        problems.add(WARN, 'unpaired images',
                     f'{unpaired} images in the last {elapsed:.1f} s found no partner with '
                     'the same stamp (the cameras must share stamps; a lost image leaves '
                     'its partner alone)')
    rate = received / elapsed if elapsed > 0 else 0.0
    values: dict[str, object] = {key: int(value) for key, value in counts.items()}
    values['pairs per second'] = f'{rate:.1f}'
    return (f'{rate:.1f} pairs/s, {counts.get("pairs processed", 0)} processed, '
            f'{counts.get("pairs skipped", 0)} skipped', values)
