"""bag_replay, bag_record and topic_echo over real DDS, with real bags.

Timing and bytes of a timed replay, no loss with --fast into a deliberately slow
subscriber, recording a running publisher and a latched topic, a replay recorded back,
topic_echo's text, and the refusals of bad arguments.
"""

from __future__ import annotations

import contextlib
import gc
import re
import signal
import subprocess
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import rclpy
import yaml
from geometry_msgs.msg import PoseStamped
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from inhand_common.point_cloud import to_point_cloud2
from inhand_common.ros_time import stamp_from_seconds
from inhand_mapping.pose_cdr import decode_pose_stamped, encode_pose_stamped
from pose_sessions import sphere_session, write_pose_bag
from ros_helpers import BackgroundNode, PosePublisher, executable_path, running

pytestmark = pytest.mark.dds

STATIONS = ('object', 'thumb', 'index', 'middle')
POSE_TOPICS = [f'polhemus/{name}/pose' for name in STATIONS]
KEEP_ALL = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def run_tool(*args, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([executable_path(str(args[0])), *map(str, args[1:])],
                          capture_output=True, text=True, timeout=timeout)


def read_bag(path: Path) -> dict[str, list[tuple[int, bytes]]]:
    """topic (relative) -> [(timestamp ns, raw bytes)] in time order, read with rosbags."""
    from rosbags.highlevel import AnyReader
    out: dict[str, list[tuple[int, bytes]]] = defaultdict(list)
    with AnyReader([Path(path)]) as reader:
        for connection, timestamp, raw in reader.messages():
            out[connection.topic.lstrip('/')].append((timestamp, bytes(raw)))
    return dict(out)


def bag_connections(path: Path) -> dict:
    from rosbags.highlevel import AnyReader
    with AnyReader([Path(path)]) as reader:
        return {c.topic.lstrip('/'): c for c in reader.connections}


class RawListener(BackgroundNode):
    """Raw subscriptions (KEEP_ALL, reliable) keeping (arrival time, topic, bytes).

    ``stall`` seconds of sleep in the first callback and ``delay`` seconds in every other
    make it a deliberately slow subscriber.
    """

    def __init__(self, topics, qos=KEEP_ALL, stall: float = 0.0, delay: float = 0.0,
                 name: str = 'test_raw_listener'):
        super().__init__(name)
        self.received: list[tuple[float, str, bytes]] = []
        self.stall, self.delay = stall, delay
        for topic in topics:
            self.node.create_subscription(PoseStamped if 'pose' in topic else PointCloud2,
                                          topic, lambda raw, t=topic: self._add(t, raw), qos,
                                          raw=True)
        self.start()

    def _add(self, topic, raw):
        now = time.monotonic()
        with self.lock:
            self.received.append((now, topic, raw))
            first = len(self.received) == 1
        if first and self.stall:
            time.sleep(self.stall)
        elif self.delay:
            time.sleep(self.delay)

    def count(self) -> int:
        with self.lock:
            return len(self.received)

    def wait_for(self, count: int, timeout: float = 20.0) -> None:
        deadline = time.monotonic() + timeout
        while self.count() < count and time.monotonic() < deadline:
            time.sleep(0.02)
        assert self.count() >= count, f'{self.count()} of {count} messages arrived'

    def by_topic(self) -> dict[str, list[bytes]]:
        out = defaultdict(list)
        with self.lock:
            for _, topic, raw in self.received:
                out[topic].append(raw)
        return dict(out)


@contextlib.contextmanager
def listening_raw(topics, **kwargs):
    listener = RawListener(topics, **kwargs)
    try:
        yield listener
    finally:
        listener.close()


class Talker:
    """A node of the test process that publishes (no executor needed for that)."""

    def __init__(self, name='test_talker'):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node(name, context=self.context)

    def wait_matched(self, publisher, timeout: float = 20.0) -> None:
        deadline = time.monotonic() + timeout
        while publisher.get_subscription_count() == 0:
            assert time.monotonic() < deadline, f'no subscriber on {publisher.topic_name}'
            time.sleep(0.02)

    def close(self):
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@contextlib.contextmanager
def talking(name='test_talker'):
    talker = Talker(name)
    try:
        yield talker
    finally:
        talker.close()


def summary_factor(stdout: str) -> float:
    return float(re.search(r'at ([\d.]+)x real time', stdout).group(1))


@pytest.fixture(scope='module')
def gap_bag(tmp_path_factory):
    """3 s of 240 Hz 4-station poses with a 1.5 s pause after the first second."""
    frames, _ = sphere_session(seconds=3.0, surface_points=50, moving=True, seed=5)
    frames = [(t + (1.5 if k >= 240 else 0.0), frame) for k, (t, frame) in enumerate(frames)]
    return write_pose_bag(tmp_path_factory.mktemp('bags') / 'gap', frames)


def single_topic_bag(path: Path, count: int, rate: float = 240.0) -> Path:
    """``count`` poses on polhemus/object/pose only (one DDS writer/reader pair to fill)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/polhemus/object/pose',
                                           'geometry_msgs/msg/PoseStamped', typestore=store)
        for k in range(count):
            ns = 1000 * 10**9 + round(k * 1e9 / rate)
            writer.write(connection, ns, encode_pose_stamped(
                ns // 10**9, ns % 10**9, 'polhemus_source',
                (0.25 + 1e-5 * k, 0.0, 0.05, 0.0, 0.0, 0.0, 1.0)))
    return path


# -- bag_replay ------------------------------------------------------------------------------

def test_replay_at_rate_10_keeps_the_relative_timing_and_the_bytes(gap_bag):
    expected = read_bag(gap_bag)
    total = sum(len(v) for v in expected.values())
    gc.disable()  # a collection in this big test process would delay the arrivals we time
    try:
        with listening_raw(POSE_TOPICS) as listener:
            result = run_tool('bag_replay', gap_bag, '--rate', '10', '--wait-subscribers', '20',
                              '--quiet')
            assert result.returncode == 0, result.stdout + result.stderr
            listener.wait_for(total)
            received = list(listener.received)
    finally:
        gc.enable()
    # Every message, on its topic, byte for byte, in order.
    by_topic = defaultdict(list)
    for _, topic, raw in received:
        by_topic[topic].append(raw)
    assert {t: len(v) for t, v in by_topic.items()} == {t: len(v) for t, v in expected.items()}
    for topic, messages in expected.items():
        assert by_topic[topic] == [raw for _, raw in messages], topic
    # Arrival times follow the bag's timestamps divided by 10.
    next_index = defaultdict(int)
    arrival, bag_time = [], []
    for when, topic, _ in received:
        arrival.append(when)
        bag_time.append(expected[topic][next_index[topic]][0] * 1e-9)
        next_index[topic] += 1
    arrival, bag_time = np.array(arrival), np.array(bag_time)
    order = np.argsort(bag_time, kind='stable')
    arrival, bag_time = arrival[order] - arrival[order][0], (bag_time[order] - bag_time[0]) / 10
    residual = arrival - bag_time
    residual -= np.median(residual)
    assert np.percentile(np.abs(residual), 95) < 0.010, residual
    assert np.abs(residual).max() < 0.040, residual
    pause = np.argmax(np.diff(bag_time))
    assert abs(np.diff(arrival)[pause] - np.diff(bag_time)[pause]) < 0.025  # the 0.15 s gap
    assert 9.0 < summary_factor(result.stdout) < 10.5, result.stdout
    assert f'published {total} messages' in result.stdout
    for topic, messages in expected.items():
        assert re.search(rf'{topic}\s+{len(messages)}\s+geometry_msgs/msg/PoseStamped',
                         result.stdout), result.stdout


def test_fast_replay_loses_nothing_to_a_slow_subscriber(tmp_path):
    """The subscriber sleeps 1.5 s on its first message, then 50 us per message: far more
    than the writer and reader queues hold arrives meanwhile, so the replay must wait."""
    count = 12000
    bag = single_topic_bag(tmp_path / 'single', count)
    expected = [raw for _, raw in read_bag(bag)['polhemus/object/pose']]
    with listening_raw(['polhemus/object/pose'], stall=1.5, delay=5e-5) as listener:
        result = run_tool('bag_replay', bag, '--fast', '--quiet')
        assert result.returncode == 0, result.stdout + result.stderr
        listener.wait_for(count, timeout=30)
        time.sleep(0.2)
        got = listener.by_topic()['polhemus/object/pose']
    assert len(got) == count and got == expected
    assert 'held back' in result.stdout, result.stdout  # publish() found the writer full
    assert 'waiting for a subscriber on /polhemus/object/pose' in result.stderr


def test_the_live_views_reader_alone_does_not_start_a_replay(tmp_path):
    """live_view reads every topic: matched to it alone, a replay would start before the
    graph's own readers were discovered (and lose them everything). Its readers are still
    fed; --ignore-readers with no names counts every reader."""
    bag = single_topic_bag(tmp_path / 'single', 50)
    with listening_raw(['polhemus/object/pose'], name='live_view') as view:
        started = time.monotonic()
        # 6 s: discovery itself can take up to 3 s (Fast DDS announces every 3 s after its
        # first five tries)
        result = run_tool('bag_replay', bag, '--fast', '--quiet', '--wait-subscribers', '6')
        waited = time.monotonic() - started
        view.wait_for(50)
    assert result.returncode == 0, result.stdout + result.stderr
    assert 'read only by live_view, which the wait does not count' in result.stderr
    assert waited > 6.0
    with listening_raw(['polhemus/object/pose'], name='live_view') as view:
        result = run_tool('bag_replay', bag, '--fast', '--quiet', '--wait-subscribers', '30',
                          '--ignore-readers')
        view.wait_for(50)
    assert result.returncode == 0 and 'no subscriber' not in result.stderr, result.stderr


def test_fast_replay_of_a_truncated_bag_says_so_and_replays_the_readable_part(gap_bag,
                                                                           tmp_path):
    (mcap,) = gap_bag.glob('*.mcap')
    data = mcap.read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(data[:int(len(data) * 0.6)])
    with listening_raw(POSE_TOPICS) as listener:
        result = run_tool('bag_replay', cut, '--fast', '--quiet')
        published = int(re.search(r'published (\d+) messages', result.stdout).group(1))
        listener.wait_for(published)
    assert result.returncode == 1, result.stdout + result.stderr
    assert 'truncated or damaged' in result.stderr and 'up to byte' in result.stderr
    assert 0 < published < sum(len(v) for v in read_bag(gap_bag).values())
    assert listener.count() == published


def test_loop_and_start_offset(gap_bag):
    expected = read_bag(gap_bag)['polhemus/thumb/pose']
    start = expected[0][0] + 3 * 10**9  # 3 s into the bag: the last 1.5 s (360 frames)
    tail = [raw for t, raw in expected if t >= start]
    with listening_raw(['polhemus/thumb/pose']) as listener:
        with running(['bag_replay', str(gap_bag), '--fast', '--loop', '--start-offset', '3',
                      '--topics', 'polhemus/thumb/pose']) as replay:
            listener.wait_for(2 * len(tail) + 1)
            assert replay.interrupt() == 0, replay.output()
        got = listener.by_topic()['polhemus/thumb/pose']
    assert got[:2 * len(tail)] == tail + tail
    assert 'passes' in replay.output() and '(stopped)' in replay.output()


# -- bag_record ------------------------------------------------------------------------------

def test_record_a_running_publisher_then_sigint_keeps_every_message(tmp_path):
    frames, _ = sphere_session(seconds=2.0, surface_points=40, moving=True, seed=2)
    names = ['thumb', 'index']
    output = tmp_path / 'recorded'
    with running(['bag_record', '-o', str(output), *[f'polhemus/{n}/pose' for n in names]]) \
            as recorder:
        publisher = PosePublisher(names)
        try:
            publisher.wait_for_subscribers()
            publisher.publish([(t, {n: f[n] for n in names}) for t, f in frames],
                              rate_factor=4.0)
            for pub in publisher.publishers.values():
                assert pub.wait_for_all_acked(Duration(seconds=10))  # in the recorder's queue
        finally:
            publisher.close()
        assert recorder.interrupt() == 0, recorder.output()
    assert f'wrote {2 * len(frames)} messages on 2 topics' in recorder.output()
    bag = read_bag(output)
    for name in names:
        messages = bag[f'polhemus/{name}/pose']
        assert len(messages) == len(frames)
        for (t, frame), (_, raw) in zip(frames, messages, strict=False):
            sec, nanosec, frame_id, pose = decode_pose_stamped(raw)
            assert abs(sec + nanosec * 1e-9 - t) < 1e-6 and frame_id == 'polhemus_source'
            assert np.allclose(pose[:3], frame[name][0])
    connection = bag_connections(output)['polhemus/thumb/pose']
    assert connection.msgtype == 'geometry_msgs/msg/PoseStamped'
    assert connection.ext.offered_qos_profiles[0].reliability.name == 'RELIABLE'


def cloud(values) -> PointCloud2:
    points = np.zeros(len(values), dtype=[('x', 'f4'), ('y', 'f4'), ('z', 'f4'),
                                          ('intensity', 'f4')])
    points['x'] = values
    points['intensity'] = 0.875
    return to_point_cloud2(points, 'object', stamp_from_seconds(12.5))


def test_record_captures_a_latched_topic_and_replay_latches_it_again(tmp_path):
    from rclpy.serialization import deserialize_message
    output = tmp_path / 'latched'
    first, second = cloud([0.5, 0.25, 0.125]), cloud([1.0])
    with talking() as talker:
        publisher = talker.node.create_publisher(PointCloud2, 'occupancy/cloud', LATCHED)
        publisher.publish(first)  # before the recorder exists
        with running(['bag_record', '-o', str(output), 'occupancy/cloud']) as recorder:
            talker.wait_matched(publisher)
            assert publisher.wait_for_all_acked(Duration(seconds=10))
            # The replay below has this long to show the first to a late joiner (a new
            # participant's discovery takes 1-2 s here; 2 s failed half the time).
            time.sleep(6.0)
            publisher.publish(second)
            assert publisher.wait_for_all_acked(Duration(seconds=10))
            assert recorder.interrupt() == 0, recorder.output()
    messages = read_bag(output)['occupancy/cloud']
    # (compared as messages: rclpy leaves the CDR alignment padding uninitialised)
    assert [deserialize_message(raw, PointCloud2) for _, raw in messages] == [first, second]
    qos = bag_connections(output)['occupancy/cloud'].ext.offered_qos_profiles[0]
    assert qos.durability.name == 'TRANSIENT_LOCAL'
    # Replayed, the topic is transient-local again: a subscriber that comes after the first
    # message was published still gets it.
    with running(['bag_replay', str(output), '--quiet', '--wait-subscribers', '0']) as replay, \
            talking('test_late') as late:
        deadline = time.monotonic() + 20
        while not late.node.get_publishers_info_by_topic('/occupancy/cloud'):
            assert time.monotonic() < deadline, replay.output()
            time.sleep(0.05)
        (info,) = late.node.get_publishers_info_by_topic('/occupancy/cloud')
        assert info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
        time.sleep(0.3)
        with listening_raw(['occupancy/cloud'], qos=LATCHED) as listener:
            listener.wait_for(1, timeout=10)
            assert listener.received[0][2] == messages[0][1]
        replay.popen.wait(20)


def test_round_trip_replay_recorded_gives_the_same_messages(gap_bag, tmp_path):
    output = tmp_path / 'again'
    with running(['bag_record', '-o', str(output), *POSE_TOPICS]) as recorder:
        result = run_tool('bag_replay', gap_bag, '--fast', '--quiet')
        assert result.returncode == 0, result.stdout + result.stderr
        assert recorder.interrupt() == 0, recorder.output()
    original, again = read_bag(gap_bag), read_bag(output)
    assert set(again) == set(original)
    for topic in original:
        assert [raw for _, raw in again[topic]] == [raw for _, raw in original[topic]], topic


def test_a_recorder_killed_with_9_loses_at_most_about_a_second(tmp_path):
    """rosbags holds the current chunk in memory: a kill -9 left a 0-byte file. The
    recorder writes it out every second, and the bag without its footer reads record by
    record."""
    from inhand_common.bag_source import BagSource
    output = tmp_path / 'killed'
    rate, seconds = 100.0, 3.5
    with talking() as talker, running(['bag_record', '-o', str(output),
                                       'polhemus/thumb/pose']) as recorder:
        publisher = talker.node.create_publisher(PoseStamped, 'polhemus/thumb/pose', KEEP_ALL)
        talker.wait_matched(publisher)
        time.sleep(0.5)
        sent = []
        for k in range(int(rate * seconds)):
            raw = encode_pose_stamped(1000, k * 10_000_000, 'polhemus_source',
                                      (0.01 * k, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0))
            publisher.publish(raw)
            sent.append(raw)
            time.sleep(1.0 / rate)
        recorder.popen.send_signal(signal.SIGKILL)
        recorder.popen.wait()
    (mcap,) = output.glob('*.mcap')
    assert mcap.stat().st_size > 0
    with BagSource(output) as bag:
        got = [raw for _, _, raw in bag.messages({'polhemus/thumb/pose'})]
        assert bag.problem and 'record by record' in bag.problem
    assert got == sent[:len(got)]                       # what was written is whole
    assert len(got) >= len(sent) - 2.0 * rate, (len(got), len(sent))


def test_record_refuses_an_existing_output_unless_forced(tmp_path):
    output = tmp_path / 'taken'
    output.mkdir()
    (output / 'notes.txt').write_text('mine')
    result = run_tool('bag_record', '-o', output, 'chatter')
    assert result.returncode == 2 and 'exists already' in result.stderr
    result = run_tool('bag_record', '-o', output, 'chatter', '--force')
    assert result.returncode == 2 and 'is not a bag folder' in result.stderr
    assert (output / 'notes.txt').read_text() == 'mine'
    result = run_tool('bag_record', '-o', tmp_path / 'x')
    assert result.returncode == 2 and 'name the topics to record, or --all' in result.stderr


def test_record_all_for_a_duration(tmp_path):
    output = tmp_path / 'all'
    with pose_stream('record_all/pose', period=0.005):
        result = run_tool('bag_record', '-o', output, '--all', '--duration', '1', timeout=30)
    assert result.returncode == 0, result.stdout + result.stderr
    bag = read_bag(output)
    assert 'rosout' not in bag and 'parameter_events' not in bag
    stamps = [decode_pose_stamped(raw)[0] for _, raw in bag['record_all/pose']]
    assert 100 <= len(stamps) <= 260 and stamps == list(range(stamps[0], stamps[0] + len(stamps)))


# -- topic_echo ------------------------------------------------------------------------------

@contextlib.contextmanager
def pose_stream(topic: str, period: float = 0.01):
    """Publishes PoseStamped with position.x = 0.25 * k until the block ends."""
    with talking('test_pose_stream') as talker:
        publisher = talker.node.create_publisher(PoseStamped, topic, 100)
        stop = threading.Event()

        def loop():
            k = 0
            while not stop.is_set():
                msg = PoseStamped()
                msg.header.frame_id = 'polhemus_source'
                msg.header.stamp.sec = 100 + k
                msg.pose.position.x, msg.pose.position.y = 0.25 * k, -1.5
                msg.pose.orientation.w = 1.0
                publisher.publish(msg)
                k += 1
                stop.wait(period)

        thread = threading.Thread(target=loop, daemon=True)
        thread.start()
        try:
            yield
        finally:
            stop.set()
            thread.join(5)


def test_topic_echo_prints_messages_and_fields():
    with pose_stream('echo_test/pose'):
        result = run_tool('topic_echo', 'echo_test/pose', '-n', '3', timeout=30)
        field = run_tool('topic_echo', 'echo_test/pose', '-n', '2', '--field',
                         'pose.position.x', timeout=30)
    assert result.returncode == 0, result.stderr
    documents = [d for d in yaml.safe_load_all(result.stdout) if d is not None]
    assert len(documents) == 3 and result.stdout.count('---') == 3
    for document in documents:
        assert document['header']['frame_id'] == 'polhemus_source'
        assert document['pose']['position']['x'] == 0.25 * (document['header']['stamp']['sec']
                                                             - 100)
        assert document['pose']['position']['y'] == -1.5
        assert document['pose']['orientation'] == {'x': 0.0, 'y': 0.0, 'z': 0.0, 'w': 1.0}
    seconds = [d['header']['stamp']['sec'] for d in documents]
    assert seconds == list(range(seconds[0], seconds[0] + 3))
    assert field.returncode == 0, field.stderr
    values = [float(line) for line in field.stdout.split()]
    assert len(values) == 2 and values[1] - values[0] == 0.25
    assert 'header' not in field.stdout and '---' not in field.stdout


def test_topic_echo_decodes_a_latched_point_cloud():
    with talking() as talker:
        publisher = talker.node.create_publisher(PointCloud2, 'echo_test/cloud', LATCHED)
        publisher.publish(cloud(np.arange(8) * 0.125))
        result = run_tool('topic_echo', 'echo_test/cloud', '--once', timeout=30)
    assert result.returncode == 0, result.stderr
    assert 'transient-local' in result.stderr
    document = yaml.safe_load(result.stdout.split('---')[0])
    assert document['width'] == 8 and document['header']['frame_id'] == 'object'
    assert [f['name'] for f in document['fields']] == ['x', 'y', 'z', 'intensity']
    assert document['data'] == '<128 bytes, decoded below>'
    assert [p['x'] for p in document['points']] == [0.0, 0.125, 0.25, 0.375, 0.5]
    assert all(p['intensity'] == 0.875 for p in document['points'])
    assert '# first 5 of 8' in result.stdout


# -- refusals --------------------------------------------------------------------------------

@pytest.fixture(scope='module')
def foreign_type_bag(tmp_path_factory):
    """A bag holding a type rosbags knows but this ROS installation has no Python class for."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    TFMessage = store.types['tf2_msgs/msg/TFMessage']
    path = tmp_path_factory.mktemp('bags') / 'tf'
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/tf', TFMessage.__msgtype__, typestore=store)
        writer.write(connection, 1, store.serialize_cdr(TFMessage(transforms=[]),
                                                        TFMessage.__msgtype__))
    return path


@pytest.mark.parametrize('args, expected', [
    (['{tmp}/missing'], 'no such bag'),
    (['{tmp}/junk.mcap'], 'cannot open as a rosbag2 bag'),
    (['{tf}'], "unknown message type 'tf2_msgs/msg/TFMessage'"),
    (['{gap}', '--rate', '0'], "argument --rate: '0' must be a finite number > 0"),
    (['{gap}', '--rate', 'fast'], "argument --rate: 'fast' is not a number"),
    (['{gap}', '--rate', '2', '--fast'], 'not allowed with argument'),
    (['{gap}', '--topics', 'nope'], 'no topic nope in this bag'),
    (['{gap}', '--start-offset', '60'], 'past the end of the bag'),
], ids=['missing', 'foreign', 'unknown-type', 'rate-0', 'rate-word', 'rate-and-fast',
        'unknown-topic', 'offset-past-end'])
def test_replay_refuses_bad_arguments(args, expected, tmp_path, gap_bag, foreign_type_bag):
    (tmp_path / 'junk.mcap').write_bytes(b'not a bag at all')
    args = [a.format(tmp=tmp_path, tf=foreign_type_bag, gap=gap_bag) for a in args]
    result = run_tool('bag_replay', *args, timeout=30)
    assert result.returncode == 2, result.stdout + result.stderr
    assert expected in result.stderr, result.stderr
    assert 'Traceback' not in result.stderr


@pytest.mark.parametrize('args, expected', [
    (['x', '--type', 'nope_msgs/msg/Thing'], "unknown message type 'nope_msgs/msg/Thing'"),
    (['x', '--type', 'geometry_msgs/msg/PoseStamped', '--field', 'pose.height'],
     "no field 'height' in geometry_msgs/msg/Pose; it has position, orientation"),
    (['x', '-n', '0'], "argument -n/--count: '0' must be at least 1"),
], ids=['unknown-type', 'unknown-field', 'count-0'])
def test_topic_echo_refuses_bad_arguments(args, expected):
    result = run_tool('topic_echo', *args, timeout=30)
    assert result.returncode == 2, result.stdout + result.stderr
    assert expected in result.stderr, result.stderr


def test_tools_stop_on_sigterm_while_waiting(tmp_path):
    """Waiting for a topic that never comes; SIGTERM ends it cleanly with a valid bag."""
    output = tmp_path / 'empty'
    with running(['bag_record', '-o', str(output), 'never/there']) as recorder:
        deadline = time.monotonic() + 20
        while 'waiting for /never/there' not in recorder.output():
            assert time.monotonic() < deadline, recorder.output()
            time.sleep(0.05)
        recorder.popen.send_signal(signal.SIGTERM)
        assert recorder.popen.wait(10) == 0, recorder.output()
    assert 'never appeared with a publisher: /never/there' in recorder.output()
    assert read_bag(output) == {}


# -- topic_echo's text, without DDS ----------------------------------------------------------

def test_echo_text_is_yaml_with_arrays_cut_and_strings_quoted():
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import PoseWithCovarianceStamped

    from inhand_tools.echo_format import Options, format_message
    diagnostics = DiagnosticArray(status=[DiagnosticStatus(
        level=b'\x01', name='liberty: driver', message="it's ok\n(mostly)",
        values=[KeyValue(key='yes', value='')])])
    assert yaml.safe_load(format_message(diagnostics))['status'] == [{
        'level': 1, 'name': 'liberty: driver', 'message': "it's ok\n(mostly)",
        'hardware_id': '', 'values': [{'key': 'yes', 'value': ''}]}]
    pose = PoseWithCovarianceStamped()
    pose.pose.covariance[:] = np.arange(36) * 0.5
    text = format_message(pose, Options(truncate_length=16))
    assert 'covariance: [0.0, 0.5, 1.0,' in text and ', 7.5, ...]  # 36 items' in text
    full = yaml.safe_load(format_message(pose))
    assert full['pose']['covariance'] == list(np.arange(36) * 0.5)
    assert "covariance: '<array type: double[36]>'" in format_message(pose, Options(no_arr=True))


@pytest.mark.parametrize('path, problem', [
    ('pose..x', 'expected names and [index] separated by dots'),
    ('[0]', 'expected names and [index] separated by dots'),
    ('pose.position[0]', "indexes geometry_msgs/msg/Point, which is not an array"),
    ('header.stamp.sec.x', "int32 has no field 'x'"),
])
def test_echo_field_paths_are_checked_against_the_type(path, problem):
    from inhand_tools.echo_format import FieldPathError, check_field_path, parse_field_path
    with pytest.raises(FieldPathError, match=re.escape(problem)):
        check_field_path(PoseStamped, parse_field_path(path), path)
    from diagnostic_msgs.msg import DiagnosticArray
    assert check_field_path(DiagnosticArray, parse_field_path('status[0].values[-1].key')) == \
        'string'
