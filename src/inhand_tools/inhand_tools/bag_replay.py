"""``bag_replay``: publish a bag's messages on their topics, on the bag's timetable or as
fast as the subscribers take them.

    bag_replay BAG [--rate FACTOR | --fast] [--loop] [--start-offset SECONDS]
                   [--topics T [T ...]] [--wait-subscribers SECONDS] [--quiet]
                   [--ros-args ...]

Each message goes out as the raw CDR bytes the bag holds (no deserialisation), on the
bag's topic made relative (``/polhemus/thumb/pose`` -> ``polhemus/thumb/pose``, so a
namespace or a remapping given with ``--ros-args`` applies), with the message type the bag
names (``pkg/msg/Type`` -> ``pkg.msg.Type``). The QoS is the one the bag recorded as
offered (reliable or best effort, transient-local or volatile, the depth) and otherwise
reliable/volatile depth 1000. Timing: the gaps between the bag's timestamps divided by
``--rate`` (default 1), after waiting up to 1 s (``--wait-subscribers``) for a
subscriber on every topic: a message published before a subscriber is matched never
reaches it. ``--start-offset`` skips the bag's first seconds; ``--loop`` starts again at
the end until Ctrl-C. A progress line goes to stderr (redrawn on a terminal, every 10%
otherwise) and a summary to stdout at the end. A truncated MCAP bag is replayed up to
its cut (read record by record, as ``build_map`` does) and said so.

``--fast``: as fast as the subscribers keep up, with nothing lost. How:

1. Before the first message it waits until every replayed topic has a matched
   subscriber (``--wait-subscribers S`` gives up after S seconds and starts anyway).
   Messages published before a reader is matched would never reach it.
2. Every topic is published reliable. Volatile topics use KEEP_ALL history: the writer
   keeps each message until every matched reliable reader has acknowledged it, and a
   reader acknowledges only what it has room for in its own history. A KEEP_ALL
   subscriber therefore pushes back: once its queue and ours are full (about 5000
   messages each with Fast DDS's default resource limits), ``publish()`` blocks, and
   after Fast DDS's max_blocking_time (100 ms) it fails with "cannot publish data";
   bag_replay then publishes the same message again, so the replay runs at the pace
   of the slowest subscriber and the summary says how long it was held back.
   Transient-local topics keep their recorded depth (KEEP_ALL would hand late joiners
   the whole history) and are paced by acknowledgements instead: when as many messages
   as the depth are unacknowledged, it waits until they are acknowledged.
3. At the end it waits until every message is acknowledged before destroying the
   publishers: a writer destroyed earlier takes its unacknowledged messages with it.
   Acknowledgements follow heartbeats, which Fast DDS sends every 3 s by default; this
   process asks for one every 20 ms (a default data-writer profile written to a
   temporary file, only when FASTRTPS_DEFAULT_PROFILES_FILE is not set already), so
   acknowledgements come within milliseconds.

The limits, stated plainly: DDS acknowledges a message when it is in the reader's
history, not when the subscriber's callback has taken it. A subscriber with KEEP_LAST
history of depth D (the mapping nodes use D = 1000) that falls more than D messages
behind loses the oldest in its own queue whatever the publisher does; a best-effort
subscriber never acknowledges anything. Subscribe with KEEP_ALL (or a depth above the
bag's message count) to be fed without loss at any speed; bag_replay warns about
best-effort subscribers (the history of a remote reader is not visible in discovery).
Measured here (2 cores, 60 s of 240 Hz poses from 4 stations, 57,600 messages): a raw
KEEP_ALL subscriber on the EventsExecutor takes 50,000-80,000 messages/s and gets all of
them; one on the SingleThreadedExecutor takes about 4,000/s and gets all of them (the
replay is held back to its pace); the same with KEEP_LAST 1000 got 9,281 of 57,600.

Exit status: 0 done (or stopped with Ctrl-C), 1 the bag is truncated or damaged (what
could be read was replayed), 2 refused arguments or bag.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from inhand_tools.bag_io import (BagError, BagSource, Progress, UnknownMessageType,
                                 message_class, non_negative_float, positive_float,
                                 relative_name)

EXIT_DAMAGED = 1
EXIT_REFUSED = 2
HEARTBEAT_NS = 20_000_000
TIMED_WAIT = 1.0          # s: a timed replay waits this long at most for subscribers
TIMED_ACK_TIMEOUT = 5.0   # s: at the end of a timed replay, wait at most this for acks
SLOW_PUBLISH = 0.002      # s: a publish() that took longer was held back by a reader

FASTDDS_PROFILE = f"""<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <data_writer profile_name="bag_replay_writer" is_default_profile="true">
    <times>
      <heartbeatPeriod><sec>0</sec><nanosec>{HEARTBEAT_NS}</nanosec></heartbeatPeriod>
    </times>
  </data_writer>
