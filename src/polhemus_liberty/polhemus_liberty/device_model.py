"""What a Liberty does with the bytes it receives and the frames it sends, without any I/O.

The emulator wraps this model around a pseudo-terminal; tests can drive it directly.
Power-on state follows the protocol notes: ASCII output, inches, output list ``2,4,1``,
240 Hz, hemisphere +X, not streaming.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from polhemus_liberty.device_pose import pose_to_record
from polhemus_liberty.protocol import (
    CTRL_U,
    CTRL_V,
    OutputList,
    encode_binary_record,
    encode_binary_reply,
    format_ascii_record,
)

__all__ = ['DeviceState', 'LibertyDevice']

POWER_ON_ITEMS = (2, 4, 1)
INVALID_COMMAND = b'\r\n*** INVALID COMMAND ***\r\n'
CTRL_Y = 0x19


@dataclass
class DeviceState:
    binary: bool = False
    centimetres: bool = False
    output_list: OutputList = field(default_factory=lambda: OutputList(POWER_ON_ITEMS))
    hemisphere: tuple[float, float, float] = (1.0, 0.0, 0.0)
    frame_rate: int = 240
    continuous: bool = False


class LibertyDevice:
    """Command interpreter and record generator of an emulated Liberty.

    ``receive(data, now)`` returns the bytes the device answers; ``frame(now)``
    returns the bytes of one tracker frame (all active stations at the poses last given to
    ``set_poses``) and advances the frame
    counter. Commands end with CR except ``P``, which acts at once.
    """

    def __init__(self, stations: Iterable[int] = (1, 2, 3, 4),
                 whoami: str = 'Liberty emulator 240/16, firmware emu-1.0',
                 reinit_seconds: float = 0.5):
        self.stations = tuple(sorted(stations))
        self.whoami = whoami
        self.reinit_seconds = reinit_seconds
        self.state = DeviceState()
        self.frame_count = 0
        self.clock_origin: float | None = None
        self.busy_until = 0.0
        self.poses: Mapping[int, tuple[np.ndarray, np.ndarray]] = {}
        self.commands_seen: list[bytes] = []
        self.invalid_commands = 0
        self._pending = bytearray()

    # ------------------------------------------------------------------ input
    def receive(self, data: bytes, now: float) -> bytes:
        out = bytearray()
        for byte in data:
            if now < self.busy_until:
                continue  # re-initialising: the real device ignores input for 10-20 s
            if not self._pending and byte in (ord('P'), ord('p')):
                self.commands_seen.append(b'P')
                self.state.continuous = False
                out += self._single_shot(now)
                continue
            if byte == 0x0D:
                command = bytes(self._pending)
                self._pending.clear()
                self.commands_seen.append(command)
                out += self._execute(command, now)
            elif byte != 0x0A:
                self._pending.append(byte)
                if len(self._pending) > 256:  # runaway input without CR: discard
                    self._pending.clear()
        return bytes(out)

    def _execute(self, command: bytes, now: float) -> bytes:
        state = self.state
        if not command:
            return self._invalid()
        head = command[0]
        if head == CTRL_U:
            return self._station_map_reply()
        if head == CTRL_V:
            return self._whoami_reply()
        if head == CTRL_Y:
            poses = self.poses
            self.__init__(self.stations, self.whoami, self.reinit_seconds)
            self.poses = poses
            self.busy_until = now + self.reinit_seconds
            return b''
        text = command.decode('ascii', 'replace').strip().upper()
        letter, rest = text[:1], text[1:]
        try:
            if letter == 'F' and rest in ('0', '1'):
                state.binary = rest == '1'
            elif letter == 'U' and rest in ('0', '1'):
                state.centimetres = rest == '1'
            elif letter == 'R' and rest in ('3', '4'):
                state.frame_rate = 120 if rest == '3' else 240
            elif letter == 'C' and not rest:
                state.continuous = True
            elif letter == 'Q' and not rest:
                self.frame_count = 0
                self.clock_origin = now
            elif letter == 'O':
                _, _, items = rest.partition(',')
                state.output_list = OutputList(int(v) for v in items.split(','))
            elif letter == 'H':
                _, _, values = rest.partition(',')
                vector = tuple(float(v) for v in values.split(','))
                if len(vector) != 3:
                    raise ValueError(text)
                state.hemisphere = vector
            else:
                return self._invalid()
        except ValueError:
            return self._invalid()
        return b''

    def _invalid(self) -> bytes:
        self.invalid_commands += 1
        return INVALID_COMMAND

    def _station_map_reply(self) -> bytes:
        bits = 0
        for station in self.stations:
            bits |= 1 << (station - 1)
        if self.state.binary:
            return encode_binary_reply(CTRL_U, struct.pack('<HH', bits, bits))
        return f' 0{chr(CTRL_U)} {bits:04X} {bits:04X}\r\n'.encode('ascii')

    def _whoami_reply(self) -> bytes:
        if self.state.binary:
            return encode_binary_reply(CTRL_V, self.whoami.encode('ascii'))
        return f' 0{chr(CTRL_V)} {self.whoami}\r\n'.encode('ascii')

    # ------------------------------------------------------------------ output
    def _records(self, poses: Mapping[int, tuple[np.ndarray, np.ndarray]], now: float,
                 command: str) -> bytes:
        state = self.state
        if self.clock_origin is None:
            self.clock_origin = now
        timestamp_ms = int((now - self.clock_origin) * 1000.0)
        units = 'cm' if state.centimetres else 'inch'
        encode = encode_binary_record if state.binary else format_ascii_record
        out = bytearray()
        for station in self.stations:
            if station not in poses:
                continue
            position, quaternion = poses[station]
            position = self._apply_hemisphere(np.asarray(position, dtype=float))
            record = pose_to_record(station, position, quaternion, units, command=command,
                                    frame_count=self.frame_count, timestamp_ms=timestamp_ms)
            out += encode(state.output_list, record)
        return bytes(out)

    def _apply_hemisphere(self, position: np.ndarray) -> np.ndarray:
        # The device reports the solution in the chosen hemisphere: a position on the
        # other side comes out mirrored through the source (the documented sign flip).
        hemisphere = np.asarray(self.state.hemisphere)
        if np.any(hemisphere) and float(position @ hemisphere) < 0.0:
            return -position
        return position

    def _single_shot(self, now: float) -> bytes:
        self.frame_count += 1
        return self._records(self.poses, now, 'P')

    def set_poses(self, poses: Mapping[int, tuple[np.ndarray, np.ndarray]]) -> None:
        """The sensors' current poses (SI, source frame), sampled by the emulator each tick."""
        self.poses = poses

    def frame(self, now: float) -> bytes:
        """The bytes of one continuous-mode frame (b'' when not streaming or busy)."""
        if not self.state.continuous or now < self.busy_until:
            return b''
        self.frame_count += 1
        return self._records(self.poses, now, 'C')

    def skip_frame(self) -> None:
        """Advance the frame counter without sending (a frame lost on the way)."""
        self.frame_count += 1
