"""Waiting in tests for something another process or thread does: poll a condition until it
holds or a deadline passes. No rclpy here, so ROS-free test files can use it too."""
from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar('T')


def wait_until(condition: Callable[[], T], timeout: float, what: str | Callable[[], str],
               period: float = 0.05) -> T:
    """The first truthy value of ``condition()``, polled every ``period`` seconds; past
    ``timeout`` seconds an AssertionError saying no ``what`` came (a callable ``what`` is
    asked only then, for a message that shows the state at the time of failure)."""
    deadline = time.monotonic() + timeout
    while not (value := condition()):
        if time.monotonic() >= deadline:
            said = what() if callable(what) else what
            raise AssertionError(f'no {said} within {timeout} s')
        time.sleep(period)
    return value
