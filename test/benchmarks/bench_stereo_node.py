#!/usr/bin/env python3
"""The stereo node at camera rate, over DDS: images in, disparity out.

    .venv/bin/python test/benchmarks/bench_stereo_node.py [--seconds S] [--rate HZ]
                                                          [--latency-pairs N] [--quick]

The pair is the bundled ``cat_static`` bag's first stereo pair (640x480 rgb8, the rig's
camera_infos), published again and again with fresh stamps by this process as a camera
driver or a bag replay would: raw CDR, the stamps written into the headers.

1. *Transport.* The left image alone, best effort depth 5 (the sensor-data QoS camera
   drivers use) at ``--rate`` for ``--seconds``, to a best-effort reader in another
   process: how many arrive, each side with Fast DDS's defaults or with the graph's
   profile (``inhand_common/dds_profile.py``: every program of the graph runs with it; a
   camera driver must too, as only the publisher's shared-memory segment counts).
2. *Latency.* ``stereo_node`` with the shipped ``config/stereo.yaml`` (static mode, so each
   pair also goes through the vision map and the texture), one pair at a time: from
   publishing the right image to receiving its ``stereo/disparity`` here; beside it the
   bare OpenCV matcher (the very object the node calls, same settings) on the same pair,
   rectified, in this process. Target: the node within 1.5x bare OpenCV (medians).
3. *Sustained.* Pairs at ``--rate`` for ``--seconds`` from a reliable publisher (a bag
   replay) and from a best-effort one (depth 5, a camera driver): every pair sent is
   processed or counted as skipped in the node's ``diagnostics`` (the newest pair is
   taken when the node is busy), none lost without a count: sent == processed + skipped
   (+ refused + unpaired halves), and the disparities received.

Printed PASS/FAIL per target; the exit status is 0 unless a check of the setup fails.
"""

from __future__ import annotations

import argparse
import os
import statistics
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

WORKSPACE = Path(__file__).resolve().parents[2]
BAG = WORKSPACE / 'bags' / 'cat_static'
TOPICS = ('stereo/left/image_raw', 'stereo/right/image_raw', 'stereo/left/camera_info',
          'stereo/right/camera_info')
CHILD_ENV = 'BENCH_STEREO_NODE_CHILD'


def say(text: str) -> None:
    print(text, flush=True)


def verdict(ok: bool) -> str:
    return 'PASS' if ok else 'FAIL'


# ---------------------------------------------------------------------------- the pair
def first_pair() -> dict[str, bytes]:
    """The raw CDR of the bag's first left and right image and camera_infos."""
    from inhand_common.bag_source import BagSource
    found: dict[str, bytes] = {}
    with BagSource(BAG) as source:
        for topic, _, raw in source.messages(set(TOPICS)):
            found.setdefault(topic, raw)
            if len(found) == len(TOPICS):
                break
    if len(found) != len(TOPICS):
        raise SystemExit(f'bench_stereo_node: {BAG} lacks {set(TOPICS) - set(found)}')
    return found


def stamped(raw: bytes, stamp_ns: int) -> bytes:
    """A message's CDR with its header stamp set (the stamp follows the 4-byte
    encapsulation header: sec int32, nanosec uint32, little-endian as the bag's are)."""
    if raw[1] != 1:
        raise SystemExit('bench_stereo_node: expected little-endian CDR in the bag')
    return raw[:4] + struct.pack('<iI', stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000) \
        + raw[12:]


# ---------------------------------------------------------------------------- part 1
def defaults_profile() -> Path:
    """A profiles file that leaves Fast DDS at its defaults (named, it keeps a process from
    taking the graph's profile)."""
    path = Path(f'/tmp/bench_stereo_node_defaults_{os.getpid()}.xml')
    path.write_text('<?xml version="1.0" encoding="UTF-8" ?>\n<profiles xmlns='
                    '"http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">\n'
                    '  <participant profile_name="defaults" is_default_profile="true">'
                    '<rtps/></participant>\n</profiles>\n')
    return path


def child_reader(seconds: float) -> int:
    """The best-effort reader of part 1 (another process): counts the images it gets."""
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image

    from inhand_common.dds_profile import shipped_profile
    with shipped_profile():   # the graph's, unless a defaults file is named
        return _count_images(rclpy, Image, qos_profile_sensor_data, seconds)


