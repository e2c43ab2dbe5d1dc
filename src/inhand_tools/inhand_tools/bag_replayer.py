"""Publish a bag's messages on their topics, on the bag's timetable or as fast as the
subscribers take them: the library behind the ``bag_replay`` command.

``plan_streams`` picks the topics and their message classes, ``start_stamp`` the bag time
to start at, ``replay_bag`` publishes in a ROS session of its own and returns
``ReplayStats``, ``replay_summary`` says what was done. How ``--fast`` keeps every
subscriber fed without loss is told in the command's help
(:mod:`inhand_tools.commands.bag_replay`).

No rclpy import at module level, so the command checks its arguments and the bag before
the ROS runtime loads.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field

from inhand_common.bag_source import BagError, BagSource, Progress, relative_name
from inhand_tools.message_types import UnknownMessageType, message_class

__all__ = ['BagClock', 'ReplayOptions', 'ReplayStats', 'Replayer', 'Stream', 'plan_streams', 'replay_bag',
           'replay_summary', 'start_stamp']

SUBSCRIBER_WAIT = 10.0    # s: a replay waits this long at most for a subscriber on every topic
SETTLE = 0.5              # s: after the match, for the readers to match our writers too
TIMED_ACK_TIMEOUT = 5.0   # s: at the end of a timed replay, wait at most this for acks
VIEW_NODE = 'live_view'
UNKNOWN_NODE = '_NODE_NAME_UNKNOWN_'   # a reader whose node's name discovery has not given yet
SLOW_PUBLISH = 0.002      # s: a publish() that took longer was held back by a reader


@dataclass
class ReplayOptions:
    """How to replay (the command's options)."""

    rate: float = 1.0                       # time scale of a timed replay
    fast: bool = False                      # as fast as the subscribers take the messages
    loop: bool = False                      # start again at the end
    wait_subscribers: float | None = None   # s; None: the default of the mode
    quiet: bool = False                     # no progress line
    clock_hz: float | None = None           # publish the bag's time on /clock at this rate
    # Readers the wait does not count as "a subscriber" (still waited for once seen): the
    # live view reads every topic, and a replay that started on its match alone lost the
    # graph's (all 5,400 poses of a replay, 1 run in 6).
    ignored_readers: tuple[str, ...] = (VIEW_NODE,)


@dataclass
class Stream:
    """One replayed topic."""

    name: str
    msgtype: str
    cls: object
    recorded_qos: list
    qos: object = None
    publisher: object = None
    window: int = 0          # transient-local in --fast: unacknowledged messages allowed
    unacked: int = 0
    published: int = 0


@dataclass
class ReplayStats:
    messages: int = 0
    wall: float = 0.0
    bag_seconds: float = 0.0
    passes: int = 0
    held_back: float = 0.0
    blocked: int = 0
    ack_wait: float = 0.0    # s after the last publish until every message was acknowledged
    clock_messages: int = 0  # /clock messages published
    stopped: bool = False
    per_topic: dict = field(default_factory=dict)


# -- planning, before ROS starts ---------------------------------------------------------

def plan_streams(source: BagSource, wanted: list[str] | None) -> dict[str, Stream]:
    """The topics to replay with their classes; BagError for anything unusable."""
    available = dict(source.topics)
    if wanted:
        names = [relative_name(t) for t in wanted]
        missing = [n for n in names if n not in available]
        if missing:
            raise BagError(f'{source.bag}: no topic {", ".join(missing)} in this bag; it has '
                           f'{sorted(available) or "no topics"}')
    else:
        names = sorted(available)
    streams = {}
    for name in dict.fromkeys(names):
        topic = available[name]
        try:
            cls = message_class(topic.msgtype)
        except UnknownMessageType as error:
            hint = '' if wanted else ' (replay the other topics with --topics)'
            raise BagError(f'{source.bag}: topic {name}: {error}{hint}') from None
        streams[name] = Stream(name, topic.msgtype, cls, topic.qos)
    if not any(available[n].count for n in streams):
        raise BagError(f'{source.bag}: no messages to replay on {sorted(streams)}')
    return streams


def start_stamp(source: BagSource, start_offset: float) -> int:
    """The bag time ``start_offset`` seconds into the bag; BagError if past its end."""
    if start_offset > source.duration:
        raise BagError(f'{source.bag}: --start-offset {start_offset:g} s is past the '
                       f'end of the bag ({source.duration:.3f} s long)')
    return source.start_ns + round(start_offset * 1e9)


# -- replaying -----------------------------------------------------------------------------

HEARTBEAT_NS = 20_000_000


def replay_bag(ros_args: list[str], source: BagSource, streams: dict[str, Stream],
               options: ReplayOptions, start_ns: int) -> ReplayStats:
    """Replay ``streams`` from bag time ``start_ns`` in a ROS session started with
    ``ros_args`` (the full command line, for ``--ros-args``); stops on SIGINT/SIGTERM.
    A second signal while stopping raises KeyboardInterrupt."""
    from rclpy.node import Node

    from inhand_tools.ros_session import RosSession
    # a heartbeat every 20 ms (3 s by default): a fast replay is paced by acknowledgements,
    # which a reliable reader sends when a heartbeat asks (dds_profile.py)
    with RosSession(ros_args, writer_heartbeat_ns=HEARTBEAT_NS) as session:
        node = Node('bag_replay')
        try:
            return Replayer(node, session.stop, source, streams, options).run(start_ns)
        finally:
            node.destroy_node()


class Replayer:
    """The publishers of a replay, and the loops that feed them."""

    def __init__(self, node, stop, source: BagSource, streams: dict[str, Stream],
                 options: ReplayOptions):
        from rclpy.impl.implementation_singleton import rclpy_implementation
        from rclpy.qos import DurabilityPolicy

        from inhand_tools.qos_profiles import replay_qos
        self.node, self.stop, self.source, self.options = node, stop, source, options
        self.streams = streams
        self.stats = ReplayStats()
        self._rcl_error = rclpy_implementation.RCLError
        for stream in streams.values():
            stream.qos = replay_qos(stream.recorded_qos, fast=options.fast)
            if options.fast and stream.qos.durability == DurabilityPolicy.TRANSIENT_LOCAL:
                stream.window = stream.qos.depth
            stream.publisher = node.create_publisher(stream.cls, stream.name, stream.qos)
        self.clock = BagClock(node, options.clock_hz, options.rate) if options.clock_hz else None

    def run(self, start_ns: int) -> ReplayStats:
        if self.clock is not None:
            self.clock.start(start_ns)
        try:
            self._run(start_ns)
        finally:
            if self.clock is not None:
                self.stats.clock_messages = self.clock.close()
        return self.stats

    def _run(self, start_ns: int) -> None:
        self.wait_for_subscribers()
        while not self.stop.is_set():
            progress = None
            if not self.options.quiet:
                prefix = f'pass {self.stats.passes + 1}: ' if self.options.loop else ''
                progress = Progress('bag_replay', self.source.start_ns, self.source.end_ns,
                                    prefix=prefix)
            self.run_pass(start_ns, progress)
            if not self.options.loop:
                break
        self.stats.stopped = self.stop.is_set()
        if not self.stats.stopped:
            self.finish()
        self.stats.per_topic = {name: s.published for name, s in self.streams.items()}

    # -- waiting -----------------------------------------------------------------------

    def wait_for_subscribers(self) -> None:
        """Messages published before a subscriber is matched never reach it: wait for one
        on every topic (SUBSCRIBER_WAIT unless told otherwise), then say which have none."""
        timeout = self.options.wait_subscribers
        if timeout is None:
            timeout = SUBSCRIBER_WAIT
        if timeout == 0.0:
            return
        from inhand_tools.ros_session import wait_until

        def unmatched() -> list[tuple[str, str]]:
            """(topic, what it waits for) of the topics not ready yet: a topic is ready when
            a reader of a node not ignored is in the graph and every reader the graph shows
            (with a QoS our writer can match) is matched. Matched counts alone would start
            on the live view's reader while the graph's own were not discovered yet."""
            waiting = []
            for stream in self.streams.values():
                topic = stream.publisher.topic_name
                readers = self.compatible_readers(stream)
                counted = [name for name in readers
                           if name not in self.options.ignored_readers and name != UNKNOWN_NODE]
                matched = stream.publisher.get_subscription_count()
                if not counted:
                    waiting.append((topic, topic if not readers else
                                    f'{topic} (read only by {", ".join(sorted(set(readers)))}, '
                                    'which the wait does not count)'))
                elif matched < len(readers):
                    waiting.append((topic, f'{topic} (only {matched} of its {len(readers)} '
                                           'subscribers matched)'))
            return waiting

        def lonely() -> list[str]:
            return [topic for topic, _ in unmatched()]

        if lonely():
            limit = 'as long as it takes, Ctrl-C to stop' if timeout is None else \
                f'up to {timeout:g} s'
            print(f'bag_replay: waiting for a subscriber on {", ".join(lonely())} ({limit})',
                  file=sys.stderr, flush=True)
        if not wait_until(lambda: not lonely(), self.stop, timeout) and not self.stop.is_set():
            said = [what for _, what in unmatched()]
            print(f'bag_replay: no subscriber on {"; ".join(said)} after {timeout:g} s: '
                  'what comes before one matches reaches nobody (--topics leaves topics '
                  'out, --wait-subscribers waits longer); starting', file=sys.stderr,
                  flush=True)
        # Our writers see the readers; the readers may not see our writers yet, and what comes
        # before that is lost to a best-effort reader (a camera topic: the one stereo pair at
        # a bag's start) and to a volatile reliable one. Let discovery settle both ways.
        self.stop.wait(SETTLE)
        if self.options.fast:
            self.warn_best_effort_readers()

    def compatible_readers(self, stream: Stream) -> list[str]:
        """The node names of the readers of the stream's topic in the graph that our writer
        can match: a reliable reader never matches a best-effort writer, nor a
        transient-local reader a volatile one. (Not rclpy's qos_check_compatible: the
        graph reports a reader's unset deadline as infinite, which it calls an error.)"""
        from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
        best_effort = stream.qos.reliability == ReliabilityPolicy.BEST_EFFORT
        volatile = stream.qos.durability == DurabilityPolicy.VOLATILE
        return [info.node_name for info in self.node.get_subscriptions_info_by_topic(
                    stream.publisher.topic_name)
                if not (best_effort and info.qos_profile.reliability == ReliabilityPolicy.RELIABLE)
                and not (volatile
                         and info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL)]

    def warn_best_effort_readers(self) -> None:
        from rclpy.qos import ReliabilityPolicy
        for stream in self.streams.values():
            topic = stream.publisher.topic_name
            readers = self.node.get_subscriptions_info_by_topic(topic)
            # A node that also reads the topic reliably (stereo_node does) loses nothing.
            reliable = {(info.node_namespace, info.node_name) for info in readers
                        if info.qos_profile.reliability == ReliabilityPolicy.RELIABLE}
            for info in readers:
                if info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT and \
                        (info.node_namespace, info.node_name) not in reliable:
                    print(f'bag_replay: warning: {info.node_namespace.rstrip("/")}/'
                          f'{info.node_name} subscribes to {topic} best effort: it '
                          'acknowledges nothing, so --fast cannot keep it from losing '
                          'messages', file=sys.stderr, flush=True)

    def wait_acked(self, stream: Stream, timeout: float | None) -> bool:
        from rclpy.duration import Duration
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self.stop.is_set():
            if stream.publisher.wait_for_all_acked(Duration(seconds=0.05)):
                return True
            if deadline is not None and time.monotonic() >= deadline:
                return False
        return False

    # -- publishing --------------------------------------------------------------------

    def publish(self, stream: Stream, raw: bytes) -> bool:
        """Publish, again and again while the writer is full (a reader pushing back)."""
        if type(raw) is not bytes:
            raw = bytes(raw)
        began = time.monotonic()
        while True:
            try:
                stream.publisher.publish(raw)
                break
            except self._rcl_error as error:
                if 'cannot publish data' not in str(error):
                    raise
                self.stats.blocked += 1
                if self.stop.is_set():
                    return False
        took = time.monotonic() - began
        if took > SLOW_PUBLISH:
            self.stats.held_back += took
        stream.published += 1
        if stream.window:
            self._keep_within_window(stream)
        return True

    def _keep_within_window(self, stream: Stream) -> None:
        """A transient-local topic in --fast keeps only its depth: once that many messages
        are unacknowledged, wait for the acknowledgements before publishing more."""
        stream.unacked += 1
        if stream.unacked >= stream.window:
            began = time.monotonic()
            self.wait_acked(stream, None)
            self.stats.held_back += time.monotonic() - began
            stream.unacked = 0

    def run_pass(self, start_ns: int, progress: Progress | None) -> None:
        fast, rate = self.options.fast, self.options.rate
        first_ns = last_ns = None
        wall0 = time.monotonic()
        count = 0
        names = set(self.streams)
        for topic, stamp, raw in self.source.messages(names, start_ns):
            if self.stop.is_set():
                break
            if first_ns is None:
                first_ns, wall0 = stamp, time.monotonic()
                if self.clock is not None and not fast:
                    self.clock.run_from(stamp, wall0)
            elif not fast:
                delay = wall0 + (stamp - first_ns) * 1e-9 / rate - time.monotonic()
                if delay > 0 and self.stop.wait(delay):
                    break
            if fast and self.clock is not None:
                self.clock.hold(stamp)
            if not self.publish(self.streams[topic], raw):
                break
            last_ns = stamp
            count += 1
            if progress is not None:
                progress.update(stamp, self.stats.messages + count, first_ns,
                                time.monotonic() - wall0, pass_messages=count)
        wall = time.monotonic() - wall0 if first_ns is not None else 0.0
        if progress is not None and last_ns is not None:
            progress.update(last_ns, self.stats.messages + count, first_ns, wall, force=True,
                            pass_messages=count)
            progress.close()
        if self.clock is not None and last_ns is not None:
            self.clock.hold(last_ns)
        self.stats.messages += count
        self.stats.wall += wall
        self.stats.passes += 1
        if first_ns is not None:
            self.stats.bag_seconds += (last_ns - first_ns) * 1e-9

    def finish(self) -> None:
        """Wait until every matched reader has acknowledged every message: a publisher
        destroyed earlier takes its unacknowledged messages with it."""
        timeout = None if self.options.fast else TIMED_ACK_TIMEOUT
        began = time.monotonic()
        told = False
        for stream in self.streams.values():
            while not self.wait_acked(stream, 2.0 if timeout is None else timeout):
                if self.stop.is_set() or timeout is not None:
                    print(f'bag_replay: {stream.publisher.topic_name}: not every subscriber '
                          'acknowledged the last messages', file=sys.stderr, flush=True)
                    break
                if not told:
                    print('bag_replay: waiting for the subscribers to acknowledge the last '
                          'messages (Ctrl-C to stop)', file=sys.stderr, flush=True)
                    told = True
        self.stats.ack_wait = time.monotonic() - began


class BagClock:
    """The bag's time on ``/clock`` (rosgraph_msgs/Clock), as ``ros2 bag play --clock``:
    nodes with ``use_sim_time`` then live in the bag's time.

    A thread publishes it ``hz`` times a second (wall clock). While a timed replay runs,
    the time runs from the first message's stamp at ``rate`` times the wall clock; before
    it, and after a pass, it holds (at the start, at the last message); in ``--fast`` it is
    the stamp of the message being published. A ``--loop`` goes back to the start each
    pass, as a bag played again would."""

    def __init__(self, node, hz: float, rate: float):
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock
        self._message = Clock
        # rosbag2's clock QoS: best effort, the latest only (a late tick is worthless).
        self._publisher = node.create_publisher(
            Clock, '/clock', QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        self.period = 1.0 / hz
        self.rate = rate
        self._lock = threading.Lock()
        self._anchor: tuple[int, float | None] = (0, None)   # bag ns, wall when it was
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._tick, name='bag_clock', daemon=True)
        self.published = 0

    def start(self, bag_ns: int) -> None:
        self.hold(bag_ns)
        self._thread.start()

    def hold(self, bag_ns: int) -> None:
        """Stand at ``bag_ns`` until told otherwise."""
        with self._lock:
            moved = self._anchor != (bag_ns, None)
            self._anchor = (bag_ns, None)
        if moved:
            self._publish()

    def run_from(self, bag_ns: int, wall: float) -> None:
        """Run from ``bag_ns`` at monotonic time ``wall``, ``rate`` times as fast."""
        with self._lock:
            self._anchor = (bag_ns, wall)
        self._publish()

    def now_ns(self) -> int:
        with self._lock:
            bag_ns, wall = self._anchor
        if wall is None:
            return bag_ns
        return bag_ns + round((time.monotonic() - wall) * self.rate * 1e9)

    def _publish(self) -> None:
        from inhand_common.ros_time import stamp_from_nanoseconds
        self._publisher.publish(self._message(clock=stamp_from_nanoseconds(self.now_ns())))
        self.published += 1

    def _tick(self) -> None:
        while not self._done.wait(self.period):
            self._publish()

    def close(self) -> int:
        """Stop the thread; the number of /clock messages published."""
        self._done.set()
        if self._thread.is_alive():
            self._thread.join()
        return self.published


# -- the summary ---------------------------------------------------------------------------

def replay_summary(stats: ReplayStats, streams: dict[str, Stream], options: ReplayOptions) -> str:
    asked = 'as fast as the subscribers take them' if options.fast else f'asked {options.rate:g}x'
    factor = f'{stats.bag_seconds / stats.wall:.2f}x' if stats.wall > 0 else 'n/a'
    rate = stats.messages / stats.wall if stats.wall > 0 else 0.0
    loops = f' in {stats.passes} passes' if stats.passes > 1 else ''
    lines = [f'bag_replay: published {stats.messages} messages{loops} in {stats.wall:.3f} s '
             f'wall time: {stats.bag_seconds:.3f} s of the bag at {factor} real time '
             f'({asked}), {rate:,.0f} msg/s' + (' (stopped)' if stats.stopped else '')]
    width = max(len(n) for n in streams)
    for name, stream in sorted(streams.items()):
        lines.append(f'  {name:<{width}}  {stream.published:>9}  {stream.msgtype}')
    if options.clock_hz:
        lines.append(f'  /clock: {stats.clock_messages} messages (the bag\'s time, '
                     f'{options.clock_hz:g} Hz)')
    if options.fast and (stats.held_back > 0.01 or stats.blocked):
        lines.append(f'  held back {stats.held_back:.2f} s by subscribers that were not '
                     f'keeping up ({stats.blocked} publish attempts found the writer full)')
    if options.fast and stats.ack_wait > 0.05 and stats.passes == 1:
        end = stats.wall + stats.ack_wait
        lines.append(f'  every message acknowledged {end:.3f} s after the first was published: '
                     f'{stats.bag_seconds / end:.2f}x real time end to end')
    return '\n'.join(lines)
