"""Conversions between float seconds (what the plain modules use) and ROS time messages."""

from __future__ import annotations

from builtin_interfaces.msg import Time

__all__ = ['stamp_from_seconds', 'seconds_from_stamp']


def stamp_from_seconds(seconds: float) -> Time:
    """builtin_interfaces/Time of a float time in seconds (nanosecond resolution)."""
    nanoseconds = int(round(seconds * 1e9))
    return Time(sec=nanoseconds // 1_000_000_000, nanosec=nanoseconds % 1_000_000_000)


def seconds_from_stamp(stamp: Time) -> float:
    return stamp.sec + stamp.nanosec * 1e-9
