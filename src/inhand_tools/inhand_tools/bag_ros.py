"""The ROS side shared by bag_replay, bag_record and topic_echo: start/stop, QoS, the graph.

``RosSession`` starts rclpy the way ``inhand_common.node_runner.run_node`` does: our own
SIGINT/SIGTERM handlers only set ``stop``, so every tool ends its loop and then closes its
bag, publishers or output with a valid context (rclpy's handlers would shut the context
down under it). The tools are loops of their own rather than plain spinners (a replay
publishes on a timetable, the recorder drains its queues before closing), which is why
they do not call ``run_node`` itself. A second signal while stopping raises
KeyboardInterrupt where that is safe (``second_signal_interrupts``).

QoS: the recorded offered QoS (rosbags ``Qos``) <-> rclpy ``QoSProfile``, and the profile
that matches the publishers seen on the graph (as ``ros2 topic echo`` / ``ros2 bag record``
choose it): reliable when every publisher is reliable, transient-local when every
publisher is, so a subscription never asks for more than is offered.
"""

from __future__ import annotations

import signal
import time
from typing import Iterable

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

__all__ = ['RosSession', 'StopFlag', 'bag_qos', 'describe_qos', 'graph_types', 'matching_qos',
           'replay_qos', 'wait_until']

DEFAULT_DEPTH = 1000          # volatile topics without a recorded depth
LATCHED_DEFAULT_DEPTH = 1     # transient-local without a recorded depth: the latest value
INFINITE_NS = 2**63 - 1


class StopFlag:
    """Set from a signal handler, polled by the loops.

    A plain flag rather than ``threading.Event``: ``Event.set()`` takes a lock that the
    interrupted main thread may be holding inside ``Event.wait()``, a rare deadlock.
    """

    def __init__(self):
        self._set = False

    def set(self) -> None:
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


class RosSession:
    """``with RosSession(argv) as session:`` rclpy initialised; ``session.stop`` on a signal."""

    def __init__(self, args: list[str], second_signal_interrupts: bool = True):
        self.args = list(args)
        self.stop = StopFlag()
        self.signal: int | None = None
        self._escalate = second_signal_interrupts
        self._previous = {}

    def _on_signal(self, signum, _frame) -> None:
        if self.stop.is_set() and self._escalate:
            raise KeyboardInterrupt
        self.signal = signum
        self.stop.set()

    def __enter__(self) -> 'RosSession':
        self._previous = {sig: signal.signal(sig, self._on_signal)
                          for sig in (signal.SIGINT, signal.SIGTERM)}
        rclpy.init(args=self.args, signal_handler_options=SignalHandlerOptions.NO)
        return self

    def __exit__(self, *exc) -> None:
        rclpy.try_shutdown()
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def sleep(self, seconds: float) -> bool:
        """Sleep unless stopped; True if stopped."""
        return self.stop.wait(seconds) if seconds > 0 else self.stop.is_set()


# -- QoS ---------------------------------------------------------------------------------

def _recorded_depth(recorded: list) -> int | None:
    from rosbags.interfaces import QosHistory
    depths = [q.depth for q in recorded if q.history == QosHistory.KEEP_LAST and q.depth > 0]
    return max(depths) if depths else None


def replay_qos(recorded: list, fast: bool = False) -> QoSProfile:
    """The publisher profile for a bag topic from its recorded offered QoS (maybe []).

    Timed replay: as recorded (best effort if any recorded publisher was; transient-local
    if all were; the recorded depth), else reliable/volatile depth 1000, and depth 1 for a
    transient-local topic recorded without a depth (late joiners get the latest message).
    ``fast``: always reliable (acknowledgements are what paces the replay); volatile
    topics keep every message (KEEP_ALL) until every reader has it; transient-local ones
    keep the recorded depth (KEEP_ALL would hand late joiners the whole history).
    """
    from rosbags.interfaces import QosDurability, QosReliability
    best_effort = any(q.reliability == QosReliability.BEST_EFFORT for q in recorded)
    transient = bool(recorded) and all(q.durability == QosDurability.TRANSIENT_LOCAL
                                       for q in recorded)
    depth = _recorded_depth(recorded) or (LATCHED_DEFAULT_DEPTH if transient else DEFAULT_DEPTH)
    durability = DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE
    if fast and not transient:
        return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                          durability=durability)
    reliability = (ReliabilityPolicy.BEST_EFFORT if best_effort and not fast
                   else ReliabilityPolicy.RELIABLE)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=reliability,
                      durability=durability)


def matching_qos(infos: Iterable, reliability: str | None = None,
                 transient_local: bool | None = None, keep_all: bool = False,
                 depth: int = 100) -> QoSProfile:
    """A subscription profile compatible with every publisher in ``infos``
    (``node.get_publishers_info_by_topic``), unless forced by the arguments."""
    infos = list(infos)
    if reliability is None:
        reliable = all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
    else:
        reliable = reliability == 'reliable'
    if transient_local is None:
        transient_local = bool(infos) and all(
            i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
    profile = QoSProfile(
        history=HistoryPolicy.KEEP_ALL if keep_all else HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if transient_local
                    else DurabilityPolicy.VOLATILE))
    return profile


def describe_qos(profile: QoSProfile) -> str:
    reliability = profile.reliability.name.lower().replace('_', '-')
    durability = profile.durability.name.lower().replace('_', '-')
    history = ('keep-all' if profile.history == HistoryPolicy.KEEP_ALL
               else f'depth {profile.depth}')
    return f'{reliability}, {durability}, {history}'


def _bag_time(duration) -> object:
    from rosbags.interfaces import QosTime
    ns = getattr(duration, 'nanoseconds', 0)
    if ns >= INFINITE_NS or ns < 0:
        return QosTime(2147483647, 4294967295)  # rosbag2's "infinite"
    return QosTime(ns // 1_000_000_000, ns % 1_000_000_000)


def bag_qos(profile: QoSProfile):
    """rosbags ``Qos`` of an rclpy profile (a publisher's offered QoS, for the bag)."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability)

    def convert(enum_type, value):
        return enum_type.__members__.get(getattr(value, 'name', ''), enum_type.UNKNOWN)

    return Qos(history=convert(QosHistory, profile.history), depth=int(profile.depth or 0),
               reliability=convert(QosReliability, profile.reliability),
               durability=convert(QosDurability, profile.durability),
               deadline=_bag_time(profile.deadline), lifespan=_bag_time(profile.lifespan),
               liveliness=convert(QosLiveliness, profile.liveliness),
               liveliness_lease_duration=_bag_time(profile.liveliness_lease_duration),
               avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions))


# -- graph -------------------------------------------------------------------------------

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