</profiles>
"""


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
class Stats:
    messages: int = 0
    wall: float = 0.0
    bag_seconds: float = 0.0
    passes: int = 0
    held_back: float = 0.0
    blocked: int = 0
    ack_wait: float = 0.0    # s after the last publish until every message was acknowledged
    stopped: bool = False
    per_topic: dict = field(default_factory=dict)


def parse_args(argv: list[str]) -> argparse.Namespace:
    parts = __doc__.split('\n\n')
    parser = argparse.ArgumentParser(
        prog='bag_replay', description=parts[0].replace('\n', ' ').replace('``', ''),
        epilog='\n\n'.join(parts[2:]), formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('bag', type=Path, help='bag folder, or .mcap / .db3 file')
    pace = parser.add_mutually_exclusive_group()
    pace.add_argument('--rate', type=positive_float, default=1.0, metavar='FACTOR',
                      help='time scale: 2 plays twice as fast, 0.5 half as fast (default 1)')
    pace.add_argument('--fast', action='store_true',
                      help='as fast as the subscribers take the messages, none lost')
    parser.add_argument('--loop', action='store_true', help='start again at the end')
    parser.add_argument('--start-offset', type=non_negative_float, default=0.0,
                        metavar='SECONDS', help="skip the bag's first SECONDS")
    parser.add_argument('--topics', nargs='+', metavar='T',
                        help='replay only these topics (default: all)')
    parser.add_argument('--wait-subscribers', type=non_negative_float, metavar='SECONDS',
                        help='before starting, wait up to SECONDS for a subscriber on every '
                        'topic (default: --fast waits as long as it takes; a timed replay '
                        'waits up to 1 s, time for running subscribers to be discovered, '
                        'so their first messages are not lost; 0: start at once)')
    parser.add_argument('--quiet', action='store_true', help='no progress line')
    return parser.parse_args(argv)


def plan_streams(source: BagSource, wanted: list[str] | None) -> dict[str, Stream]:
    """The topics to replay with their classes; BagError for anything unusable."""
    available = {name: topic for name, topic in source.topics.items()}
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


def fastdds_profile() -> Path | None:
    """A default data-writer profile with a 20 ms heartbeat, unless the user has one."""
    rmw = os.environ.get('RMW_IMPLEMENTATION', '') or 'rmw_fastrtps_cpp'
    if not rmw.startswith('rmw_fastrtps') or os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE') \
            or os.environ.get('FASTDDS_DEFAULT_PROFILES_FILE'):
        return None
    handle, path = tempfile.mkstemp(prefix='bag_replay_fastdds_', suffix='.xml')
    with os.fdopen(handle, 'w') as out:
        out.write(FASTDDS_PROFILE)
    os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = path
    return Path(path)


class Replayer:
    def __init__(self, session, node, source: BagSource, streams: dict[str, Stream],
                 args: argparse.Namespace):
        from rclpy.impl.implementation_singleton import rclpy_implementation
        from rclpy.qos import DurabilityPolicy
        from inhand_tools.bag_ros import replay_qos
        self.session, self.node, self.source, self.args = session, node, source, args
        self.streams = streams
        self.stop = session.stop
        self.stats = Stats()
        self._rcl_error = rclpy_implementation.RCLError
        for stream in streams.values():
            stream.qos = replay_qos(stream.recorded_qos, fast=args.fast)
            if args.fast and stream.qos.durability == DurabilityPolicy.TRANSIENT_LOCAL:
                stream.window = stream.qos.depth
            stream.publisher = node.create_publisher(stream.cls, stream.name, stream.qos)

    # -- waiting -----------------------------------------------------------------------

    def wait_for_subscribers(self) -> None:
        timeout = self.args.wait_subscribers
        if timeout is None:
            timeout = None if self.args.fast else TIMED_WAIT
        if timeout == 0.0:
            return
        from inhand_tools.bag_ros import wait_until

        def lonely():
            return [s.publisher.topic_name for s in self.streams.values()
                    if s.publisher.get_subscription_count() == 0]

        if lonely():
            limit = 'as long as it takes, Ctrl-C to stop' if timeout is None else \
                f'up to {timeout:g} s'
            print(f'bag_replay: waiting for a subscriber on {", ".join(lonely())} ({limit})',
                  file=sys.stderr, flush=True)
        if not wait_until(lambda: not lonely(), self.stop, timeout) and not self.stop.is_set():
            print(f'bag_replay: no subscriber on {", ".join(lonely())}; starting anyway',
                  file=sys.stderr, flush=True)
        if self.args.fast:
            self.warn_best_effort_readers()

    def warn_best_effort_readers(self) -> None:
        from rclpy.qos import ReliabilityPolicy
        for stream in self.streams.values():
            topic = stream.publisher.topic_name
            for info in self.node.get_subscriptions_info_by_topic(topic):
                if info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT:
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
            stream.unacked += 1
            if stream.unacked >= stream.window:
                began = time.monotonic()
                self.wait_acked(stream, None)
                self.stats.held_back += time.monotonic() - began
                stream.unacked = 0
        return True

    def run_pass(self, start_ns: int, progress: Progress | None) -> None:
        fast, rate = self.args.fast, self.args.rate
        first_ns = last_ns = None
        wall0 = time.monotonic()
        count = 0
        names = set(self.streams)
        for topic, stamp, raw in self.source.messages(names, start_ns):
            if self.stop.is_set():
                break
            if first_ns is None:
                first_ns, wall0 = stamp, time.monotonic()
            elif not fast:
                delay = wall0 + (stamp - first_ns) * 1e-9 / rate - time.monotonic()
                if delay > 0 and self.stop.wait(delay):
                    break
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
        self.stats.messages += count
        self.stats.wall += wall
        self.stats.passes += 1
        if first_ns is not None:
            self.stats.bag_seconds += (last_ns - first_ns) * 1e-9

    def run(self, start_ns: int) -> Stats:
        self.wait_for_subscribers()
        while not self.stop.is_set():
            progress = None
            if not self.args.quiet:
                prefix = f'pass {self.stats.passes + 1}: ' if self.args.loop else ''
                progress = Progress('bag_replay', self.source.start_ns, self.source.end_ns,
                                    prefix=prefix)
            self.run_pass(start_ns, progress)
            if not self.args.loop:
                break
        self.stats.stopped = self.stop.is_set()
        if not self.stats.stopped:
            self.finish()
        self.stats.per_topic = {name: s.published for name, s in self.streams.items()}
        return self.stats

    def finish(self) -> None:
        """Wait until every matched reader has acknowledged every message."""
        timeout = None if self.args.fast else TIMED_ACK_TIMEOUT
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


def summary(stats: Stats, streams: dict[str, Stream], args) -> str:
    asked = 'as fast as the subscribers take them' if args.fast else f'asked {args.rate:g}x'
    factor = f'{stats.bag_seconds / stats.wall:.2f}x' if stats.wall > 0 else 'n/a'
    rate = stats.messages / stats.wall if stats.wall > 0 else 0.0
    loops = f' in {stats.passes} passes' if stats.passes > 1 else ''
    lines = [f'bag_replay: published {stats.messages} messages{loops} in {stats.wall:.3f} s '
             f'wall time: {stats.bag_seconds:.3f} s of the bag at {factor} real time '
             f'({asked}), {rate:,.0f} msg/s' + (' (stopped)' if stats.stopped else '')]
    width = max(len(n) for n in streams)
    for name, stream in sorted(streams.items()):
        lines.append(f'  {name:<{width}}  {stream.published:>9}  {stream.msgtype}')
    if args.fast and (stats.held_back > 0.01 or stats.blocked):
        lines.append(f'  held back {stats.held_back:.2f} s by subscribers that were not '
                     f'keeping up ({stats.blocked} publish attempts found the writer full)')
    if args.fast and stats.ack_wait > 0.05 and stats.passes == 1:
        end = stats.wall + stats.ack_wait
        lines.append(f'  every message acknowledged {end:.3f} s after the first was published: '
                     f'{stats.bag_seconds / end:.2f}x real time end to end')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    from rclpy.utilities import remove_ros_args
    full = list(sys.argv if argv is None else ['bag_replay', *argv])
    args = parse_args(remove_ros_args(full)[1:])
    try:
        with BagSource(args.bag) as source:
            streams = plan_streams(source, args.topics)
            if args.start_offset > source.duration:
                raise BagError(f'{args.bag}: --start-offset {args.start_offset:g} s is past the '
                               f'end of the bag ({source.duration:.3f} s long)')
            if source.problem:
                print(f'bag_replay: {args.bag} is truncated or damaged: {source.problem}',
                      file=sys.stderr, flush=True)
            start_ns = source.start_ns + int(round(args.start_offset * 1e9))
            return replay(full, source, streams, args, start_ns)
    except BagError as error:
        print(f'bag_replay: {error}', file=sys.stderr)
        return EXIT_REFUSED


def replay(full_argv, source, streams, args, start_ns) -> int:
    from inhand_tools.bag_ros import RosSession
    from rclpy.node import Node
    profile = fastdds_profile()
    node = replayer = None
    try:
        with RosSession(full_argv) as session:
            try:
                node = Node('bag_replay')
                replayer = Replayer(session, node, source, streams, args)
                stats = replayer.run(start_ns)
            finally:
                if node is not None:
                    node.destroy_node()
    except KeyboardInterrupt:  # a second Ctrl-C while stopping
        return 0
    finally:
        if profile is not None:
            profile.unlink(missing_ok=True)
    print(summary(stats, streams, args), flush=True)
    if source.problem:
        print(f'bag_replay: the bag is truncated or damaged: {source.problem}. Replayed the '
              f'{stats.messages} messages that could be read.', file=sys.stderr)
        return EXIT_DAMAGED
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
