"""Polhemus Liberty host protocol: commands, output items, record codecs, stream parsers.

Pure Python (no ROS, no serial port): the driver, the device emulator and the tests all
speak the protocol through this one module. The layout facts are those of
``shared/liberty-protocol.md``:

* binary (``F1``) records: ``'LY'``, station (1-16), initiating command (``C``/``P``),
  error byte (0x20 = no error), a reserved byte, the payload size as uint16 little-endian,
  then the output items in list order, little-endian;
* ASCII (``F0``) records: one CR LF terminated line per station, a 4-character header
  (station in two characters, command, error) and fixed-width numeric fields.

The stream parsers never raise on device bytes: they resynchronise after garbage, partial
reads, wrong size fields or impossible station numbers, and count what they dropped.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

__all__ = [
    'CMD_CONTINUOUS',
    'CMD_FLUSH',
    'CMD_RESET_COUNTERS',
    'CMD_SINGLE',
    'CMD_STATION_MAP',
    'CMD_WHOAMI',
    'CTRL_U',
    'CTRL_V',
    'DEFAULT_OUTPUT_ITEMS',
    'ITEMS',
    'MAX_STATIONS',
    'NO_ERROR',
    'AsciiStreamParser',
    'BinaryStreamParser',
    'OutputItem',
    'OutputList',
    'ParserStats',
    'Reply',
    'StationRecord',
    'cmd_format',
    'cmd_frame_rate',
    'cmd_hemisphere',
    'cmd_output_list',
    'cmd_units',
    'decode_station_map',
    'encode_binary_record',
    'encode_binary_reply',
    'format_ascii_record',
    'link_bytes_per_second',
    'make_stream_parser',
]

SYNC_LIBERTY = b'LY'
HEADER = struct.Struct('<2sBBBBH')  # sync, station, command, error, reserved, payload size
HEADER_SIZE = HEADER.size  # 8
NO_ERROR = 0x20
MAX_STATIONS = 16
DATA_COMMANDS = frozenset(b'CP')  # continuous, single-shot
CTRL_U = 0x15  # active station map
CTRL_V = 0x16  # WhoAmI
MAX_REPLY_PAYLOAD = 1024


@dataclass(frozen=True)
class OutputItem:
    """One entry of the Liberty output list (``O*,...``).

    ``fmt`` is the binary struct code used to decode (little-endian, no prefix; padding
    and CR LF are skipped there, the CR LF is checked separately), ``encode_fmt`` the one
    used to encode when it differs, ``field`` the :class:`StationRecord` attribute it
    fills, ``ascii_format`` the printf format of one value in ASCII mode (its width is the
    field width).
    """

    code: int
    name: str
    fmt: str
    field: str | None
    ascii_format: str | None
    encode_fmt: str | None = None

    @property
    def size(self) -> int:
        return struct.calcsize('<' + self.fmt)

    @property
    def ascii_width(self) -> int:
        """Characters of one value in ASCII mode (padding items take one, CR LF none)."""
        if self.ascii_format is None:
            return 1 if self.code == 0 else 0
        width = re.match(r'%(\d+)', self.ascii_format)
        if width is None:
            raise ValueError(f'item {self.code}: ASCII format {self.ascii_format!r} has no width')
        return int(width.group(1))

    @property
    def count(self) -> int:
        """Number of values this item carries (0 for padding and CR LF)."""
        if self.field is None:
            return 0
        return len(struct.unpack('<' + self.fmt, bytes(self.size)))


ITEMS: dict[int, OutputItem] = {item.code: item for item in (
    OutputItem(0, 'space', 'x', None, None, encode_fmt='c'),
    OutputItem(1, 'crlf', '2x', None, None, encode_fmt='2s'),
    OutputItem(2, 'position', '3f', 'position', '%9.4f'),
    OutputItem(3, 'position_ext', '3f', 'position', '%13.6e'),
    OutputItem(4, 'euler', '3f', 'euler_deg', '%9.4f'),
    OutputItem(5, 'euler_ext', '3f', 'euler_deg', '%13.6e'),
    OutputItem(6, 'direction_cosines', '9f', 'direction_cosines', '%9.5f'),
    OutputItem(7, 'quaternion', '4f', 'quaternion_wxyz', '%9.5f'),
    OutputItem(8, 'timestamp', 'I', 'timestamp_ms', '%11d'),
    OutputItem(9, 'frame_count', 'I', 'frame_count', '%11d'),
    OutputItem(10, 'stylus', 'I', 'stylus', '%3d'),
    OutputItem(11, 'distortion', 'i', 'distortion', '%4d'),
    OutputItem(12, 'external_sync', 'I', 'external_sync', '%3d'),
)}

# Timestamp, frame count, position, quaternion, CR LF: 46-byte records (the protocol notes'
# worked example). The quaternion avoids the Euler singularity at elevation +-90 degrees.
DEFAULT_OUTPUT_ITEMS = (8, 9, 2, 7, 1)


@dataclass
class StationRecord:
    """One station's data from one tracker frame, in device units (cm or inches, degrees).

    Fields the output list does not carry stay None.
    """

    station: int
    command: str = 'C'
    error: int = NO_ERROR
    position: tuple[float, float, float] | None = None
    euler_deg: tuple[float, float, float] | None = None
    direction_cosines: tuple[float, ...] | None = None
    quaternion_wxyz: tuple[float, float, float, float] | None = None
    timestamp_ms: int | None = None
    frame_count: int | None = None
    stylus: int | None = None
    distortion: int | None = None
    external_sync: int | None = None


@dataclass
class Reply:
    """A device reply that is not a data record (station map, WhoAmI, ASCII text)."""

    command: int
    station: int
    payload: bytes


class OutputList:
    """A validated output item list with its binary layout and ASCII field widths."""

    def __init__(self, codes: Iterable[int]):
        codes = tuple(int(c) for c in codes)
        unknown = [c for c in codes if c not in ITEMS]
        if not codes or unknown:
            raise ValueError(f'output list {list(codes)}: unknown item codes {unknown}; '
                             f'allowed are {sorted(ITEMS)}')
        fields = [ITEMS[c].field for c in codes if ITEMS[c].field]
        if len(fields) != len(set(fields)):
            raise ValueError(f'output list {list(codes)} carries the same quantity twice')
        if 1 in codes and (codes[-1] != 1 or codes.count(1) > 1):
            raise ValueError(f'output list {list(codes)}: CR LF (item 1) may only come last')
        self.codes = codes
        self.items = tuple(ITEMS[c] for c in codes)
        self.payload_struct = struct.Struct('<' + ''.join(i.fmt for i in self.items))
        self.encode_struct = struct.Struct('<' + ''.join(i.encode_fmt or i.fmt
                                                         for i in self.items))
        self.payload_size = self.payload_struct.size
        self.record_size = HEADER_SIZE + self.payload_size
        self.ends_with_crlf = codes[-1] == 1
        self.value_items = tuple(i for i in self.items if i.field)
        # (StationRecord attribute, number of values) of each value item, worked out once:
        # record_from_values walks them for every record.
        self._value_slots = tuple((i.field, i.count) for i in self.items if i.field)
        self.value_count = sum(count for _, count in self._value_slots)
        # 4 header characters (station, command, error), the fields, CR LF.
        self.ascii_line_size = 4 + sum(i.ascii_width * max(i.count, 1) for i in self.items) + 2

    def __repr__(self) -> str:
        return f'OutputList({list(self.codes)})'

    def __eq__(self, other: object) -> bool:
        return isinstance(other, OutputList) and other.codes == self.codes

    def __hash__(self) -> int:
        return hash(self.codes)

    @property
    def has_orientation(self) -> bool:
        return any(c in self.codes for c in (4, 5, 6, 7))

    @property
    def has_position(self) -> bool:
        return 2 in self.codes or 3 in self.codes

    def record_from_values(self, station: int, command: str, error: int,
                           flat: Sequence[float]) -> StationRecord:
        """Distribute a flat value sequence (in item order) over a :class:`StationRecord`."""
        record = StationRecord(station=station, command=command, error=error)
        index = 0
        for name, n in self._value_slots:
            if n == 1:
                setattr(record, name, flat[index])
            else:
                setattr(record, name, tuple(flat[index:index + n]))
            index += n
        return record

    def values_of(self, record: StationRecord) -> list[float]:
        """Flat value list of ``record`` in item order (the inverse of record_from_values)."""
        flat: list[float] = []
        for item, (name, _) in zip(self.value_items, self._value_slots, strict=True):
            value = getattr(record, name)
            if value is None:
                raise ValueError(f'record for station {record.station} lacks {item.name} '
                                 f'(item {item.code}) required by {self}')
            if item.count == 1:
                flat.append(value)
            else:
                if len(value) != item.count:
                    raise ValueError(f'{item.name} needs {item.count} values, got {len(value)}')
                flat.extend(value)
        return flat


# ----------------------------------------------------------------------------- encoding

def encode_binary_record(output_list: OutputList, record: StationRecord) -> bytes:
    """The F1 bytes of one station record (what the device sends)."""
    flat = output_list.values_of(record)
    packed: list[float | bytes] = []
    index = 0
    for item in output_list.items:
        if item.code == 0:
            packed.append(b' ')
        elif item.code == 1:
            packed.append(b'\r\n')
        else:
            packed.extend(flat[index:index + item.count])
            index += item.count
    header = HEADER.pack(SYNC_LIBERTY, record.station, ord(record.command), record.error, 0,
                         output_list.payload_size)
    return header + output_list.encode_struct.pack(*packed)


def encode_binary_reply(command: int, payload: bytes, station: int = 0) -> bytes:
    """An F1 reply frame to a system command (e.g. the Ctrl-U station map)."""
    return HEADER.pack(SYNC_LIBERTY, station, command, NO_ERROR, 0, len(payload)) + payload


def format_ascii_record(output_list: OutputList, record: StationRecord) -> bytes:
    """The F0 line of one station record, CR LF terminated."""
    parts = [f'{record.station:2d}{record.command}{chr(record.error)}']
    flat = output_list.values_of(record)
    index = 0
    for item in output_list.items:
        if item.code == 0:
            parts.append(' ')
        elif item.field:
            if item.ascii_format is None:
                raise ValueError(f'item {item.code} ({item.name}) has no ASCII format')
            for value in flat[index:index + item.count]:
                parts.append(item.ascii_format % value)
            index += item.count
    return (''.join(parts) + '\r\n').encode('ascii')


def decode_station_map(payload: bytes) -> tuple[set[int], set[int]]:
    """Detected and active stations from a Ctrl-U reply payload (two uint16 bit maps)."""
    detected, active = struct.unpack_from('<HH', payload)
    return ({s for s in range(1, MAX_STATIONS + 1) if detected >> (s - 1) & 1},
            {s for s in range(1, MAX_STATIONS + 1) if active >> (s - 1) & 1})


# ----------------------------------------------------------------------------- commands

CMD_CONTINUOUS = b'C\r'
CMD_SINGLE = b'P'          # no CR: the device acts on the letter; also stops continuous mode
CMD_FLUSH = b'\r'          # answered with "invalid command"; clears a half-sent command
CMD_STATION_MAP = bytes([CTRL_U]) + b'0\r'
CMD_WHOAMI = bytes([CTRL_V]) + b'\r'
CMD_RESET_COUNTERS = b'Q\r'


def cmd_format(binary: bool) -> bytes:
    return b'F1\r' if binary else b'F0\r'


def cmd_units(centimetres: bool) -> bytes:
    return b'U1\r' if centimetres else b'U0\r'


def cmd_output_list(codes: Iterable[int], station: str | int = '*') -> bytes:
    return f'O{station},{",".join(str(int(c)) for c in codes)}\r'.encode('ascii')


def cmd_hemisphere(vector: Sequence[float], station: str | int = '*') -> bytes:
    return f'H{station},{",".join(f"{float(v):g}" for v in vector)}\r'.encode('ascii')


def cmd_frame_rate(hz: int) -> bytes:
    if hz not in (120, 240):
        raise ValueError(f'frame rate {hz} Hz: the Liberty offers 120 or 240')
    return b'R3\r' if hz == 120 else b'R4\r'


def link_bytes_per_second(baud: int) -> float:
    """Payload bytes per second an 8N1 serial line carries (10 bits on the wire per byte)."""
    return baud / 10.0


# ----------------------------------------------------------------------------- parsing

@dataclass
class ParserStats:
    """Counters of a stream parser; the driver reports them in its diagnostics."""

    records: int = 0
    replies: int = 0
    bytes_in: int = 0
    bytes_dropped: int = 0
    resyncs: int = 0
    bad_lines: int = 0
    error_records: int = 0
    reasons: dict[str, int] = field(default_factory=dict)

    def drop(self, count: int, reason: str) -> None:
        if count <= 0:
            return
        self.bytes_dropped += count
        self.resyncs += 1
        self.reasons[reason] = self.reasons.get(reason, 0) + 1


class _StreamParser:
    """What both stream parsers share: the held-back bytes and the counters."""

    def __init__(self, output_list: OutputList, accept_replies: bool):
        self.output_list = output_list
        self.accept_replies = accept_replies
        self.stats = ParserStats()
        self._buffer = bytearray()

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a record or line."""
        return len(self._buffer)

    def reset(self) -> None:
        """Forget a partial record (after a port re-open or a device reset)."""
        self.stats.drop(len(self._buffer), 'reset')
        self._buffer.clear()


