"""Helpers for end-to-end tests: run workspace executables and listen to topics over DDS."""

from __future__ import annotations

import atexit
import contextlib
import os
import pathlib
import re
import signal
import subprocess
import tempfile
import threading
import time
from collections import defaultdict
from types import SimpleNamespace

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.duration import Duration
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from inhand_tools.launching import call_trigger as launching_call_trigger
from inhand_tools.launching import executable
from polling import wait_until

WORKSPACE = pathlib.Path(__file__).resolve().parents[1]


executable_path = executable


def _remove_file(path: str) -> None:
    with contextlib.suppress(OSError):
        os.unlink(path)


class Process:
    """A workspace executable in the background, its output kept in a file (removed when
    the test process ends; a test may read a process's output after it stopped)."""

    def __init__(self, args: list[str]):
        self.log = tempfile.NamedTemporaryFile('w+', prefix='proc-', suffix='.log', delete=False)
        atexit.register(_remove_file, self.log.name)
        self.popen = subprocess.Popen([executable_path(args[0]), *args[1:]], stdout=self.log,
                                      stderr=subprocess.STDOUT, env=dict(os.environ),
                                      start_new_session=True)

    def output(self) -> str:
        return pathlib.Path(self.log.name).read_text(errors='replace')

    def alive(self) -> bool:
        return self.popen.poll() is None

    def wait_for_matches(self, topics, other_end: str = 'publisher',
                         timeout: float = 30.0) -> None:
        """Wait until the node logged a match on each topic (``topic: N publisher(s)``,
        inhand_common.ros_matches): its reader then takes whatever is published next."""
        patterns = {topic: re.compile(rf'\]: {re.escape(topic)}: [1-9][0-9]* {other_end}\(s\)')
                    for topic in topics}
        deadline = time.monotonic() + timeout
        while True:
            output = self.output()
            missing = [t for t, pattern in patterns.items() if not pattern.search(output)]
            if not missing:
                return
            assert time.monotonic() < deadline, \
                f'{self.popen.args[0]} matched no {other_end} on {missing}:\n{output}'
            assert self.alive(), f'{self.popen.args[0]} ended:\n{output}'
            time.sleep(0.05)

    def interrupt(self, timeout: float = 10.0) -> int:
        """Ctrl-C, as a user would; kills the group if it does not end within ``timeout``."""
        if self.alive():
            self.popen.send_signal(signal.SIGINT)
        try:
            return self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.popen.pid, signal.SIGKILL)
            self.popen.wait()
            raise AssertionError(
                f'{self.popen.args[0]} did not stop on SIGINT:\n{self.output()}') from None


@contextlib.contextmanager
def running(args: list[str]):
    process = Process(args)
    try:
        yield process
    finally:
        if process.alive():
            with contextlib.suppress(AssertionError):
                process.interrupt()


class BackgroundNode:
    """A node of the test process in a context of its own, spun by a background thread."""

    def __init__(self, name: str):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node(name, context=self.context)
        self.lock = threading.Lock()
        self.executor = EventsExecutor(context=self.context)
        self._stopping = threading.Event()
        self.thread = None

    def start(self) -> None:
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        # spin_once in a loop: EventsExecutor.shutdown() from another thread while spin()
        # runs never returns, so the thread stops itself and the executor is shut after.
        while not self._stopping.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    def close(self):
        self._stopping.set()
        if self.thread is not None:
            self.thread.join(5.0)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


class TopicListener(BackgroundNode):
    """Subscribes to the driver's pose topics and diagnostics in a background executor."""

    def __init__(self, names=('thumb', 'index', 'middle', 'object')):
        super().__init__('test_listener')
        self.poses: dict[str, list[PoseStamped]] = defaultdict(list)
        self.diagnostics: list[DiagnosticArray] = []
        qos = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
        for name in names:
            self.node.create_subscription(PoseStamped, f'polhemus/{name}/pose',
                                          lambda msg, name=name: self._add(name, msg), qos)
        self.node.create_subscription(DiagnosticArray, 'diagnostics', self._add_diag, 10)
        self.start()

    def _add(self, name, msg):
        with self.lock:
            self.poses[name].append(msg)

    def _add_diag(self, msg):
        with self.lock:
            self.diagnostics.append(msg)

    def count(self, name: str) -> int:
        with self.lock:
            return len(self.poses[name])

    def snapshot(self) -> dict[str, list[PoseStamped]]:
        with self.lock:
            return {name: list(msgs) for name, msgs in self.poses.items()}

    def diagnostic_values(self) -> dict[str, str]:
        with self.lock:
            if not self.diagnostics:
                return {}
            status = self.diagnostics[-1].status[0]
        return {kv.key: kv.value for kv in status.values} | {'_message': status.message,
                                                               '_level': status.level[0]}

    def wait_for(self, predicate, timeout: float, what: str = 'condition') -> None:
        wait_until(predicate, timeout, what)


@contextlib.contextmanager
def listening(**kwargs):
    listener = TopicListener(**kwargs)
    try:
        yield listener
    finally:
        listener.close()


