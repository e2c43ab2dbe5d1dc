"""Record topics into an MCAP bag as they are published: the library behind the
``bag_record`` command.

``prepare_output`` refuses (or, forced, removes) an existing bag folder, ``record_topics``
subscribes and writes in a ROS session of its own until stopped and returns the
``Recorder`` with what it wrote, ``recording_summary`` says so. What is recorded, with
which QoS and how stopping loses nothing is told in the command's help
(:mod:`inhand_tools.commands.bag_record`).

No rclpy import at module level, so the command checks its arguments before the ROS
runtime loads.
"""

from __future__ import annotations

import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from inhand_common.mcap_integrity import stamp_bag_crcs
from inhand_tools.message_types import UnknownMessageType, message_class

__all__ = ['RecordRequest', 'Recorder', 'prepare_output', 'record_topics', 'recording_summary']

DISCOVERY_PERIOD = 0.2   # s between looks at the graph for topics still to subscribe
DRAIN_IDLE = 0.05        # s: spin_once timeout while draining
QUEUE_EMPTY = 0.002      # s: a spin_once that waited this long found the queue empty
DRAIN_MAX = 2.0          # s: never drain longer than this
FLUSH_PERIOD = 1.0       # s: what was recorded reaches the file this often (a kill -9 loses
#                          at most this much; rosbags would hold up to 1 MB in memory)
QUIET_TOPICS = ('/rosout', '/parameter_events')
BAG_FILES = ('.mcap', '.db3', '.yaml', '.zstd')


@dataclass
class RecordRequest:
    """What to record (the command's arguments)."""

    output: Path                   # the bag folder to create
    topics: list[str]              # as given: relative names resolve in the node's namespace
    record_all: bool = False       # every topic with a publisher, also ones appearing later
    duration: float | None = None  # s from the first subscription; None: until stopped


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

    def flush(self) -> None:
        """Write what is held in memory to the file: rosbags' MCAP writer keeps the
        current chunk (up to 1 MB) in memory until it is full or the bag is closed, so a
        recorder killed with -9 left a 0-byte file. Closing the chunk early writes it and
        its message indexes; without the footer a kill leaves, the bag is read record by
        record (bag_source.py). Uses the writer's storage object, not a public API: when
        it changes, nothing is flushed early."""
        storage = getattr(self.writer, 'storage', None)
        chunk = getattr(storage, 'chunk', None)
        held = getattr(getattr(chunk, 'bio', None), 'tell', None)   # bytes in the chunk
        if held is None or not held() or not callable(getattr(storage, 'close_chunk', None)):
            return
        storage.close_chunk()
        storage.bio.flush()

    def waiting_for(self) -> list[str]:
        return [t for t in self.requested if t not in self.counts]

    def discover(self) -> None:
        """Subscribe to every wanted topic the graph now shows with a publisher."""
        from inhand_tools.ros_session import graph_types
        graph = graph_types(self.node)
        for topic in self._candidates(graph):
            if topic in self.counts or topic in self.ignored or topic not in graph:
                continue
            infos = self.node.get_publishers_info_by_topic(topic)
            if not infos:
                continue  # the QoS to ask for depends on the publishers
            try:
                msgtype, cls = self._recordable_type(topic, graph[topic])
            except UnknownMessageType as error:
                self._refuse(topic, error)
                continue
            self._subscribe(topic, msgtype, cls, infos)

    def _candidates(self, graph: dict[str, list[str]]) -> list[str]:
        """The requested topics, then with --all every other topic but the quiet ones."""
        candidates = list(self.requested)
        if self.record_all:
            candidates += sorted(t for t in graph if t not in QUIET_TOPICS)
        return list(dict.fromkeys(candidates))

    def _recordable_type(self, topic: str, types: list[str]) -> tuple[str, object]:
        """The topic's one type and its class; UnknownMessageType unless both this ROS
        installation (to subscribe) and rosbags' type store (to write the definition into
        the bag) know it."""
        types = sorted(set(types))
        if len(types) > 1:
            raise UnknownMessageType(f'{topic} has several types on the graph: '
                                     f'{", ".join(types)}')
        msgtype = types[0]
        cls = message_class(msgtype)
        if msgtype not in self.store.types:
            raise UnknownMessageType(f"message type '{msgtype}' of {topic} is not in "
                                     "rosbags' ROS 2 Jazzy type store: its definition "
                                     'cannot be written to the bag')
        return msgtype, cls

    def _refuse(self, topic: str, error: UnknownMessageType) -> None:
        """A requested topic that cannot be recorded ends the recording (an error); one
        found by --all is left out with a notice."""
        self.ignored.add(topic)
        if topic in self.requested:
            self.errors.append(str(error))
        else:
            print(f'bag_record: not recording {topic}: {error}', file=sys.stderr, flush=True)

    def _subscribe(self, topic: str, msgtype: str, cls, infos: list) -> None:
        """A raw subscription matching the publishers, with KEEP_ALL history (a message
        stays in the DDS queue until written); their offered QoS goes into the bag."""
        from inhand_tools.qos_profiles import bag_qos, describe_qos, matching_qos
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


