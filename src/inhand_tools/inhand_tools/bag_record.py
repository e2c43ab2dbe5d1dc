"""``bag_record``: record topics into an MCAP bag (rosbag2 format, written with rosbags).

    bag_record -o OUTPUT [TOPIC ...] [--all] [--duration SECONDS] [--force]
               [--ros-args ...]

Subscribes to each TOPIC (relative names resolve in the node's namespace) as soon as the
graph shows it with a publisher, with the type the graph reports, and writes every message
as the raw CDR bytes received (``raw=True``: no deserialisation), stamped with the time
of receipt, into the bag folder OUTPUT (``OUTPUT/OUTPUT.mcap`` and ``metadata.yaml``).
``--all`` records every topic with a publisher, including ones that appear later
(``rosout`` and ``parameter_events`` only when named). Message definitions come from
rosbags' ROS 2 Jazzy type store, so any rosbag2 tool can read the bag.

QoS: the subscription matches the publishers (reliable when they all are, so a reliable
publisher gets acknowledgements; transient-local when they all offer it, so the latest
message of a latched topic such as a map, published before the recorder started, is
recorded too) with KEEP_ALL history: a message stays in the DDS queue until it is
written, and a publisher faster than the recorder is held back rather than overwriting
what was not written yet. The publishers' offered QoS is stored with each topic, so
``bag_replay`` offers the same again.

Stopping: Ctrl-C (SIGINT), SIGTERM or the end of ``--duration`` (counted from the first
subscription) ends the loop; the recorder then takes every message already in its
queues (until it finds them empty, at most 2 s), and closes the bag (chunk index,
summary, metadata.yaml). Nothing received is lost. A recorder killed outright
(SIGKILL, power loss) leaves an MCAP without its summary: ``bag_replay`` and
``build_map`` still read it up to the last complete chunk (1 MiB).

OUTPUT must not exist; ``--force`` replaces an existing bag folder (a folder holding only
metadata.yaml, .mcap and .db3 files), never anything else.
Exit status: 0 recorded, 2 refused arguments, unknown message type.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

from inhand_tools.bag_io import UnknownMessageType, message_class, positive_float

EXIT_REFUSED = 2
DISCOVERY_PERIOD = 0.2   # s between looks at the graph for topics still to subscribe
DRAIN_IDLE = 0.05        # s: spin_once timeout while draining
QUEUE_EMPTY = 0.002      # s: a spin_once that waited this long found the queue empty
DRAIN_MAX = 2.0          # s: never drain longer than this
QUIET_TOPICS = ('/rosout', '/parameter_events')
BAG_FILES = ('.mcap', '.db3', '.yaml', '.zstd')


def parse_args(argv: list[str]) -> argparse.Namespace:
    parts = __doc__.split('\n\n')
    parser = argparse.ArgumentParser(
        prog='bag_record', description=parts[0].replace('\n', ' ').replace('``', ''),
        epilog='\n\n'.join(parts[2:]), formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('-o', '--output', type=Path, required=True,
                        help='bag folder to create')
    parser.add_argument('topics', nargs='*', metavar='TOPIC', help='topics to record')
    parser.add_argument('--all', action='store_true', help='record every topic with a publisher')
    parser.add_argument('--duration', type=positive_float, metavar='SECONDS',
                        help='stop after SECONDS of recording')
    parser.add_argument('--force', action='store_true', help='replace an existing bag folder')
    args = parser.parse_args(argv)
    if not args.topics and not args.all:
        parser.error('name the topics to record, or --all')
    return args


def prepare_output(output: Path, force: bool) -> None:
    """Refuse an existing OUTPUT; with ``force`` remove it if it is a bag folder."""
    if not output.exists() and not output.is_symlink():
        return
    if not force:
        raise ValueError(f'{output}: exists already (--force replaces a bag folder)')
    if output.is_dir() and not output.is_symlink():
        entries = list(output.iterdir())
        if all(e.is_file() and e.suffix in BAG_FILES for e in entries):
            shutil.rmtree(output)
            return
    raise ValueError(f'{output}: exists and is not a bag folder; not replacing it')


class Recorder:
    """Subscriptions that write into a rosbags Writer as messages arrive."""

    def __init__(self, node, writer, requested: list[str], record_all: bool):
        from rosbags.typesys import Stores, get_typestore
        self.node, self.writer = node, writer
        self.store = get_typestore(Stores.ROS2_JAZZY)
        self.requested, self.record_all = requested, record_all
        self.counts: dict[str, int] = {}
        self.types: dict[str, str] = {}
        self.ignored: set[str] = set()
        self.total = 0
        self.busy = 0.0  # s spent in message callbacks (tells waiting from working)
        self.errors: list[str] = []
        self.first_subscription: float | None = None
        self._subscriptions = []

    def waiting_for(self) -> list[str]:
        return [t for t in self.requested if t not in self.counts]

    def discover(self) -> None:
        from inhand_tools.bag_ros import bag_qos, describe_qos, graph_types, matching_qos
        graph = graph_types(self.node)
        candidates = list(self.requested)
        if self.record_all:
            candidates += sorted(t for t in graph if t not in QUIET_TOPICS)
        for topic in dict.fromkeys(candidates):
            if topic in self.counts or topic in self.ignored or topic not in graph:
                continue
            infos = self.node.get_publishers_info_by_topic(topic)
            if not infos:
                continue  # the QoS to ask for depends on the publishers
            types = sorted(set(graph[topic]))
            try:
                if len(types) > 1:
                    raise UnknownMessageType(f'{topic} has several types on the graph: '
                                             f'{", ".join(types)}')
                msgtype = types[0]
                cls = message_class(msgtype)
                if msgtype not in self.store.types:
                    raise UnknownMessageType(f"message type '{msgtype}' of {topic} is not in "
                                             "rosbags' ROS 2 Jazzy type store: its definition "
                                             'cannot be written to the bag')
            except UnknownMessageType as error:
                self.ignored.add(topic)
                if topic in self.requested:
                    self.errors.append(str(error))
                else:
                    print(f'bag_record: not recording {topic}: {error}', file=sys.stderr,
                          flush=True)
                continue
            qos = matching_qos(infos, keep_all=True)
            connection = self.writer.add_connection(
                topic, msgtype, typestore=self.store,
                offered_qos_profiles=[bag_qos(i.qos_profile) for i in infos])
            self.counts[topic] = 0
            self.types[topic] = msgtype

            def on_message(raw, connection=connection, topic=topic):
                began = time.monotonic()
                self.writer.write(connection, time.time_ns(), raw)
                self.counts[topic] += 1
                self.total += 1
                self.busy += time.monotonic() - began

            self._subscriptions.append(
                self.node.create_subscription(cls, topic, on_message, qos, raw=True))
            if self.first_subscription is None:
                self.first_subscription = time.monotonic()
            print(f'bag_record: recording {topic} ({msgtype}; {describe_qos(qos)})',
                  file=sys.stderr, flush=True)


def record(args, full_argv: list[str]) -> int:
    from rclpy.executors import ExternalShutdownException
    from rclpy.experimental import EventsExecutor
    from rclpy.node import Node
    from rosbags.rosbag2 import StoragePlugin, Writer
    from inhand_tools.bag_ros import RosSession

    writer = node = executor = recorder = None
    began = time.monotonic()
    with RosSession(full_argv, second_signal_interrupts=False) as session:
        try:
            node = Node('bag_record', enable_rosout=False, start_parameter_services=False)
            try:
                requested = [node.resolve_topic_name(t) for t in args.topics]
            except Exception as error:  # rclpy's InvalidTopicNameException and friends
                print(f'bag_record: {error}', file=sys.stderr)
                return EXIT_REFUSED
            writer = Writer(args.output, version=9, storage_plugin=StoragePlugin.MCAP)
            writer.open()
            recorder = Recorder(node, writer, requested, args.all)
            executor = EventsExecutor(context=node.context)
            executor.add_node(node)
            recorder.discover()
            if recorder.waiting_for():
                print(f'bag_record: waiting for {", ".join(recorder.waiting_for())} to appear '
                      'with a publisher', file=sys.stderr, flush=True)
            next_look = time.monotonic() + DISCOVERY_PERIOD
            while not session.stop.is_set() and not recorder.errors:
                executor.spin_once(timeout_sec=0.05)
                now = time.monotonic()
                if now >= next_look and (recorder.waiting_for() or args.all):
                    recorder.discover()
                    next_look = now + DISCOVERY_PERIOD
                if args.duration is not None and recorder.first_subscription is not None \
                        and now - recorder.first_subscription >= args.duration:
                    break
            drain(executor, recorder)
        except ExternalShutdownException:
            pass
        finally:
            if executor is not None:
                executor.shutdown()
            if node is not None:
                node.destroy_node()
            if writer is not None and writer.storage is not None:
                writer.close()
    if recorder is None:
        return EXIT_REFUSED
    for error in recorder.errors:
        print(f'bag_record: {error}', file=sys.stderr)
    print(summary(recorder, args.output, time.monotonic() - began), flush=True)
    return EXIT_REFUSED if recorder.errors else 0


def drain(executor, recorder: Recorder) -> None:
    """Take what was queued when the recording stopped.

    The executor's event queue holds everything DDS has received and not yet handed to a
    callback. Spin until one ``spin_once`` had to wait for an event (the time it took,
    less the time spent in our callbacks, is over QUEUE_EMPTY): the queue was empty then,
    so everything received before the stop is written. A publisher that keeps sending
    does not keep the drain going, and DRAIN_MAX bounds it anyway.
    """
    end = time.monotonic() + DRAIN_MAX
    while time.monotonic() < end:
        busy_before = recorder.busy
        began = time.monotonic()
        executor.spin_once(timeout_sec=DRAIN_IDLE)
        waited = time.monotonic() - began - (recorder.busy - busy_before)
        if waited > QUEUE_EMPTY:
            return


def summary(recorder: Recorder, output: Path, wall: float) -> str:
    topics = len(recorder.counts)
    lines = [f'bag_record: wrote {recorder.total} messages on {topics} '
             f'topic{"" if topics == 1 else "s"} to {output} in {wall:.1f} s']
    width = max((len(t) for t in recorder.counts), default=0)
    for topic, count in sorted(recorder.counts.items()):
        lines.append(f'  {topic:<{width}}  {count:>9}  {recorder.types[topic]}')
    missing = recorder.waiting_for()
    if missing and not recorder.errors:
        lines.append(f'  never appeared with a publisher: {", ".join(missing)}')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    from rclpy.utilities import remove_ros_args
    full = list(sys.argv if argv is None else ['bag_record', *argv])
    args = parse_args(remove_ros_args(full)[1:])
    try:
        prepare_output(args.output, args.force)
    except (ValueError, OSError) as error:
        print(f'bag_record: {error}', file=sys.stderr)
        return EXIT_REFUSED
    return record(args, full)


if __name__ == '__main__':
    raise SystemExit(main())
