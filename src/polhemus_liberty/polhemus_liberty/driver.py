"""The Liberty driver without ROS: port handling, set-up, streaming, faults and statistics.

``LibertyDriver.run()`` is a loop that owns the serial port:

1. open the port (retrying every ``reconnect_period`` while it is missing);
2. set the device up: CR, P, flush, F1, U1/U0, O*,..., H*,..., R3/R4, then read back the
   WhoAmI and the active-station map (in binary, whatever the streaming format), then F0
   if ASCII was asked for, then C;
3. stream: parse records, group them into frames, stamp each frame with the host clock at
   receipt minus ``latency_offset``, hand it to ``on_frame`` in SI units;
4. on silence longer than ``silence_timeout``: the reset sequence (back to 2);
   on a vanished port (USB unplug): close, back to 1;
5. on stop: P (ends continuous output), close the port.

The ROS node is a thin adapter around this class; tests and benchmarks drive it directly
against the emulator on a pty.
"""

from __future__ import annotations

import logging
import termios
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import serial

from inhand_common.health import ERROR, WARN, IntervalCounts, Problems
from polhemus_liberty.device_pose import record_to_pose
from polhemus_liberty.driver_config import DriverConfig
from polhemus_liberty.frames import Frame, FrameAssembler
from polhemus_liberty.protocol import (
    CMD_CONTINUOUS,
    CMD_FLUSH,
    CMD_SINGLE,
    CMD_STATION_MAP,
    CMD_WHOAMI,
    CTRL_U,
    CTRL_V,
    Reply,
    cmd_format,
    cmd_frame_rate,
    cmd_hemisphere,
    cmd_output_list,
    cmd_units,
    decode_station_map,
    link_bytes_per_second,
    make_stream_parser,
)

__all__ = ['LibertyDriver', 'PoseFrame']

# What a vanished or broken port raises: pyserial's own errors, OS errors, and termios
# errors from flushes on a pty whose other end is gone.
PORT_ERRORS = (serial.SerialException, OSError, termios.error)

READ_TIMEOUT = 0.02       # s: how long one read waits; bounds stop and silence latency
SETTLE_AFTER_LIST = 0.1   # s: readers wait this long after setting the output list
READBACK_TIMEOUT = 0.5    # s: how long to wait for the WhoAmI and station map replies



@dataclass
class PoseFrame:
    """One tracker frame in SI units: what the node publishes under one stamp."""

    stamp: float                                   # host time (s) minus latency offset
    frame_count: int | None
    poses: dict[int, tuple[np.ndarray, np.ndarray]]  # station -> (position m, quat xyzw)
    distortion: dict[int, int] = field(default_factory=dict)


