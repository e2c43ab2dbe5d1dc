"""Float seconds (what the plain modules use) to ROS time messages."""

from __future__ import annotations

from builtin_interfaces.msg import Time

__all__ = ['stamp_from_nanoseconds', 'stamp_from_seconds']


def stamp_from_seconds(seconds: float) -> Time:
    """builtin_interfaces/Time of a float time in seconds (nanosecond resolution)."""
    return stamp_from_nanoseconds(round(seconds * 1e9))



def stamp_from_nanoseconds(nanoseconds: int) -> Time:
    """builtin_interfaces/Time of integer nanoseconds (exact)."""
    nanoseconds = int(nanoseconds)
    return Time(sec=nanoseconds // 1_000_000_000, nanosec=nanoseconds % 1_000_000_000)
