"""The QoS profiles the bag tools publish and subscribe with, and the QoS a bag records.

- ``replay_qos``: a bag_replay publisher's profile from the QoS the bag recorded as offered.
- ``matching_qos``: a subscription profile that matches the publishers seen on the graph
  (as ``ros2 topic echo`` / ``ros2 bag record`` choose it): reliable when every publisher
  is reliable, transient-local when every publisher is, so a subscription never asks for
  more than is offered.
- ``bag_qos``: an rclpy profile as the rosbags ``Qos`` stored in a bag's metadata.
- ``describe_qos``: one line for the user ("reliable, volatile, depth 1000").

Imports rclpy: the commands import this module only once their arguments are checked.
"""

from __future__ import annotations

from collections.abc import Iterable

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

__all__ = ['bag_qos', 'describe_qos', 'matching_qos', 'replay_qos']

DEFAULT_DEPTH = 1000          # volatile topics without a recorded depth
LATCHED_DEFAULT_DEPTH = 1     # transient-local without a recorded depth: the latest value
INFINITE_NS = 2**63 - 1


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
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability

    def convert(enum_type, value):
        return enum_type.__members__.get(getattr(value, 'name', ''), enum_type.UNKNOWN)

    return Qos(history=convert(QosHistory, profile.history), depth=int(profile.depth or 0),
               reliability=convert(QosReliability, profile.reliability),
               durability=convert(QosDurability, profile.durability),
               deadline=_bag_time(profile.deadline), lifespan=_bag_time(profile.lifespan),
               liveliness=convert(QosLiveliness, profile.liveliness),
               liveliness_lease_duration=_bag_time(profile.liveliness_lease_duration),
               avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions))