class LibertyDriver:
    def __init__(self, config: DriverConfig, on_frame: Callable[[PoseFrame], None],
                 log=None, clock: Callable[[], float] = time.time):
        self.config = config
        self.on_frame = on_frame
        self.log = log or logging.getLogger('polhemus_liberty')
        self.clock = clock
        self.state = 'starting'
        self.whoami: str | None = None
        self.active_stations: set[int] | None = None
        self.reconnects = 0
        self.resets = 0
        self.published = 0
        self.invalid_poses = 0
        self.distortion: dict[int, int] = {}
        self.assembler = FrameAssembler(config.stations, config.frame_rate)
        self._parser = make_stream_parser(config.output_list, config.binary)
        self._parser_totals = {'bytes_dropped': 0, 'resyncs': 0, 'records': 0,
                               'error_records': 0}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._port: serial.Serial | None = None
        self._interval = IntervalCounts(time.monotonic())
        self._warned_missing = False
        self._last_receipt = float('-inf')

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> LibertyDriver:
        self._thread = threading.Thread(target=self.run, name='liberty-driver', daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 3.0) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def run(self) -> None:
        try:
            while not self._stop.is_set():
                if self._port is None and not self._open():
                    self._stop.wait(self.config.reconnect_period)
                    continue
                try:
                    self._configure()
                    self._stream()
                except PORT_ERRORS as error:
                    self._lost(error)
        finally:
            self._close(stop_device=True)
            self.state = 'stopped'

    # ------------------------------------------------------------------ port
    def _open(self) -> bool:
        try:
            self._port = serial.Serial(self.config.port, self.config.baud, timeout=READ_TIMEOUT,
                                       write_timeout=1.0)
        except PORT_ERRORS as error:
            if not self._warned_missing:
                self.log.warning(f'cannot open {self.config.port} ({error}); retrying every '
                                 f'{self.config.reconnect_period:g} s')
                self._warned_missing = True
            self.state = 'disconnected'
            return False
        if self._warned_missing or self.reconnects:
            self.log.info(f'{self.config.port} is back')
        self._warned_missing = False
        return True

    def _lost(self, error: Exception) -> None:
        self.log.warning(f'lost {self.config.port}: {error}; reconnecting')
        self.reconnects += 1
        self._finish_frame()
        self._close(stop_device=False)
        self.state = 'disconnected'

    def _close(self, stop_device: bool) -> None:
        port, self._port = self._port, None
        if port is None:
            return
        try:
            if stop_device:
                port.write(CMD_SINGLE)  # P ends continuous output
                port.flush()
                time.sleep(0.05)
                port.reset_input_buffer()
        except PORT_ERRORS:
            pass
        finally:
            try:
                port.close()
            except PORT_ERRORS:
                pass

    def _send(self, command: bytes) -> None:
        self.log.debug(f'sent {command!r}')
        self._port.write(command)

    # ------------------------------------------------------------------ set-up
    def _configure(self) -> None:
        """The set-up sequence, also the reset sequence for a silent device."""
        config = self.config
        self.state = 'configuring'
        port = self._port
        self._send(CMD_FLUSH)
        self._send(CMD_SINGLE)
        time.sleep(0.05)
        port.reset_input_buffer()
        for command in (cmd_format(True), cmd_units(config.units == 'cm'),
                        cmd_output_list(config.output_list.codes)):
            self._send(command)
        time.sleep(SETTLE_AFTER_LIST)
        self._send(cmd_hemisphere(config.hemisphere))
        self._send(cmd_frame_rate(config.frame_rate))
        self._read_back()
        if not config.binary:
            self._send(cmd_format(False))
        self._check_link_budget()
        self._accumulate_parser_stats()
        self._parser = make_stream_parser(config.output_list, config.binary)
        self.assembler.restart()
        self._send(CMD_CONTINUOUS)
        self.state = 'streaming'
        self.log.info(f'streaming {len(config.stations)} station(s) from {config.port} at '
                      f'{config.frame_rate} Hz, {"binary" if config.binary else "ASCII"}, '
                      f'output list {list(config.output_list.codes)}')

    def _read_back(self) -> None:
        """Ask for WhoAmI and the station map; settings themselves have no read-back."""
        self._send(CMD_WHOAMI)
        self._send(CMD_STATION_MAP)
        parser = make_stream_parser(self.config.output_list, binary=True, accept_replies=True)
        deadline = time.monotonic() + READBACK_TIMEOUT
        whoami = station_map = None
        while time.monotonic() < deadline and (whoami is None or station_map is None):
            for item in parser.feed(self._port.read(max(self._port.in_waiting, 1))):
                if isinstance(item, Reply) and item.command == CTRL_V:
                    whoami = item.payload.decode('ascii', 'replace').strip()
                elif isinstance(item, Reply) and item.command == CTRL_U and \
                        len(item.payload) >= 4:
                    station_map = decode_station_map(item.payload)
        if whoami is not None:
            self.whoami = whoami
            self.log.info(f'device: {whoami}')
        else:
            self.log.warning('no WhoAmI reply (old firmware or not a Liberty?)')
        if station_map is not None:
            _, active = station_map
            self.active_stations = active
            missing = sorted(set(self.config.stations) - active)
            if missing:
                self.log.warning('configured stations not active on the device: ' + ', '.join(
                    f'{s} ({self.config.stations[s]})' for s in missing))
        else:
            self.log.warning('no station map reply; publishing the configured stations')

    def _check_link_budget(self) -> None:
        need = self.config.bytes_per_second()
        capacity = link_bytes_per_second(self.config.baud)
        if need > capacity:
            self.log.warning(
                f'the link cannot carry this stream: {self.config.frame_rate} Hz x '
                f'{len(self.config.stations)} stations x record size needs {need:.0f} B/s, '
                f'{self.config.baud} baud carries {capacity:.0f} B/s; expect lost frames '
                '(use the USB link, fewer stations, 120 Hz or a shorter output list)')

    # ------------------------------------------------------------------ streaming
    def _stream(self) -> None:
        port = self._port
        last_data = time.monotonic()
        while not self._stop.is_set():
            chunk = port.read(max(port.in_waiting, 1))
            now = time.monotonic()
            if not chunk:
                if now - last_data > 2.0 / self.config.frame_rate:
                    self._finish_frame()
                if now - last_data > self.config.silence_timeout:
                    self.log.warning(f'no data for {self.config.silence_timeout:g} s: '
                                     'resetting the device (CR, P, flush, set-up, C)')
                    self.resets += 1
                    self._finish_frame()
                    return  # back to run(): configure again
                continue
            last_data = now
            receipt = self.clock()
            frames = []
            for record in self._parser.feed(chunk):
                if not isinstance(record, Reply):
                    frames.extend(self.assembler.add(record, receipt))
            self._backdate(frames, receipt)
            for frame in frames:
                self._emit(frame)

    def _backdate(self, frames: list[Frame], receipt: float) -> None:
        """Give frames that arrived together in one read their own, earlier stamps.

        USB and the OS deliver the stream in bursts; the device sent those frames one
        period apart, so the k-th last frame of a burst is stamped k periods before
        receipt. Stamps also never go backwards, so every frame has a stamp of its own.
        """
        period = 1.0 / self.config.frame_rate
        count = len(frames)
        for index, frame in enumerate(frames):
            if frame.receipt_time == receipt:
                frame.receipt_time = receipt - (count - 1 - index) * period
            if frame.receipt_time <= self._last_receipt:
                frame.receipt_time = self._last_receipt + 1e-6
            self._last_receipt = frame.receipt_time

    def _finish_frame(self) -> None:
        frame = self.assembler.flush()
        if frame is not None:
            self._emit(frame)

    def _emit(self, frame: Frame) -> None:
        poses = {}
        for station, record in frame.records.items():
            pose = record_to_pose(record, self.config.units)
            if pose is None:
                self.invalid_poses += 1
            else:
                poses[station] = pose
        if not poses:
            return
        distortion = {s: r.distortion for s, r in frame.records.items()
                      if r.distortion is not None}
        self.distortion.update(distortion)
        self.published += 1
        self.on_frame(PoseFrame(stamp=frame.receipt_time - self.config.latency_offset,
                                frame_count=frame.frame_count, poses=poses,
                                distortion=distortion))

    # ------------------------------------------------------------------ statistics
    def _accumulate_parser_stats(self) -> None:
        stats = self._parser.stats
        for key in self._parser_totals:
            self._parser_totals[key] += getattr(stats, key)
        self._parser.stats = type(stats)()

    def counters(self) -> dict[str, int]:
        """Totals since start (parser counters of every session added up)."""
        stats = self._parser.stats
        totals = {key: value + getattr(stats, key) for key, value in self._parser_totals.items()}
        frames = self.assembler.counters
        totals.update(frames=frames.frames, dropped_frames=frames.dropped,
                      incomplete_frames=frames.incomplete, counter_resets=frames.counter_resets,
                      unmapped_records=frames.unmapped_records, reconnects=self.reconnects,
                      resets=self.resets, published_frames=self.published,
                      invalid_poses=self.invalid_poses)
        return totals

    def report(self, now: float, problems: Problems) -> tuple[str, dict[str, object]]:
        """The OK message and the values for diagnostics, with what is wrong added to
        ``problems``. Rates and problems are those since the previous call: WARN on dropped
        or incomplete frames and resyncs in that interval, a slow stream or an over-budget
        link; ERROR while not streaming."""
        counters = self.counters()
        elapsed, new = self._interval.step(now, counters)
        rate = new['frames'] / elapsed
        detects_drops = 9 in self.config.output_list.codes or 8 in self.config.output_list.codes
        values: dict[str, object] = dict(counters)
        values.update(state=self.state, port=self.config.port, frame_rate_hz=f'{rate:.1f}',
                      expected_rate_hz=str(self.config.frame_rate),
                      drop_detection='frame counter' if 9 in self.config.output_list.codes
                      else ('timestamp' if detects_drops else 'unavailable (no item 8 or 9)'),
                      link_need_bytes_per_s=f'{self.config.bytes_per_second():.0f}',
                      link_capacity_bytes_per_s=f'{link_bytes_per_second(self.config.baud):.0f}')
        if self.whoami:
            values['device'] = self.whoami
        for station, level in sorted(self.distortion.items()):
            values[f'distortion_{self.config.stations[station]}'] = str(level)
        if self.state != 'streaming':
            problems.add(ERROR, 'not_streaming', f'{self.state}: no data from {self.config.port}')
        else:
            interval = f'in the last {elapsed:.1f} s'
            if new['dropped_frames']:
                problems.add(WARN, 'dropped', f"{new['dropped_frames']} frame(s) dropped {interval}")
            if new['incomplete_frames']:
                problems.add(WARN, 'incomplete', f"{new['incomplete_frames']} incomplete frame(s) "
                             f'{interval}')
            if new['resyncs']:
                problems.add(WARN, 'resyncs', f"{new['resyncs']} resync(s) of a corrupt stream "
                             f"({new['bytes_dropped']} bytes skipped) {interval}")
            if self.config.bytes_per_second() > link_bytes_per_second(self.config.baud):
                problems.add(WARN, 'link_budget', 'stream exceeds the serial link budget')
            if rate < 0.9 * self.config.frame_rate:
                problems.add(WARN, 'slow', f'frame rate {rate:.0f} Hz below the expected '
                             f'{self.config.frame_rate} Hz')
        return f'streaming at {rate:.0f} Hz', values

