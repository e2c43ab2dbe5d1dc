"""A ROS session for the bag tools: rclpy started and stopped around a loop of their own,
a stop flag set by SIGINT/SIGTERM, and waits on the ROS graph.

``RosSession`` starts rclpy the way ``inhand_common.node_runner.run_node`` does: our own
SIGINT/SIGTERM handlers only set ``stop``, so every tool ends its loop and then closes its
bag, publishers or output with a valid context (rclpy's handlers would shut the context
down under it). The tools are loops of their own rather than plain spinners (a replay
publishes on a timetable, the recorder drains its queues before closing), which is why
they do not call ``run_node`` itself. A second signal while stopping raises
KeyboardInterrupt where that is safe (``second_signal_interrupts``).

Imports rclpy: the commands import this module only once their arguments are checked.
"""

from __future__ import annotations

import signal
import time

import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from inhand_common.dds_profile import shipped_profile
from inhand_common.stop_flag import StopFlag

__all__ = ['InvalidTopicName', 'RosSession', 'StopFlag', 'graph_types', 'resolve_topic',
           'wait_until']


class RosSession:
    """``with RosSession(argv) as session:`` rclpy initialised; ``session.stop`` on a signal."""

    def __init__(self, args: list[str], second_signal_interrupts: bool = True,
                 writer_heartbeat_ns: int | None = None):
        self.args = list(args)
        # the graph's Fast DDS profile (dds_profile.py), with a writer heartbeat if asked
        self._profile = shipped_profile(writer_heartbeat_ns)
        self.stop = StopFlag()
        self.signal: int | None = None
        self._escalate = second_signal_interrupts
        self._previous = {}

    def _on_signal(self, signum, _frame) -> None:
        if self.stop.is_set() and self._escalate:
            raise KeyboardInterrupt
        self.signal = signum
        self.stop.set()

    def __enter__(self) -> RosSession:
        self._previous = {sig: signal.signal(sig, self._on_signal)
                          for sig in (signal.SIGINT, signal.SIGTERM)}
        self._profile.__enter__()
        try:
            rclpy.init(args=self.args, signal_handler_options=SignalHandlerOptions.NO)
        except BaseException:
            self._profile.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc) -> None:
        rclpy.try_shutdown()
        self._profile.__exit__(None, None, None)
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def sleep(self, seconds: float) -> bool:
        """Sleep unless stopped; True if stopped."""
        return self.stop.wait(seconds) if seconds > 0 else self.stop.is_set()


# -- the graph ---------------------------------------------------------------------------

class InvalidTopicName(ValueError):
    """A topic name rcl cannot expand (bad characters, '//', unknown substitution ...)."""


def resolve_topic(node: Node, name: str) -> str:
    """``name`` expanded in the node's namespace and remapped; InvalidTopicName if invalid."""
    try:
        return node.resolve_topic_name(name)
    except rclpy_implementation.RCLError as error:  # what rcl's name expansion raises
        raise InvalidTopicName(str(error)) from None


def graph_types(node: Node) -> dict[str, list[str]]:
    """Absolute topic name -> its types, as the graph knows them now."""
    return {name: list(types) for name, types in node.get_topic_names_and_types()}


def wait_until(predicate, stop: StopFlag, timeout: float | None,
               period: float = 0.05) -> bool:
    """Poll ``predicate`` until true (True), ``timeout`` (False) or ``stop`` (False)."""
    deadline = None if timeout is None else time.monotonic() + timeout
    while not stop.is_set():
        if predicate():
            return True
        if deadline is not None and time.monotonic() >= deadline:
            return False
        stop.wait(period)
    return False
