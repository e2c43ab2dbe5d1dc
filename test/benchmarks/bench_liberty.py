#!/usr/bin/env python3
"""Polhemus Liberty benchmarks: codec parse rate and end-to-end driver throughput.

Run from the workspace root with the workspace's environment (or through
``bash launch_scripts/benchmark.sh``)::

    .venv/bin/python test/benchmarks/bench_liberty.py [--seconds 20] [--quick] [--codec-only]

Part (a), codec: a real byte stream is captured from the emulated Liberty on a pty
(set-up F1/F0, U1, O*,8,9,2,7,1, R4, C, about 2 s of continuous output read with
pyserial), checked against what the emulator says it sent, looped to at least 200,000
records, and fed to BinaryStreamParser / AsciiStreamParser in 4096-byte chunks. Prints
records/s and MB/s and whether every captured record came back.

Part (b), driver end to end: the emulator streams 4 stations at 240 Hz on a pty under
/tmp, ``.venv/bin/liberty_driver`` runs as a subprocess in a DDS domain of its own
(loopback discovery only), and this process subscribes to polhemus/<name>/pose with
reliable QoS (depth 1000) on an EventsExecutor (raw subscriptions: counting needs no
deserialization). The emulator is held paused until the driver streams and its publishers
are matched, so every frame sent is owed to the subscriber. Frames the emulator sent are
compared with the poses received per station and with the driver's 'dropped_frames'
diagnostic. Then a stress step repeats the run with the emulator faster than a real Liberty
(rate_override) and reports the highest rate with nothing dropped or lost.

Exit status: 0 when the 240 Hz run dropped and lost nothing (and the codec lost no
record), 1 otherwise.
"""

from __future__ import annotations

import argparse
import math
import os
import random
import secrets
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import serial

from inhand_common.ros_names import station_pose_topic
from polhemus_liberty.emulator import LibertyEmulator
from polhemus_liberty.motion import BuiltinMotion
from polhemus_liberty.protocol import (
    DEFAULT_OUTPUT_ITEMS,
    AsciiStreamParser,
    BinaryStreamParser,
    OutputList,
    StationRecord,
    cmd_output_list,
)

WORKSPACE = Path(__file__).resolve().parents[2]
DRIVER_EXE = WORKSPACE / '.venv' / 'bin' / 'liberty_driver'
STATIONS = (1, 2, 3, 4)
STATION_NAMES = ('thumb', 'index', 'middle', 'object')
DEVICE_RATE = 240
CHUNK = 4096
STRESS_RATES = (480, 960, 1920)


def say(text: str = '') -> None:
    print(text, flush=True)


def unique_link(tag: str) -> str:
    return f'/tmp/bench_liberty_{os.getpid()}_{secrets.token_hex(3)}_{tag}'


# ============================================================================ (a) codec

def capture_stream(binary: bool, seconds: float) -> tuple[bytes, int]:
    """Bytes of ``seconds`` of continuous output from the emulator, and the records sent.

    The record count comes from the emulator's own frame counter (frames sent x stations),
    not from the parser under test.
    """
    emulator = LibertyEmulator(BuiltinMotion(STATIONS), unique_link('codec'))
    emulator.start()
    try:
        with serial.Serial(emulator.port, 921600, timeout=0.05) as port:
            for command in (b'F1\r' if binary else b'F0\r', b'U1\r',
                            cmd_output_list(DEFAULT_OUTPUT_ITEMS), b'R4\r', b'C\r'):
                port.write(command)
            data = bytearray()
            deadline = time.monotonic() + seconds
            while time.monotonic() < deadline:
                data += port.read(max(port.in_waiting, 1))
            port.write(b'P')  # ends continuous output; then drain what is in flight
            quiet_since = time.monotonic()
            while time.monotonic() - quiet_since < 0.3:
                chunk = port.read(max(port.in_waiting, 1))
                if chunk:
                    data += chunk
                    quiet_since = time.monotonic()
        stats = emulator.stats
        if stats.frames_lost_buffer_full or stats.frames_skipped:
            raise RuntimeError(f'emulator lost frames during capture: {stats}')
        # P answers with one single-shot frame (command 'P') after the continuous ones: cut
        # it off so the capture is the continuous stream alone.
        layout = OutputList(DEFAULT_OUTPUT_ITEMS)
        tail = len(STATIONS) * (layout.record_size if binary else layout.ascii_line_size)
        single_shot = bytes(data[-tail:])
        marks = ([single_shot[i + 3] for i in range(0, tail, layout.record_size)] if binary
                 else [line[2] for line in single_shot.split(b'\r\n')[:-1]])
        if marks != [ord('P')] * len(STATIONS):
            raise RuntimeError('the capture does not end with the single-shot answer to P')
        return bytes(data[:-tail]), stats.frames_sent * len(STATIONS)
    finally:
        emulator.stop()