def record_topics(ros_args: list[str], request: RecordRequest) -> Recorder | None:
    """Record in a ROS session started with ``ros_args`` (the full command line, for
    ``--ros-args``) until SIGINT/SIGTERM, the end of ``request.duration`` or a requested
    topic that cannot be recorded; then drain the queues and close the bag.

    Returns the Recorder (counts, types, errors), None if ROS shut down before it
    started. InvalidTopicName for a topic name rcl cannot expand.
    """
    from rclpy.executors import ExternalShutdownException
    from rclpy.experimental import EventsExecutor
    from rclpy.node import Node
    from rosbags.rosbag2 import StoragePlugin, Writer

    from inhand_tools.ros_session import RosSession, resolve_topic

    writer = node = executor = recorder = None
    with RosSession(ros_args, second_signal_interrupts=False) as session:
        try:
            node = Node('bag_record', enable_rosout=False, start_parameter_services=False)
            requested = [resolve_topic(node, t) for t in request.topics]
            writer = Writer(request.output, version=9, storage_plugin=StoragePlugin.MCAP)
            writer.open()
            recorder = Recorder(node, writer, requested, request.record_all)
            executor = EventsExecutor(context=node.context)
            executor.add_node(node)
            _record_until_stopped(executor, recorder, session.stop, request)
            drain(executor, recorder)
        except ExternalShutdownException:
            pass
        finally:
            # the bag is closed last, after the subscriptions that write into it
            if executor is not None:
                executor.shutdown()
            if node is not None:
                node.destroy_node()
            if writer is not None and writer.storage is not None:
                writer.close()
                # rosbags writes no CRCs; with them a damaged message is found on reading
                stamp_bag_crcs(request.output)
    return recorder


def _record_until_stopped(executor, recorder: Recorder, stop, request: RecordRequest) -> None:
    """Spin, looking at the graph every DISCOVERY_PERIOD for topics still to subscribe
    (with --all, for new ones), until stopped, an error or the duration is over."""
    recorder.discover()
    if recorder.waiting_for():
        print(f'bag_record: waiting for {", ".join(recorder.waiting_for())} to appear '
              'with a publisher', file=sys.stderr, flush=True)
    next_look = time.monotonic() + DISCOVERY_PERIOD
    next_flush = time.monotonic() + FLUSH_PERIOD
    while not stop.is_set() and not recorder.errors:
        executor.spin_once(timeout_sec=0.05)
        now = time.monotonic()
        if now >= next_flush:
            recorder.flush()
            next_flush = now + FLUSH_PERIOD
        if now >= next_look and (recorder.waiting_for() or request.record_all):
            recorder.discover()
            next_look = now + DISCOVERY_PERIOD
        if request.duration is not None and recorder.first_subscription is not None \
                and now - recorder.first_subscription >= request.duration:
            break


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


def recording_summary(recorder: Recorder, output: Path, wall: float) -> str:
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