class _Header(NamedTuple):
    """The 8-byte binary header (``HEADER``)."""

    sync: bytes
    station: int
    command: int
    error: int
    reserved: int
    payload_size: int


class BinaryStreamParser(_StreamParser):
    """Incremental F1 parser: feed it whatever the port returned, get whole records back.

    A candidate record must have the sync bytes, a station in 1..16, a ``C`` or ``P``
    command byte, the payload size of the configured output list and, when the list ends
    with item 1, the trailing CR LF. Anything else is dropped one byte at a time until a
    candidate passes (the sliding-window resync of VRPN and libplhm). Replies to system
    commands (other command bytes) are only accepted while ``accept_replies`` is set,
    i.e. during set-up, so garbage cannot swallow good records while streaming.
    """

    def __init__(self, output_list: OutputList, accept_replies: bool = False,
                 max_buffer: int = 1 << 16):
        super().__init__(output_list, accept_replies)
        self.max_buffer = max_buffer

    def feed(self, data: bytes) -> list[StationRecord | Reply]:
        """Records and replies completed by ``data``, in stream order; an incomplete one at the
        end is held back for the next call (``pending``)."""
        self.stats.bytes_in += len(data)
        self._buffer.extend(data)
        out: list[StationRecord | Reply] = []
        pos = 0
        while True:
            pos = self._skip_to_sync(pos)
            if len(self._buffer) - pos < HEADER_SIZE:
                break   # no header yet, or no sync at all (at most a trailing 'L' is left)
            header = _Header._make(HEADER.unpack_from(self._buffer, pos))
            if header.command in DATA_COMMANDS:
                after = self._take_record(pos, header, out)
            elif self._may_be_reply(header):
                after = self._take_reply(pos, header, out)
            else:
                after = self._resync(pos, 'bad command byte')
            if after is None:
                break   # a candidate that is not complete yet
            pos = after
        del self._buffer[:pos]
        if len(self._buffer) > self.max_buffer:  # cannot happen with a sane size check; be safe
            self.stats.drop(len(self._buffer), 'overflow')
            self._buffer.clear()
        return out

    # Each step below looks at the buffer from ``pos`` and returns where the next one
    # starts, or None when the candidate there needs more bytes.

    def _skip_to_sync(self, pos: int) -> int:
        """Position of the next sync bytes at or after ``pos``, what comes before dropped.
        Without one, everything is dropped except a trailing 'L': it may be the first half of
        the next sync."""
        buffer = self._buffer
        start = buffer.find(SYNC_LIBERTY, pos)
        if start < 0:
            n = len(buffer)
            keep = 1 if n > pos and buffer[n - 1] == 0x4C else 0
            self.stats.drop(n - keep - pos, 'no sync')
            return n - keep
        if start > pos:
            self.stats.drop(start - pos, 'garbage before sync')
        return start

    def _take_record(self, pos: int, header: _Header, out: list[StationRecord | Reply]
                     ) -> int | None:
        """A data record (``C``/``P``) at ``pos``, appended to ``out`` if it passes every check
        of the class docstring; otherwise a resync."""
        layout = self.output_list
        size = layout.payload_size
        if not 1 <= header.station <= MAX_STATIONS or header.payload_size != size:
            return self._resync(pos, 'bad station' if header.payload_size == size
                                else 'bad size field')
        end = pos + layout.record_size
        if len(self._buffer) < end:
            return None
        if layout.ends_with_crlf and self._buffer[end - 2:end] != b'\r\n':
            return self._resync(pos, 'missing CR LF')
        values = layout.payload_struct.unpack_from(self._buffer, pos + HEADER_SIZE)
        out.append(layout.record_from_values(header.station, chr(header.command), header.error,
                                             values))
        if header.error != NO_ERROR:
            self.stats.error_records += 1
        self.stats.records += 1
        return end

    def _may_be_reply(self, header: _Header) -> bool:
        """A header that can start a reply to a system command: only during set-up
        (``accept_replies``), so that garbage cannot swallow good records while streaming."""
        return (self.accept_replies and header.station <= MAX_STATIONS
                and header.payload_size <= MAX_REPLY_PAYLOAD and header.command >= 0x01)

    def _take_reply(self, pos: int, header: _Header, out: list[StationRecord | Reply]
                    ) -> int | None:
        """The reply at ``pos``, appended to ``out`` once its payload is complete."""
        end = pos + HEADER_SIZE + header.payload_size
        if len(self._buffer) < end:
            return None
        out.append(Reply(command=header.command, station=header.station,
                         payload=bytes(self._buffer[pos + HEADER_SIZE:end])))
        self.stats.replies += 1
        return end

    def _resync(self, pos: int, reason: str) -> int:
        """The candidate at ``pos`` is not a record: drop its first byte and look again from
        the next one (a sync inside the rejected bytes is still found)."""
        self.stats.drop(1, reason)
        return pos + 1


