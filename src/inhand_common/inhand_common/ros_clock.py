"""Which clock a node's work runs on.

A node's processing cadence (batching poses, applying held samples, diagnostics) is about
the CPU, not about the data's time: it runs on the steady clock, so the nodes map the same
under ``use_sim_time`` with or without ``/clock`` (a ROS-clock timer never fires while
nothing publishes ``/clock``). What the nodes stamp with their own time (the object
frame, diagnostics, transforms) uses the node's ROS clock, so it follows sim time.
"""

from __future__ import annotations

from collections.abc import Callable

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.timer import Timer

__all__ = ['steady_timer', 'uses_sim_time']


def steady_timer(node: Node, period: float, callback: Callable[[], object]) -> Timer:
    """A timer of ``node`` every ``period`` seconds of the steady (monotonic) clock."""
    return node.create_timer(period, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))


def uses_sim_time(node: Node) -> bool:
    """Whether ``node`` runs with ``use_sim_time`` (its time comes from ``/clock``)."""
    return bool(node.get_parameter('use_sim_time').value)
