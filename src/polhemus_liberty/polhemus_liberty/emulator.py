"""An emulated Liberty on a pseudo-terminal: device model + motion source + fault injection.

It is the embedded default for live mode (no hardware needed) and the driver's test
fixture. Faults are injected on demand through methods that are safe to call from any
thread (the CLI maps console commands and a schedule onto them):

* ``inject_garbage(n)``: n random bytes (never containing the sync word) into the stream;
* ``drop_bytes(n)``: cut n bytes out of the next frame, as a lossy link would;
* ``skip_frames(n)``: n frames counted by the device but never sent;
* ``pause(seconds)``: the device stalls, then carries on streaming by itself;
* ``stall()``: the device stops streaming until the host restarts it (reset sequence);
* ``disconnect(seconds)``: the port vanishes (USB unplug) and reappears under its name,
  the device still streaming as it was; the frames it sends before the host writes to the
  port again reach no reader (``EmulatorStats.frames_before_host``).
"""

from __future__ import annotations

import random
import threading
import time
from collections import deque
from dataclasses import dataclass

from polhemus_liberty.device_model import LibertyDevice
from polhemus_liberty.motion import MotionSource
from polhemus_liberty.pty_link import PtyLink

__all__ = ['EmulatorStats', 'LibertyEmulator']

MAX_PENDING_BYTES = 1 << 16  # like a device's USB buffer: past this, frames are lost


@dataclass
class EmulatorStats:
    frames_sent: int = 0
    frames_lost_buffer_full: int = 0
    frames_skipped: int = 0
    bytes_sent: int = 0
    garbage_bytes: int = 0
    bytes_cut: int = 0
    disconnects: int = 0
    late_ticks: int = 0
    # sent after a re-plug and before the host wrote to the port again: a real device's
    # frames that no host was reading (a driver's set-up discards them)
    frames_before_host: int = 0


class LibertyEmulator:
    """Streams ``motion`` through an emulated Liberty on a pty at ``link_path``.

    ``rate_override`` streams faster or slower than the device's 120/240 Hz (for stress
    benchmarks). ``history`` keeps the last N frames sent as (frame_count, poses) so tests
    can compare what the driver published with what the device sent.
    """

    def __init__(self, motion: MotionSource, link_path: str | None = None,
                 stations: tuple[int, ...] | None = None, rate_override: float | None = None,
                 history: int = 0, seed: int = 0):
        self.motion = motion
        self.device = LibertyDevice(stations or motion.stations)
        self.link = PtyLink(link_path)
        self.rate_override = rate_override
        self.stats = EmulatorStats()
        self.sent_frames: deque = deque(maxlen=history)
        self._rng = random.Random(seed)
        self._lock = threading.Lock()
        self._garbage = 0
        self._cut = 0
        self._skip = 0
        self._paused_until = 0.0
        self._reappear_at: float | None = None
        self._unplug_for: float | None = None
        self._stall = False
        self._host_back = True      # False from a re-plug until the host writes again
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._out = bytearray()

    # ------------------------------------------------------------------ control
    @property
    def port(self) -> str:
        return self.link.port

    def start(self) -> LibertyEmulator:
        self._thread = threading.Thread(target=self.run, name='liberty-emulator', daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.link.close()

    def __enter__(self) -> LibertyEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def inject_garbage(self, count: int) -> None:
        with self._lock:
            self._garbage += int(count)

    def drop_bytes(self, count: int) -> None:
        with self._lock:
            self._cut += int(count)

    def skip_frames(self, count: int) -> None:
        with self._lock:
            self._skip += int(count)

    def pause(self, seconds: float) -> None:
        with self._lock:
            self._paused_until = time.monotonic() + float(seconds)

    def stall(self) -> None:
        with self._lock:
            self._stall = True

    def disconnect(self, seconds: float) -> None:
        with self._lock:
            self._unplug_for = float(seconds)

    def status(self) -> str:
        state = self.device.state
        mode = 'binary' if state.binary else 'ascii'
        streaming = f'streaming {mode} {self._rate():g} Hz' if state.continuous else 'idle'
        link = f'{self.port} -> {self.link.slave_name}' if self.link.connected else \
            f'{self.port} (unplugged)'
        return (f'{link} | {streaming} | frames sent {self.stats.frames_sent} | '
                f'lost {self.stats.frames_lost_buffer_full} | skipped {self.stats.frames_skipped} | '
                f'before the host came back {self.stats.frames_before_host}')

    # ------------------------------------------------------------------ loop
    def _rate(self) -> float:
        return float(self.rate_override or self.device.state.frame_rate)

    def run(self) -> None:
        start = time.monotonic()
        next_tick = start
        while not self._stop.is_set():
            now = time.monotonic()
            with self._lock:
                if self._unplug_for is not None:
                    # Unplug from this thread only: the pty is never closed under a select.
                    self._reappear_at = now + self._unplug_for
                    self._unplug_for = None
                    self.stats.disconnects += 1
                    self._out.clear()
                    self.link.unplug()
                if self._reappear_at is not None and now >= self._reappear_at:
                    self._reappear_at = None
                    self.link.plug()
                    self._host_back = False
            if not self.link.connected:
                time.sleep(0.005)
                next_tick = time.monotonic()
                continue
            data = self.link.read(min(max(next_tick - now, 0.0), 0.01))
            if data:
                self._host_back = True
                self._out += self.device.receive(data, time.monotonic())
            now = time.monotonic()
            period = 1.0 / self._rate()
            if now >= next_tick:
                if now - next_tick > 0.5:  # starved of CPU for long: do not burst the backlog
                    self.stats.late_ticks += 1
                    next_tick = now
                self._tick(now, now - start)
                next_tick += period
            self._flush()

    def _tick(self, now: float, t: float) -> None:
        device = self.device
        device.set_poses(self.motion.sample(t))
        with self._lock:
            if self._stall:
                self._stall = False
                device.state.continuous = False
            if now < self._paused_until or not device.state.continuous:
                return
            if self._skip > 0:
                self._skip -= 1
                device.skip_frame()
                self.stats.frames_skipped += 1
                return
            garbage, self._garbage = self._garbage, 0
            cut, self._cut = self._cut, 0
        frame = device.frame(now)
        if not frame:
            return
        if len(self._out) + len(frame) > MAX_PENDING_BYTES:
            self.stats.frames_lost_buffer_full += 1
            return
        if garbage:
            self._out += self._garbage_bytes(garbage, line_end=not device.state.binary)
            self.stats.garbage_bytes += garbage
        if cut:
            offset = self._rng.randrange(max(len(frame) - cut, 1))
            frame = frame[:offset] + frame[offset + cut:]
            self.stats.bytes_cut += min(cut, len(frame))
        self._out += frame
        self.stats.frames_sent += 1
        if not self._host_back:
            self.stats.frames_before_host += 1
        if self.sent_frames.maxlen:
            self.sent_frames.append((device.frame_count, dict(device.poses)))

    def _garbage_bytes(self, count: int, line_end: bool) -> bytes:
        garbage = bytes(self._rng.randrange(256) for _ in range(count))
        # Keep the sync word out so the next good record is provably recoverable; in ASCII
        # mode the garbage is a line of its own, so it costs no good line.
        garbage = garbage.replace(b'LY', b'lY').replace(b'\n', b'.')
        return garbage + b'\r\n' if line_end else garbage

    def _flush(self) -> None:
        if self._out:
            written = self.link.write(bytes(self._out))
            self.stats.bytes_sent += written
            del self._out[:written]
