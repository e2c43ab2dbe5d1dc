"""Start and stop a graph of workspace executables: what ``ros2 launch`` would do here.

The pip runtime has no ``launch``; the launch scripts in ``launch_scripts/`` are Python
files built on this module. A :class:`ProcessGroup` starts each process in a session of
its own, prefixes its output with its name, and on exit (normal end, an exception,
Ctrl-C, SIGTERM, or SIGHUP when the terminal closes) stops them in reverse order of start:
SIGINT first (each node's ``close()`` runs, the driver sends ``P``, the occupancy node
saves), SIGKILL after a grace period. The first signal interrupts the launch script; those
after it only say that it is stopping, so a second Ctrl-C does not cut a save short. No
process outlives the launch script: were it killed with ``kill -9``, the kernel sends each
child SIGTERM (parent_death.py).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from inhand_tools.parent_death import command_with_parent_death

__all__ = ['ProcessGroup', 'TopicWatch', 'add_view_arguments', 'call_trigger', 'driver_command',
           'executable', 'hold_view', 'mapping_graph', 'save_when_drained', 'start_occupancy',
           'start_view']


def executable(name: str) -> str:
    """A workspace executable: beside this Python (the venv), else on PATH, else under
    AMENT_PREFIX_PATH's ``lib/<package>/`` (a colcon install)."""
    beside = Path(sys.executable).parent / name
    if beside.exists():
        return str(beside)
    found = shutil.which(name)
    if found:
        return found
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        for path in Path(prefix or '.').glob(f'lib/*/{name}'):
            return str(path)
    raise FileNotFoundError(f'executable {name!r} not found (bootstrap the workspace first)')


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class ProcessGroup:
    def __init__(self, grace: float = 10.0, stream=sys.stdout):
        self.grace = grace
        self.stream = stream
        self.processes: list[tuple[str, subprocess.Popen]] = []
        self.stopping = False      # a stop signal came, or the group is stopping its processes
        self._lock = threading.Lock()

    def __enter__(self) -> ProcessGroup:
        self._previous = {sig: signal.signal(sig, self._on_signal) for sig in STOP_SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        self.stop_all()
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def _on_signal(self, signum, _frame) -> None:
        if self.stopping:
            self.say(f'[launch] {signal.Signals(signum).name} again: still stopping; each '
                     f'process saves and ends on its own (killed after {self.grace:g} s)')
            return
        self.stopping = True
        raise KeyboardInterrupt(f'signal {signum}')

    def say(self, text: str) -> None:
        """A line on the launch's output; nothing when that output is gone (the terminal
        closed: SIGHUP), so that stopping goes on."""
        with self._lock:
            try:
                self.stream.write(text + '\n')
                self.stream.flush()
            except (OSError, ValueError):
                pass

    def start(self, name: str, args: Sequence[str], env: dict | None = None,
              prefix: Sequence[str] = ()) -> subprocess.Popen:
        """Start ``args`` (first element: an executable name or path) as ``name``, through
        ``prefix`` if given (e.g. ``ip netns exec NAME``). From the main thread: the
        parent-death signal follows the thread that started the child."""
        command = [*prefix, executable(args[0]) if os.sep not in args[0] else args[0],
                   *args[1:]]
        process = subprocess.Popen(command_with_parent_death(command), stdout=subprocess.PIPE,
                                   stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                                   start_new_session=True, text=True, bufsize=1)
        threading.Thread(target=self._pump, args=(name, process), daemon=True).start()
        self.processes.append((name, process))
        return process

    def _pump(self, name: str, process: subprocess.Popen) -> None:
        # Read to the end even when our output is gone: a child blocked on a full pipe
        # would never finish saving.
        for line in process.stdout:
            self.say(f'[{name}] {line.rstrip()}')

    def run(self, name: str, args: Sequence[str], timeout: float | None = None) -> int:
        """Start ``args``, wait for it to end, return its exit code."""
        process = self.start(name, args)
        try:
            return process.wait(timeout)
        finally:
            self.stop(name, process)

    def stop(self, name: str, process: subprocess.Popen) -> int | None:
        if process.poll() is None:
            try:
                os.killpg(process.pid, signal.SIGINT)
            except ProcessLookupError:
                pass
            try:
                process.wait(self.grace)
            except subprocess.TimeoutExpired:
                self.say(f'[launch] {name} did not stop within {self.grace:g} s: killing it')
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
        return process.returncode

    def stop_named(self, *names: str) -> None:
        """Stop the processes started under these names, in this order (the sources of a
        graph first, so that what they sent reaches the map before it is saved)."""
        for wanted in names:
            for name, process in self.processes:
                if name == wanted:
                    self.stop(name, process)

    def stop_all(self) -> None:
        self.stopping = True
        for name, process in reversed(self.processes):
            self.stop(name, process)
        time.sleep(0.05)  # let the output threads print the last lines


SERVICE_SETTLE = 0.5   # s after a service appears before the first request
RESEND_AFTER = 5.0     # s without an answer before the request is sent again


def call_trigger(service: str, timeout: float = 30.0) -> tuple[bool, str]:
    """Call a std_srvs/Trigger service (waiting for it to appear); (success, message).

    A client that calls as soon as the service appears can lose the answer: the server's
    response writer may not have matched the client's reader yet (seen under load: a save
    done, its answer never delivered). So the first request waits SERVICE_SETTLE, and an
    unanswered one is sent again every RESEND_AFTER s until ``timeout``: the services
    called this way (save, reset) give the same result when repeated."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from std_srvs.srv import Trigger

    context = rclpy.Context()
    rclpy.init(context=context)
    node = Node('launch_service_client', context=context)
    try:
        client = node.create_client(Trigger, service)
        if not client.wait_for_service(timeout_sec=timeout):
            return False, f'service {service} did not appear within {timeout:g} s'
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        time.sleep(SERVICE_SETTLE)
        deadline = time.monotonic() + timeout
        futures = [client.call_async(Trigger.Request())]
        resend = time.monotonic() + RESEND_AFTER
        while not any(f.done() for f in futures) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
            if time.monotonic() >= resend:
                futures.append(client.call_async(Trigger.Request()))
                resend += RESEND_AFTER
        future = next((f for f in futures if f.done()), futures[0])
        if not future.done():
            return False, f'service {service} did not answer within {timeout:g} s'
        result = future.result()
        return bool(result.success), result.message
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def mapping_graph(group: ProcessGroup, config: str, output_dir: str, map_name: str,
                  namespace: str | None = None, stereo_config: str | None = None,
                  sim_time: bool = False, autosave: float = 0.0, env: dict | None = None,
                  prefix: Sequence[str] = (), shape: bool = False, exploration: bool = False) -> None:
    """Start ``registration_node`` and ``occupancy_node`` with the parameters of ``config``
    (a file with both nodes' sections), saving maps to ``output_dir/map_name``; with
    ``stereo_config`` (the rig's file, e.g. config/stereo.yaml) also ``stereo_node``, which
    takes its session settings from ``config`` and the rig's from ``stereo_config``.
    ``sim_time``: the nodes run with ``use_sim_time`` (a replay publishes ``/clock``);
    ``autosave``: the occupancy node saves a changed map every so many seconds; ``shape``:
    also ``shape_node`` (the ``shape/extract`` service); ``exploration``: also
    ``exploration_node`` (the predicted surface and next touches, with the ``exploration_node``
    section of ``config``); ``env`` and ``prefix`` as in ProcessGroup.start."""
    ros_args = _ros_arguments(config, namespace, sim_time)
    group.start('registration', ['registration_node', *ros_args], env, prefix)
    start_occupancy(group, config, output_dir, map_name, namespace=namespace,
                    sim_time=sim_time, autosave=autosave, env=env, prefix=prefix)
    if stereo_config:
        group.start('stereo', ['stereo_node', *ros_args, '--params-file', stereo_config],
                    env, prefix)
    if shape:
        group.start('shape', ['shape_node', *ros_args], env, prefix)
    if exploration:
        group.start('exploration', ['exploration_node', *ros_args], env, prefix)


def start_occupancy(group: ProcessGroup, config: str, output_dir: str, map_name: str, *,
                    namespace: str | None = None, sim_time: bool = False,
                    autosave: float = 0.0, initial_map: str | None = None,
                    env: dict | None = None, prefix: Sequence[str] = ()) -> subprocess.Popen:
    """Start ``occupancy_node`` as :func:`mapping_graph` does; ``initial_map``: an NPZ to
    start from (after a crash: its autosave)."""
    args = ['occupancy_node', *_ros_arguments(config, namespace, sim_time),
            '-p', f'output_dir:={output_dir}', '-p', f'map_name:={map_name}',
            '-p', f'autosave_period:={float(autosave)}']
    if initial_map:
        args += ['-p', f'initial_map:={initial_map}']
    return group.start('occupancy', args, env, prefix)


def driver_command(config: str, port: str, *parameters: str) -> list[str]:
    """``liberty_driver``'s command line: its parameter file, the serial port, and more
    ``name:=value`` parameters."""
    args = ['liberty_driver', '--ros-args', '--params-file', config, '-p', f'port:={port}']
    for parameter in parameters:
        args += ['-p', parameter]
    return args


def _ros_arguments(config: str, namespace: str | None, sim_time: bool) -> list[str]:
    ros_args = ['--ros-args', '--params-file', config]
    if sim_time:
        ros_args += ['-p', 'use_sim_time:=true']
    if namespace:
        ros_args += ['-r', f'__ns:={namespace}']
    return ros_args


class TopicWatch:
    """Watches a topic from before a replay starts until the graph has gone quiet.

    ``with TopicWatch('registration/points', PointCloud2) as watch: ...; watch.wait_quiet()``
    The end of a replay is not the end of the work: the graph may still hold a queue of
    messages acknowledged but not yet processed. Subscribing before the replay (so
    discovery is done) and then waiting until nothing has arrived for ``quiet`` seconds
    tells when it is done.
    """

    def __init__(self, topic: str, msg_type):
        self.topic, self.msg_type = topic, msg_type
        self.count = 0
        self.last: float | None = None  # monotonic time of the last message

    def __enter__(self) -> TopicWatch:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

        self._context = rclpy.Context()
        rclpy.init(context=self._context)
        # one node per watched topic: two of one name share their rosout logger and warn
        name = 'launch_watch_' + ''.join(c if c.isalnum() else '_' for c in self.topic)
        self._node = Node(name.strip('_'), context=self._context)
        self._node.create_subscription(
            self.msg_type, self.topic, self._arrived,
            QoSProfile(depth=1000, history=HistoryPolicy.KEEP_ALL,
                       reliability=ReliabilityPolicy.RELIABLE), raw=True)
        self._executor = SingleThreadedExecutor(context=self._context)
        self._executor.add_node(self._node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()
        return self

    def _arrived(self, _raw) -> None:
        self.count += 1
        self.last = time.monotonic()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self._executor.spin_once(timeout_sec=0.05)

    def wait_connected(self, publishers: int = 1, subscribers: int = 2,
                       timeout: float = 30.0, settle: float = 0.5) -> bool:
        """Until the graph shows this many publishers and subscribers of the topic (this
        watch is one of the subscribers), then ``settle`` more seconds for the endpoints
        to match: messages published before a reader matched are not delivered to it."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._node.count_publishers(self.topic) >= publishers and \
                    self._node.count_subscribers(self.topic) >= subscribers:
                time.sleep(settle)
                return True
            time.sleep(0.05)
        return False

    def wait_reader(self, node_name: str, timeout: float = 60.0, settle: float = 0.5) -> bool:
        """Until the node ``node_name`` subscribes to the topic (other readers, such as a
        viewer, do not count), then ``settle`` s for the match: what is published before
        the reader matched is not delivered to it."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(info.node_name == node_name
                   for info in self._node.get_subscriptions_info_by_topic(
                       self._node.resolve_topic_name(self.topic))):
                time.sleep(settle)
                return True
            time.sleep(0.05)
        return False

    def wait_first(self, timeout: float) -> bool:
        """Until a message has arrived (False if none within ``timeout``)."""
        deadline = time.monotonic() + timeout
        while self.count == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        return self.count > 0

    def wait_quiet(self, quiet: float = 1.0, timeout: float = 300.0) -> None:
        """Until nothing has arrived for ``quiet`` seconds (or ``timeout``)."""
        start = time.monotonic()
        while time.monotonic() - start < timeout:
            since = time.monotonic() - (self.last if self.last is not None else start)
            if since >= quiet:
                return
            time.sleep(0.05)

    def __exit__(self, *exc) -> None:
        import rclpy
        self._stop.set()
        self._thread.join(5.0)
        self._node.destroy_node()
        rclpy.try_shutdown(context=self._context)


# -- the live view (inhand_view) -------------------------------------------------------------

def add_view_arguments(parser) -> None:
    """``--view``, ``--http-port``, ``--foxglove-port`` on a launch script's parser."""
    parser.add_argument('--view', action='store_true',
                        help='also start live_view: the page at http://127.0.0.1:HTTP_PORT/ and '
                        'the Foxglove WebSocket server at ws://127.0.0.1:FOXGLOVE_PORT')
    parser.add_argument('--http-port', type=int, default=8080, metavar='PORT',
                        help="with --view: the page's port (default 8080)")
    parser.add_argument('--foxglove-port', type=int, default=8765, metavar='PORT',
                        help="with --view: the Foxglove WebSocket server's port (default 8765)")


def start_view(group: ProcessGroup, args, namespace: str | None = None) -> str | None:
    """Start ``live_view`` when ``args.view`` (see :func:`add_view_arguments`); its page's
    address, or None."""
    if not getattr(args, 'view', False):
        return None
    ros_args = ['--ros-args', '-p', f'http_port:={args.http_port}',
                '-p', f'foxglove_port:={args.foxglove_port}']
    if namespace:
        ros_args += ['-r', f'__ns:={namespace}']
    group.start('view', ['live_view', *ros_args])
    return f'http://127.0.0.1:{args.http_port}/'


def save_when_drained(group: ProcessGroup, watch: TopicWatch, quiet: float,
                      sources: Sequence[str] = (), timeout: float = 30.0) -> tuple[bool, str]:
    """Stop the graph's ``sources`` (in this order), wait until ``watch`` has been quiet for
    ``quiet`` s (what they sent has reached the map), then call ``occupancy/save`` and say
    its answer (``timeout``: see call_trigger); (success, message). From here on a signal
    only says that we are stopping."""
    group.stopping = True
    group.stop_named(*sources)
    watch.wait_quiet(quiet)
    ok, message = call_trigger('occupancy/save', timeout=timeout)
    group.say(f'[launch] occupancy/save: {message}')
    return ok, message


def hold_view(group: ProcessGroup, url: str) -> None:
    """Keep the graph and the view up until Ctrl-C (or the view ends)."""
    print(f'[launch] live view at {url} (Foxglove: see its page); Ctrl-C to stop', flush=True)
    view = [process for name, process in group.processes if name == 'view']
    try:
        while all(process.poll() is None for process in view):
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
