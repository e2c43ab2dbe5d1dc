"""Helpers for end-to-end tests: run workspace executables and listen to topics over DDS."""

from __future__ import annotations

import contextlib
import os
import pathlib
import signal
import subprocess
import tempfile
import threading
import time
from collections import defaultdict

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

WORKSPACE = pathlib.Path(__file__).resolve().parents[1]
VENV_BIN = WORKSPACE / '.venv' / 'bin'


def executable_path(name: str) -> str:
    """The workspace executable: in .venv/bin (embedded ROS), else where colcon installed it
    (``<prefix>/lib/<package>/<name>`` on a full ROS 2 install, found via AMENT_PREFIX_PATH)."""
    candidate = VENV_BIN / name
    if candidate.exists():
        return str(candidate)
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        for path in pathlib.Path(prefix or '.').glob(f'lib/*/{name}'):
            return str(path)
    raise FileNotFoundError(f'{name}: not in {VENV_BIN} nor under AMENT_PREFIX_PATH')


class Process:
    """A workspace executable in the background, its output kept in a file."""

    def __init__(self, args: list[str]):
        self.log = tempfile.NamedTemporaryFile('w+', prefix='proc-', suffix='.log', delete=False)
        self.popen = subprocess.Popen([executable_path(args[0]), *args[1:]], stdout=self.log,
                                      stderr=subprocess.STDOUT, env=dict(os.environ),
                                      start_new_session=True)

    def output(self) -> str:
        return pathlib.Path(self.log.name).read_text(errors='replace')

    def alive(self) -> bool:
        return self.popen.poll() is None

    def interrupt(self, timeout: float = 10.0) -> int:
        """Ctrl-C, as a user would; kills the group if it does not end within ``timeout``."""
        if self.alive():
            self.popen.send_signal(signal.SIGINT)
        try:
            return self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.popen.pid, signal.SIGKILL)
            self.popen.wait()
            raise AssertionError(f'{self.popen.args[0]} did not stop on SIGINT:\n{self.output()}')


@contextlib.contextmanager
def running(args: list[str]):
    process = Process(args)
    try:
        yield process
    finally:
        if process.alive():
            with contextlib.suppress(AssertionError):
                process.interrupt()


class TopicListener:
    """Subscribes to the driver's pose topics and diagnostics in a background executor."""

    def __init__(self, names=('thumb', 'index', 'middle', 'object')):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node('test_listener', context=self.context)
        self.lock = threading.Lock()
        self.poses: dict[str, list[PoseStamped]] = defaultdict(list)
        self.diagnostics: list[DiagnosticArray] = []
        qos = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
        for name in names:
            self.node.create_subscription(PoseStamped, f'polhemus/{name}/pose',
                                          lambda msg, name=name: self._add(name, msg), qos)
        self.node.create_subscription(DiagnosticArray, 'diagnostics', self._add_diag, 10)
        self.executor = EventsExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stopping = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        # spin_once in a loop: EventsExecutor.shutdown() from another thread while spin()
        # runs never returns, so the thread stops itself and the executor is shut after.
        while not self._stopping.is_set():
            self.executor.spin_once(timeout_sec=0.05)

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
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return
            time.sleep(0.05)
        raise AssertionError(f'timed out after {timeout} s waiting for {what}')

    def close(self):
        self._stopping.set()
        self.thread.join(5.0)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@contextlib.contextmanager
def listening(**kwargs):
    listener = TopicListener(**kwargs)
    try:
        yield listener
    finally:
        listener.close()