def check_capture(data: bytes, records_sent: int, layout: OutputList, binary: bool) -> None:
    """The capture holds exactly the records sent, station order 1..4, consecutive counts."""
    if binary:
        if len(data) != records_sent * layout.record_size:
            raise RuntimeError(f'binary capture is {len(data)} bytes, expected '
                               f'{records_sent} x {layout.record_size}')
    else:
        lines = data.count(b'\r\n')
        if lines != records_sent or len(data) != records_sent * layout.ascii_line_size:
            raise RuntimeError(f'ASCII capture has {lines} lines / {len(data)} bytes, expected '
                               f'{records_sent} lines of {layout.ascii_line_size} bytes')
    parser = (BinaryStreamParser if binary else AsciiStreamParser)(layout)
    records = [r for r in parser.feed(data) if isinstance(r, StationRecord)]
    stations = [r.station for r in records]
    if stations != list(STATIONS) * (len(records) // len(STATIONS)):
        raise RuntimeError('captured records are not in station order 1, 2, 3, 4')
    counts = [r.frame_count for r in records[::len(STATIONS)]]
    if counts != list(range(counts[0], counts[0] + len(counts))):
        raise RuntimeError('captured frame counts are not consecutive')


def time_parser(binary: bool, layout: OutputList, chunks: list[bytes], passes: int):
    """Best-of-``passes`` seconds to feed all chunks, with the records and stats of a pass."""
    cls = BinaryStreamParser if binary else AsciiStreamParser
    times = []
    for _ in range(passes):
        parser = cls(layout)
        feed = parser.feed
        parsed = 0
        start = time.perf_counter()
        for chunk in chunks:
            parsed += len(feed(chunk))
        times.append(time.perf_counter() - start)
    return min(times), statistics.median(times), parsed, parser.stats, parser.pending


def bench_codec(quick: bool) -> bool:
    capture_seconds = 0.5 if quick else 2.0
    min_records = 20_000 if quick else 200_000
    passes = 1 if quick else 3
    layout = OutputList(DEFAULT_OUTPUT_ITEMS)
    say(f'== codec: parse rate on a captured stream (output list {list(layout.codes)}, '
        f'{len(STATIONS)} stations, {CHUNK}-byte chunks)')
    ok = True
    for binary, name in ((True, 'binary F1'), (False, 'ASCII F0')):
        say(f'  capturing {capture_seconds:g} s of {name} output from the emulator on a pty ...')
        data, sent = capture_stream(binary, capture_seconds)
        check_capture(data, sent, layout, binary)
        copies = math.ceil(min_records / sent)
        stream = data * copies
        expected = sent * copies
        chunks = [stream[i:i + CHUNK] for i in range(0, len(stream), CHUNK)]
        say(f'  captured {sent} records ({len(data)} bytes, '
            f'{len(data) // sent} B/record); looped x{copies} -> {expected} records, '
            f'{len(stream) / 1e6:.2f} MB; timing {passes} pass(es) ...')
        best, median, parsed, stats, pending = time_parser(binary, layout, chunks, passes)
        lossless = (parsed == expected and stats.records == expected and
                    stats.bytes_dropped == 0 and stats.bad_lines == 0 and pending == 0)
        ok &= lossless
        say(f'  {name}: {expected / best:,.0f} records/s, {len(stream) / best / 1e6:.2f} MB/s '
            f'(best of {passes}; median {expected / median:,.0f} records/s)')
        say(f'  {name}: parsed {parsed} of {expected} records, bytes dropped '
            f'{stats.bytes_dropped}, resyncs {stats.resyncs}, bad lines {stats.bad_lines}: '
            f'{"no records lost" if lossless else "RECORDS LOST"}')
    return ok


# ============================================================================ (b) driver

def udp_ports_in_use() -> set[int]:
    ports = set()
    for table in ('/proc/net/udp', '/proc/net/udp6'):
        try:
            with open(table) as handle:
                next(handle)
                for line in handle:
                    ports.add(int(line.split()[1].rsplit(':', 1)[1], 16))
        except (OSError, StopIteration, ValueError, IndexError):
            pass
    return ports


def free_domain_id() -> int:
    """A random ROS domain in 100..200 whose DDS port block nobody on this machine uses.

    Fast DDS takes UDP ports 7400 + 250 x domain + (0..249) for a domain's participants.
    """
    candidates = list(range(100, 201))
    random.shuffle(candidates)
    used = udp_ports_in_use()
    for domain in candidates:
        base = 7400 + 250 * domain
        if not any(base <= port < base + 250 for port in used):
            return domain
    raise RuntimeError('no free ROS domain id in 100..200')


@dataclass
class RunResult:
    rate: float
    seconds: float
    sent: int
    received: dict[str, int]
    lost_buffer_full: int
    dropped_diag: int | None
    diag: dict = field(default_factory=dict)
    driver_cpu: float | None = None   # driver process CPU seconds per wall second
    bench_cpu: float | None = None    # this process (emulator + subscriber) likewise

    @property
    def achieved_rate(self) -> float:
        return self.sent / self.seconds

    @property
    def emulator_bound(self) -> bool:
        return self.achieved_rate < 0.95 * self.rate

    @property
    def frames_received(self) -> int:
        return min(self.received.values())

    @property
    def messages(self) -> int:
        return sum(self.received.values())

    @property
    def dropped_by_count(self) -> int:
        return max(self.sent - self.frames_received, 0)

    @property
    def clean(self) -> bool:
        return (self.dropped_diag == 0 and self.lost_buffer_full == 0 and
                all(n == self.sent for n in self.received.values()))


class PoseCounter:
    """Counts poses per topic and keeps the driver's latest diagnostics (runs in rclpy)."""

    def __init__(self):
        import rclpy
        import rclpy.task
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.experimental import EventsExecutor
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions

        # Keep Python's own signal handling (Ctrl-C -> KeyboardInterrupt, SIGTERM -> SystemExit
        # via main()) so the finally blocks always stop the driver and the emulator.
        rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
        self.rclpy = rclpy
        self.node = rclpy.create_node('liberty_benchmark')
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
        self.counts = {name: 0 for name in STATION_NAMES}
        self.lock = threading.Lock()
        self.subscriptions = {}
        for name in STATION_NAMES:
            # raw=True: the callback gets the serialized message; counting needs no
            # deserialization, which keeps this process's CPU for the emulator.
            self.subscriptions[name] = self.node.create_subscription(
                PoseStamped, station_pose_topic(name), self._counter(name), qos, raw=True)
        self.diag: dict[str, str] | None = None
        self.diag_time = 0.0
        self.node.create_subscription(DiagnosticArray, 'diagnostics', self._on_diag, 10)
        self.executor = EventsExecutor()
        self.executor.add_node(self.node)
        self.done = rclpy.task.Future()
        self.thread = threading.Thread(target=self._spin, name='bench-spin', daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        # Always spin with a timeout: in this rclpy (Jazzy 7.1.6) EventsExecutor.spin() and
        # an untimed spin_until_future_complete() busy-wait holding the GIL (100 % CPU, the
        # other threads starve) and executor.shutdown() from another thread never returns.
        try:
            while not self.done.done():
                self.executor.spin_until_future_complete(self.done, timeout_sec=0.2)
        except Exception:
            pass

    def _counter(self, name):
        def on_pose(_msg) -> None:
            self.counts[name] += 1  # one executor thread: no lock needed for increments
        return on_pose

    def _on_diag(self, msg) -> None:
        for status in msg.status:
            if 'liberty_driver' in status.name:
                with self.lock:
                    self.diag = {kv.key: kv.value for kv in status.values}
                    self.diag_time = time.monotonic()

    def reset(self) -> None:
        with self.lock:
            for name in self.counts:
                self.counts[name] = 0
            self.diag = None
            self.diag_time = 0.0

    def snapshot(self) -> dict[str, int]:
        return dict(self.counts)

    def publishers_matched(self) -> bool:
        return all(sub.get_publisher_count() >= 1 for sub in self.subscriptions.values())

    def latest_diag(self, after: float) -> dict[str, str] | None:
        with self.lock:
            return dict(self.diag) if self.diag is not None and self.diag_time > after else None

    def close(self) -> None:
        self.done.set_result(True)
        self.executor.wake()
        self.thread.join(timeout=3.0)
        try:
            self.executor.shutdown()
            self.node.destroy_node()
        except Exception:
            pass
        self.rclpy.try_shutdown()


def process_cpu_seconds(pid: int) -> float | None:
    try:
        with open(f'/proc/{pid}/stat') as handle:
            fields = handle.read().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    except (OSError, IndexError, ValueError):
        return None


def wait_for(predicate, timeout: float, step: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return predicate()


def stop_process(proc: subprocess.Popen, log_path: Path) -> None:
    """SIGINT, then SIGKILL to the process group we created if it does not exit in time."""
    if proc.poll() is None:
        try:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=8.0)
        except subprocess.TimeoutExpired:
            say(f'  driver did not stop on SIGINT within 8 s; killing pid {proc.pid}')
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(timeout=5.0)


def tail(path: Path, lines: int = 15) -> str:
    try:
        return '\n'.join(path.read_text(errors='replace').splitlines()[-lines:])
    except OSError:
        return '(no log)'


def driver_run(counter: PoseCounter, rate: float | None, seconds: float, logdir: Path,
               label: str) -> RunResult:
    """One end-to-end run; the emulator is held paused until the driver's publishers are
    matched and it is streaming, so every frame sent can be expected at the subscriber."""
    counter.reset()
    emulator = LibertyEmulator(BuiltinMotion(STATIONS), unique_link(label),
                               rate_override=rate)
    emulator.pause(1e6)  # no frame leaves the device until the subscriber is ready
    emulator.start()
    log_path = logdir / f'driver_{label}.log'
    proc = None
    try:
        with open(log_path, 'wb') as log:
            proc = subprocess.Popen(
                [str(DRIVER_EXE), '--ros-args',
                 '-p', f'port:={emulator.port}', '-p', 'baud:=921600',
                 '-p', f'frame_rate:={DEVICE_RATE}', '-p', 'silence_timeout:=30.0',
                 '-p', 'reconnect_period:=0.2'],
                stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                cwd=WORKSPACE, env=os.environ.copy(), start_new_session=True)
        started = time.monotonic()
        ready = wait_for(lambda: proc.poll() is not None or (
            counter.publishers_matched() and
            (counter.latest_diag(started) or {}).get('state') == 'streaming'), 30.0)
        if proc.poll() is not None or not ready:
            why = (f'driver exited with code {proc.returncode}' if proc.poll() is not None
                   else 'driver not streaming with all publishers matched after 30 s')
            raise RuntimeError(f'{why}; log:\n{tail(log_path)}')
        time.sleep(0.5)  # let the driver's writers finish matching our readers
        counter.reset()
        sent_before = emulator.stats.frames_sent
        lost_before = emulator.stats.frames_lost_buffer_full
        cpu0_driver, cpu0_bench = process_cpu_seconds(proc.pid), time.process_time()
        t0 = time.monotonic()
        emulator.pause(0.0)
        nominal = rate or DEVICE_RATE
        say(f'  [{label}] streaming {len(STATIONS)} stations at {nominal:g} Hz for '
            f'{seconds:g} s (driver frame_rate {DEVICE_RATE}) ...')
        next_report = t0 + min(5.0, seconds / 2)
        while time.monotonic() - t0 < seconds:
            time.sleep(0.1)
            if proc.poll() is not None:
                raise RuntimeError(f'driver exited ({proc.returncode}) during the run; log:\n'
                                   f'{tail(log_path)}')
            now = time.monotonic()
            if now >= next_report:
                got = counter.snapshot()
                sent = emulator.stats.frames_sent - sent_before
                say(f'  [{label}] t={now - t0:5.1f} s  sent {sent} frames, received '
                    f'{min(got.values())} frames ({sum(got.values())} poses)')
                next_report += 5.0
        emulator.pause(1e6)
        elapsed = time.monotonic() - t0
        cpu1_driver, cpu1_bench = process_cpu_seconds(proc.pid), time.process_time()
        # Drain: wait until the pose counts stop moving, then for a diagnostics message
        # published after that.
        last, still_since = None, time.monotonic()
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            got = counter.snapshot()
            if got != last:
                last, still_since = got, time.monotonic()
            elif time.monotonic() - still_since > 0.5:
                break
            time.sleep(0.05)
        sent = emulator.stats.frames_sent - sent_before
        lost = emulator.stats.frames_lost_buffer_full - lost_before
        drained = time.monotonic()
        wait_for(lambda: counter.latest_diag(drained) is not None, 3.0)
        diag = counter.latest_diag(drained) or counter.latest_diag(0.0) or {}
        dropped = int(diag['dropped_frames']) if 'dropped_frames' in diag else None
        return RunResult(rate=nominal, seconds=elapsed, sent=sent, received=counter.snapshot(),
                         lost_buffer_full=lost, dropped_diag=dropped, diag=diag,
                         driver_cpu=None if cpu0_driver is None or cpu1_driver is None
                         else (cpu1_driver - cpu0_driver) / elapsed,
                         bench_cpu=(cpu1_bench - cpu0_bench) / elapsed)
    finally:
        if proc is not None:
            stop_process(proc, log_path)
            if proc.returncode not in (0, -signal.SIGINT):
                say(f'  [{label}] driver exit code {proc.returncode}; log tail:\n'
                    f'{tail(log_path)}')
        emulator.stop()


def report(result: RunResult, label: str) -> None:
    s = result.seconds
    say(f'  [{label}] {result.seconds:.2f} s: emulator sent {result.sent} frames '
        f'({result.sent / s:.1f} frames/s); received {result.frames_received / s:.1f} frames/s, '
        f'{result.messages / s:.1f} messages/s')
    if result.emulator_bound:
        say(f'  [{label}] note: the emulator reached only {result.achieved_rate:.0f} of '
            f'{result.rate:g} Hz (it runs in this process, in Python, on a 2-core machine): '
            'this rate measures the emulator, not the driver')
    cpu = lambda v: 'n/a' if v is None else f'{100 * v:.0f}%'  # noqa: E731
    per_frame = '' if result.driver_cpu is None or not result.sent else (
        f' = {1e6 * result.driver_cpu / result.achieved_rate:.0f} us per frame')
    say(f'  [{label}] CPU (of one core): driver process {cpu(result.driver_cpu)}{per_frame}, '
        f'benchmark process (emulator + subscriber) {cpu(result.bench_cpu)}')
    say(f'  [{label}] per station sent/received: ' + ', '.join(
        f'{name} {result.sent}/{n}' for name, n in result.received.items()))
    diag = result.diag
    published = diag.get('published_frames')
    if published is not None and published.isdigit():
        say(f'  [{label}] where: device -> driver {result.sent - int(published)} frames not '
            f'published (driver published {published} of {result.sent}); driver -> DDS -> '
            f'subscriber {int(published) - result.frames_received} frames not received')
    say(f'  [{label}] dropped frames: diagnostics dropped_frames={result.dropped_diag}, '
        f'by count {result.dropped_by_count}, emulator buffer-full losses '
        f'{result.lost_buffer_full}; driver frames={diag.get("frames")} '
        f'incomplete={diag.get("incomplete_frames")} resyncs={diag.get("resyncs")} '
        f'bytes_dropped={diag.get("bytes_dropped")} resets={diag.get("resets")}')


def bench_driver(seconds: float, stress_seconds: float, stress_rates) -> bool:
    if not DRIVER_EXE.exists():
        raise SystemExit(f'{DRIVER_EXE} missing: run bash launch_scripts/bootstrap.sh')
    domain = free_domain_id()
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.pop('ROS_LOCALHOST_ONLY', None)
    logdir = Path(tempfile.mkdtemp(prefix='bench_liberty_'))
    os.environ['ROS_LOG_DIR'] = str(logdir / 'ros_log')
    # The emulator thread is CPU-bound at high rates; the executor thread gives the GIL up
    # for every DDS wait and would then wait a whole switch interval (5 ms) to get it back,
    # capping the subscriber near 200 callbacks/s (the convoy effect). A short interval
    # keeps the subscriber's share of this process fair.
    sys.setswitchinterval(0.0005)
    say(f'== driver end to end: emulator (in-process, pty) -> liberty_driver (subprocess) '
        f'-> DDS -> EventsExecutor subscriber; ROS_DOMAIN_ID={domain}, discovery LOCALHOST')
    counter = PoseCounter()
    ok = False
    try:
        try:
            base = driver_run(counter, None, seconds, logdir, '240Hz')
        except RuntimeError as error:
            say(f'  [240Hz] run failed: {error}')
            say('driver sustained: n/a (the 240 Hz run failed)')
            return False
        report(base, '240Hz')
        ok = base.clean
        fps = base.frames_received / base.seconds
        say(f'driver sustained: {fps:.1f} frames/s x {len(STATIONS)} stations, dropped '
            f'{base.dropped_diag if base.dropped_diag is not None else "?"}, lost '
            f'{base.dropped_by_count} ({"OK" if ok else "FAIL"})')
        if stress_rates:
            say(f'== stress: emulator rate_override {", ".join(f"{r:g}" for r in stress_rates)}'
                f' Hz, {stress_seconds:g} s each (driver frame_rate stays {DEVICE_RATE}; its '
                'diagnostics rate check does not apply)')
            best = base if ok else None
            for rate in stress_rates:
                label = f'{rate:g}Hz'
                try:
                    result = driver_run(counter, rate, stress_seconds, logdir, label)
                except RuntimeError as error:
                    say(f'  [{label}] run failed: {error}')
                    break
                report(result, label)
                if not result.clean:
                    say(f'  [{label}] dropped or lost frames: stopping the stress step')
                    break
                best = result
            if best is None:
                say('stress: highest clean rate: none (the 240 Hz run already dropped frames)')
            else:
                fps = best.frames_received / best.seconds
                say(f'stress: highest clean rate: {fps:.1f} frames/s x {len(STATIONS)} stations '
                    f'= {fps * len(STATIONS):.0f} poses/s (emulator set to {best.rate:g} Hz'
                    + (', emulator-bound' if best.emulator_bound else '')
                    + '), nothing dropped or lost')
    finally:
        counter.close()
        shutil.rmtree(logdir, ignore_errors=True)
    return ok


# ============================================================================ main

def _terminate(signum, _frame) -> None:
    raise SystemExit(128 + signum)  # unwinds through the finally blocks


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seconds', type=float, default=None,
                        help='length of the 240 Hz driver run (default 20, 3 with --quick)')
    parser.add_argument('--stress-seconds', type=float, default=None,
                        help='length of each stress run (default 8, 2 with --quick)')
    parser.add_argument('--stress-rates', type=float, nargs='*', default=list(STRESS_RATES),
                        help='emulator rates for the stress step (Hz); none to skip it')
    parser.add_argument('--quick', action='store_true',
                        help='short runs and fewer records: a smoke check')
    parser.add_argument('--codec-only', action='store_true', help='only the codec part (a)')
    args = parser.parse_args(argv)
    seconds = args.seconds if args.seconds is not None else (3.0 if args.quick else 20.0)
    stress_seconds = args.stress_seconds if args.stress_seconds is not None else (
        2.0 if args.quick else 8.0)
    signal.signal(signal.SIGTERM, _terminate)
    start = time.monotonic()
    codec_ok = bench_codec(args.quick)
    driver_ok = True
    if not args.codec_only:
        driver_ok = bench_driver(seconds, stress_seconds, args.stress_rates)
    say(f'== done in {time.monotonic() - start:.0f} s: codec '
        f'{"OK" if codec_ok else "LOST RECORDS"}'
        + ('' if args.codec_only else f', driver 240 Hz {"OK" if driver_ok else "DROPPED/LOST"}'))
    return 0 if codec_ok and driver_ok else 1


if __name__ == '__main__':
    sys.exit(main())