class PosePublisher:
    """Publishes tracker frames on polhemus/<name>/pose as the driver does (one stamp each)."""

    def __init__(self, names, namespace: str = ''):
        from inhand_mapping.pose_cdr import encode_pose_stamped  # noqa: F401 (import check)
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node('test_pose_publisher', namespace=namespace, context=self.context)
        qos = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
        self.publishers = {name: self.node.create_publisher(PoseStamped, f'polhemus/{name}/pose',
                                                            qos) for name in names}

    def wait_for_subscribers(self, timeout: float = 20.0, reader: Process | None = None) -> None:
        """Wait until our writers see a reader on every topic, and with ``reader`` (a
        registration node) until that node's readers logged our writers too."""
        deadline = time.monotonic() + timeout
        while not all(p.get_subscription_count() > 0 for p in self.publishers.values()):
            if time.monotonic() > deadline:
                raise AssertionError('no subscriber for the pose topics')
            time.sleep(0.05)
        # Our writers see the readers; the readers may not see our writers yet, and a
        # volatile reader that matches late drops what came before the match: a lost first
        # object pose drops every fingertip before it (a CI run lost 84 of 720 points so,
        # and a loaded one 38 of 2,880 half a second after our writers matched).
        if reader is not None:
            reader.wait_for_matches([f'polhemus/{name}/pose' for name in self.publishers],
                                    timeout=max(deadline - time.monotonic(), 1.0))
        else:   # a reader that does not log its matches: let discovery settle both ways
            time.sleep(0.5)

    def publish(self, frames, rate_factor: float = 2.0, frame_rate: float = 240.0) -> None:
        from inhand_common.ros_time import stamp_from_seconds
        start = time.monotonic()
        for k, (t, frame) in enumerate(frames):
            stamp = stamp_from_seconds(t)
            for name, (p, q) in frame.items():
                msg = PoseStamped()
                msg.header.stamp = stamp
                msg.header.frame_id = 'polhemus_source'
                msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = map(float, p)
                (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
                 msg.pose.orientation.w) = map(float, q)
                self.publishers[name].publish(msg)
            ahead = k / (frame_rate * rate_factor) - (time.monotonic() - start)
            if ahead > 0:
                time.sleep(ahead)
        # Everything in the readers' hands before the caller closes us: a writer destroyed
        # with samples unacknowledged takes them along (a loaded run lost 1,184 of 2,880).
        for name, publisher in self.publishers.items():
            assert publisher.wait_for_all_acked(Duration(seconds=30)), \
                f'polhemus/{name}/pose: the readers did not take every pose within 30 s'

    def close(self):
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def call_trigger(service: str, timeout: float = 20.0):
    """Call a std_srvs/Trigger service once; returns (success, message) as a response
    (a service that never answers comes back unsuccessful, with the reason)."""
    success, message = launching_call_trigger(service, timeout)
    return SimpleNamespace(success=success, message=message)


class CloudCounter(BackgroundNode):
    """Counts the points arriving on a PointCloud2 topic (in a background executor)."""

    def __init__(self, topic: str):
        from sensor_msgs.msg import PointCloud2
        super().__init__('test_cloud_counter')
        self.points = 0
        self.node.create_subscription(
            PointCloud2, topic, self._add,
            QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        self.start()

    def _add(self, msg):
        self.points += msg.width * msg.height

    def wait_ready(self, topic: str, timeout: float = 20.0) -> None:
        """Until a publisher of ``topic`` is matched, so no early message is missed."""
        deadline = time.monotonic() + timeout
        while self.node.count_publishers(topic) == 0:
            assert time.monotonic() < deadline, f'no publisher on {topic}'
            time.sleep(0.05)
        time.sleep(0.3)  # discovery: let the reliable reader/writer match settle

    def wait_for(self, count: int, timeout: float = 20.0) -> None:
        deadline = time.monotonic() + timeout
        while self.points < count and time.monotonic() < deadline:
            time.sleep(0.05)
        assert self.points >= count, f'{self.points} of {count} points arrived'


class MapWatcher(BackgroundNode):
    """Keeps the latest ``occupancy/cloud`` (latched) and tells how many hits it holds."""

    def __init__(self):
        from sensor_msgs.msg import PointCloud2
        super().__init__('test_map_watcher')
        self.latest = None
        self.node.create_subscription(
            PointCloud2, 'occupancy/cloud', self._keep,
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.start()

    def _keep(self, msg):
        self.latest = msg

    def hits(self) -> int:
        from inhand_common.point_cloud import from_point_cloud2
        msg = self.latest
        return 0 if msg is None else int(from_point_cloud2(msg)['hits'].sum())

    def wait_for_hits(self, count: int, timeout: float = 20.0) -> None:
        deadline = time.monotonic() + timeout
        while self.hits() < count and time.monotonic() < deadline:
            time.sleep(0.05)
        assert self.hits() >= count, f'the map holds {self.hits()} of {count} hits'
