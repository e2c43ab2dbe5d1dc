"""A flag a signal handler raises and loops poll: how every process here stops on a signal.

A plain attribute rather than ``threading.Event``: ``Event.set()`` takes a lock, and a
handler that runs while the main thread holds it (inside ``Event.wait()``, or inside the
``set()`` of a first signal when a second comes at once, as when a launcher is killed and
each child gets its parent-death signal) deadlocks the process.
"""

from __future__ import annotations

import time

__all__ = ['StopFlag']


class StopFlag:
    """Set from a signal handler (any number of times), polled by the loops."""

    def __init__(self) -> None:
        self._set = False

    def set(self, *_signal: object) -> None:
        """Raise the flag; takes and ignores a signal handler's arguments."""
        self._set = True

    def is_set(self) -> bool:
        return self._set

    def wait(self, timeout: float | None = None) -> bool:
        """Sleep up to ``timeout`` (forever if None) in short slices; True if set."""
        end = None if timeout is None else time.monotonic() + timeout
        while not self._set:
            left = 0.05 if end is None else end - time.monotonic()
            if left <= 0:
                break
            time.sleep(min(left, 0.05))
        return self._set