_NUMBER = re.compile(rb'[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?')
_BODY = re.compile(rb'[-+.0-9eE ]*')


class AsciiStreamParser(_StreamParser):
    """Incremental F0 parser: splits CR LF lines and decodes each as one station record.

    Fields are cut at their fixed widths when the line has the expected length; otherwise
    numbers are split by sign and spacing (negative numbers may run into the previous
    field). A line that yields the wrong count of numbers or an impossible station is
    dropped and counted. Lines whose station field is 0 are replies to system commands.
    """

    def __init__(self, output_list: OutputList, accept_replies: bool = False,
                 max_line: int = 1024):
        super().__init__(output_list, accept_replies)
        self.max_line = max_line
        int_fields = {'timestamp_ms', 'frame_count', 'stylus', 'distortion', 'external_sync'}
        self._is_int = [item.field in int_fields
                        for item in output_list.value_items for _ in range(item.count)]
        self._slices: list[tuple[int, int]] = []
        offset = 4
        for item in output_list.items:
            for _ in range(item.count if item.field else 1):
                if item.field:
                    self._slices.append((offset, offset + item.ascii_width))
                offset += item.ascii_width
        self._line_length = offset

    def feed(self, data: bytes) -> list[StationRecord | Reply]:
        self.stats.bytes_in += len(data)
        self._buffer.extend(data)
        out: list[StationRecord | Reply] = []
        while True:
            end = self._buffer.find(b'\n')
            if end < 0:
                if len(self._buffer) > self.max_line:
                    self.stats.drop(len(self._buffer), 'line too long')
                    self._buffer.clear()
                break
            raw_length = end + 1
            line = bytes(self._buffer[:end])
            del self._buffer[:raw_length]
            if line.endswith(b'\r'):
                line = line[:-1]
            if not line.strip():
                continue
            parsed = self._parse_line(line)
            if parsed is None:
                self.stats.drop(raw_length, 'bad line')
                self.stats.bad_lines += 1
            else:
                out.append(parsed)
        return out

    def _parse_line(self, line: bytes) -> StationRecord | Reply | None:
        if len(line) < 4 or not line[:2].strip().isdigit():
            return None
        station = int(line[:2])
        if station == 0:
            if not self.accept_replies:
                return None
            self.stats.replies += 1
            return Reply(command=line[2], station=0, payload=line[2:])
        if station > MAX_STATIONS:
            return None
        command = chr(line[2])
        error = line[3]
        # The error field is a printable character and the body holds only numbers: a
        # line with anything else was corrupted on the way and is not guessed at.
        if command not in 'CP' or not 0x20 <= error < 0x7F or not _BODY.fullmatch(line, 4):
            return None
        if len(line) == self._line_length:
            tokens = [line[a:b] for a, b in self._slices]
        else:
            tokens = _NUMBER.findall(line, 4)
        if len(tokens) != self.output_list.value_count:
            return None
        values: list[float] = []
        try:
            for token, is_int in zip(tokens, self._is_int, strict=True):
                values.append(int(token) if is_int else float(token))
        except ValueError:
            return None
        self.stats.records += 1
        if error != NO_ERROR:
            self.stats.error_records += 1
        return self.output_list.record_from_values(station, command, error, values)


def make_stream_parser(output_list: OutputList, binary: bool, accept_replies: bool = False
                       ) -> BinaryStreamParser | AsciiStreamParser:
    """The parser for the device's current output format."""
    if binary:
        return BinaryStreamParser(output_list, accept_replies=accept_replies)
    return AsciiStreamParser(output_list, accept_replies=accept_replies)