def _count_images(rclpy, Image, qos, seconds: float) -> int:
    rclpy.init()
    node = rclpy.create_node('bench_reader')
    got = [0]
    node.create_subscription(Image, TOPICS[0], lambda _raw: got.__setitem__(0, got[0] + 1),
                             qos, raw=True)
    print('ready', flush=True)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.1)
    print('received', got[0], flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def transport(pair: dict[str, bytes], rate: float, seconds: float, writer_profile: bool,
              reader_profile: bool) -> int:
    """Part 1 in a fresh pair of processes (a profile is read when a process starts), each
    with the graph's profile or Fast DDS's defaults: the number of images received."""
    env = dict(os.environ, **{CHILD_ENV: '1'})
    env.pop('FASTRTPS_DEFAULT_PROFILES_FILE', None)
    env.pop('FASTDDS_DEFAULT_PROFILES_FILE', None)
    defaults = dict(env, FASTRTPS_DEFAULT_PROFILES_FILE=str(defaults_profile()))
    reader = subprocess.Popen([sys.executable, __file__, '--child-reader', str(seconds + 6)],
                              env=env if reader_profile else defaults, stdout=subprocess.PIPE,
                              text=True)
    writer = subprocess.Popen([sys.executable, __file__, '--child-writer', str(seconds),
                               str(rate)], env=env if writer_profile else defaults,
                              stdin=subprocess.PIPE, text=True)
    assert writer.stdin is not None and reader.stdout is not None
    writer.stdin.write(pair[TOPICS[0]].hex())
    writer.stdin.close()
    reader.stdout.readline()
    writer.wait(timeout=seconds + 60)
    out = reader.communicate(timeout=seconds + 60)[0]
    return int(out.split()[-1])


def child_writer(seconds: float, rate: float) -> int:
    """The best-effort writer of part 1, with the graph's profile unless a defaults file is
    named: the image on standard input (hex)."""
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image

    from inhand_common.dds_profile import shipped_profile
    raw = bytes.fromhex(sys.stdin.read())
    with shipped_profile():
        rclpy.init()
        node = rclpy.create_node('bench_writer')
        publisher = node.create_publisher(Image, TOPICS[0], qos_profile_sensor_data)
        time.sleep(2.0)                                   # discovery
        count = int(seconds * rate)
        start = time.monotonic()
        for k in range(count):
            publisher.publish(stamped(raw, time.time_ns()))
            delay = start + (k + 1) / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        time.sleep(1.0)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


# ---------------------------------------------------------------------------- parts 2, 3
class Graph:
    """``stereo_node`` running, and this process as camera and listener."""

    def __init__(self, pair: dict[str, bytes]):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, Image
        from stereo_msgs.msg import DisparityImage

        from inhand_common.dds_profile import shipped_profile
        from inhand_mapping.qos import LATCHED_QOS
        self.pair = pair
        self._profile = shipped_profile()
        self._profile.__enter__()
        rclpy.init()
        self.rclpy = rclpy
        self.node = rclpy.create_node('bench_stereo_camera')
        self.log = open(f'/tmp/bench_stereo_node_{os.getpid()}.log', 'w')
        self.process = subprocess.Popen(
            [str(WORKSPACE / '.venv' / 'bin' / 'stereo_node'), '--ros-args', '--params-file',
             str(WORKSPACE / 'config' / 'stereo.yaml'), '-p', 'mode:=static'],
            stdout=self.log, stderr=subprocess.STDOUT)
        reliable = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
        self.publishers = {
            qos_name: {topic: self.node.create_publisher(CameraInfo if 'info' in topic else Image,
                                                         topic, qos)
                       for topic in TOPICS}
            for qos_name, qos in (('reliable', reliable), ('best effort', qos_profile_sensor_data))}
        self.lock = threading.Lock()
        self.disparities: dict[int, float] = {}      # stamp -> arrival (monotonic)
        self.node.create_subscription(DisparityImage, 'stereo/disparity', self._on_disparity,
                                      LATCHED_QOS, raw=True)
        self.status: dict[str, str] = {}
        self.node.create_subscription(DiagnosticArray, 'diagnostics', self._on_diagnostics, 10)
        self._spinning = True
        self._spinner = threading.Thread(target=self._spin, daemon=True)
        self._spinner.start()

    def _spin(self) -> None:
        from rclpy.executors import SingleThreadedExecutor
        executor = SingleThreadedExecutor()
        executor.add_node(self.node)
        while self._spinning:
            executor.spin_once(timeout_sec=0.05)

    def _on_disparity(self, raw: bytes) -> None:
        arrived = time.monotonic()
        sec, nanosec = struct.unpack_from('<iI', raw, 4)
        with self.lock:
            self.disparities[sec * 1_000_000_000 + nanosec] = arrived

    def _on_diagnostics(self, msg) -> None:
        for status in msg.status:
            if 'stereo_node' in status.name:
                with self.lock:
                    self.status = {value.key: value.value for value in status.values}
                    self.status['message'] = status.message

    def wait_ready(self, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise SystemExit(f'stereo_node exited ({self.process.returncode}); see '
                                 f'{self.log.name}')
            with self.lock:
                if self.status:
                    return
            time.sleep(0.2)
        raise SystemExit(f'stereo_node gave no diagnostics within {timeout} s; see {self.log.name}')

    def send(self, qos_name: str, stamp_ns: int) -> float:
        """One pair (camera_infos, then left, then right); the time the right image went."""
        publishers = self.publishers[qos_name]
        for topic in (TOPICS[2], TOPICS[3], TOPICS[0]):
            publishers[topic].publish(stamped(self.pair[topic], stamp_ns))
        sent = time.monotonic()
        publishers[TOPICS[1]].publish(stamped(self.pair[TOPICS[1]], stamp_ns))
        return sent

    def disparity_of(self, stamp_ns: int, timeout: float) -> float | None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                if stamp_ns in self.disparities:
                    return self.disparities[stamp_ns]
            time.sleep(0.001)
        return None

    def counters(self) -> dict[str, int]:
        with self.lock:
            return {key: int(value) for key, value in self.status.items()
                    if key.startswith('pairs ') and value.isdigit()}

    def close(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.process.kill()
        self._spinning = False
        self._spinner.join(timeout=5)
        self.node.destroy_node()
        self.rclpy.try_shutdown()
        self._profile.__exit__(None, None, None)
        self.log.close()


def bare_opencv_ms(pair: dict[str, bytes], runs: int) -> float:
    """The node's OpenCV matcher (same object, same settings: the node's parameters from
    config/stereo.yaml) on the pair rectified and grey, in this process (median)."""
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import CameraInfo, Image

    from inhand_stereo.image_encoding import image_to_array
    from inhand_stereo.stereo_config import load_stereo_config
    from inhand_stereo.stereo_inputs import camera_model_of
    from inhand_stereo.stereo_pipeline import StereoPipeline
    config = load_stereo_config([str(WORKSPACE / 'config' / 'stereo.yaml')])
    images = [deserialize_message(pair[topic], Image) for topic in TOPICS[:2]]
    infos = [deserialize_message(pair[topic], CameraInfo) for topic in TOPICS[2:]]
    arrays = [image_to_array(m.encoding, m.height, m.width, m.step, bytes(m.data),
                             bool(m.is_bigendian)) for m in images]
    pipeline = StereoPipeline(config.disparity, point_step=config.point_step)
    shot = pipeline.process(0, arrays[0], arrays[1], images[0].encoding,
                            camera_model_of(infos[0], 'left'), camera_model_of(infos[1], 'right'))
    frame = shot.rectifier.rectify_frame(arrays[0], arrays[1], images[0].encoding)
    bare = pipeline.matcher.opencv_matcher            # the very OpenCV object the node calls
    times = []
    for _ in range(runs + 1):
        started = time.perf_counter()
        bare.compute(frame.left_grey, frame.right_grey)
        times.append(time.perf_counter() - started)
    return statistics.median(times[1:]) * 1e3


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seconds', type=float, default=60.0)
    parser.add_argument('--rate', type=float, default=15.0)
    parser.add_argument('--latency-pairs', type=int, default=30)
    parser.add_argument('--quick', action='store_true', help='10 s, 10 latency pairs')
    parser.add_argument('--child-reader', type=float, help=argparse.SUPPRESS)
    parser.add_argument('--child-writer', type=float, nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child_reader is not None:
        return child_reader(args.child_reader)
    if args.child_writer is not None:
        return child_writer(*args.child_writer)
    if args.quick:
        args.seconds, args.latency_pairs = 10.0, 10
    say(f'### benchmark: stereo node over DDS ({time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}'
        f', {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f})')
    pair = first_pair()
    size = len(pair[TOPICS[0]])
    sent = int(args.seconds * args.rate)
    say(f'== Part 1: transport, one 640x480 rgb8 image ({size:,} B of CDR) best effort at '
        f'{args.rate:g} Hz for {args.seconds:g} s to a best-effort reader in another process')
    results = {}
    for writer_profile, reader_profile, label in (
            (False, False, 'Fast DDS defaults on both sides'),
            (False, True, 'the graph profile on the reader only'),
            (True, False, 'the graph profile on the publisher only'),
            (True, True, 'the graph profile on both (the graph)')):
        got = results[writer_profile, reader_profile] = transport(
            pair, args.rate, args.seconds, writer_profile, reader_profile)
        say(f'  {label:42s} {got:5d} of {sent} received')
    transport_ok = results[True, True] == sent
    say(f'  every image arrives with the graph profile: {verdict(transport_ok)}')

    say('== Part 2: latency, publish -> stereo/disparity, one pair at a time (static mode: '
        'the vision map and the texture run too)')
    graph = Graph(pair)
    try:
        graph.wait_ready()
        latencies = []
        base = time.time_ns()
        for k in range(args.latency_pairs + 2):
            stamp = base + k * 100_000_000
            sent_at = graph.send('reliable', stamp)
            arrived = graph.disparity_of(stamp, 10.0)
            if arrived is None:
                raise SystemExit(f'no disparity for pair {k} within 10 s; see {graph.log.name}')
            if k >= 2:                              # the first pairs warm the node
                latencies.append((arrived - sent_at) * 1e3)
            time.sleep(0.5)                         # the node's work after the disparity
        bare = bare_opencv_ms(pair, args.latency_pairs)
        node_median = statistics.median(latencies)
        latency_ok = node_median <= 1.5 * bare
        say(f'  stereo_node: {node_median:6.1f} ms median, {min(latencies):6.1f} best '
            f'({len(latencies)} pairs)')
        say(f'  bare OpenCV matcher on the rectified pair (same settings, this process): '
            f'{bare:6.1f} ms median')
        say(f'  node / bare: {node_median / bare:.2f} (target <= 1.5): {verdict(latency_ok)}')

        say(f'== Part 3: sustained, {args.rate:g} pairs/s for {args.seconds:g} s')
        sustained_ok = True
        for qos_name in ('reliable', 'best effort'):
            before = graph.counters()
            base = time.time_ns()
            stamps = [base + round(k * 1e9 / args.rate) for k in range(sent)]
            start = time.monotonic()
            for k, stamp in enumerate(stamps):
                graph.send(qos_name, stamp)
                delay = start + (k + 1) / args.rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            graph.disparity_of(stamps[-1], 5.0)
            time.sleep(2.5)                          # the diagnostics' next period
            after = graph.counters()
            delta = {key: after.get(key, 0) - before.get(key, 0) for key in after}
            received = sum(1 for stamp in stamps if stamp in graph.disparities)
            counted = sum(delta.get(key, 0) for key in ('pairs processed', 'pairs skipped',
                                                        'pairs refused'))
            ok = counted == sent and delta.get('pairs received', -1) == sent
            sustained_ok &= ok
            say(f'  {qos_name:12s} sent {sent}, node: ' + ', '.join(
                f'{key[6:]} {value}' for key, value in sorted(delta.items())) +
                f'; disparities received {received}; every pair processed or counted: '
                f'{verdict(ok)}')
    finally:
        graph.close()
    say(f'== Summary: transport {verdict(transport_ok)}, latency {verdict(latency_ok)}, '
        f'sustained {verdict(sustained_ok)}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
