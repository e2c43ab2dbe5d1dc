"""Read the messages of a truncated or damaged MCAP file (a recorder that died, a copy cut
short, bytes overwritten).

rosbags needs the MCAP footer and summary to open a file, so a file cut short cannot be
opened at all, and it stops at the first record it cannot parse. MCAP is a sequence of
length-prefixed records, though: this reader walks the records in file order,
decompresses chunks (none, lz4 or zstd, as rosbag2 writes them), and at a record that does
not parse (a length past the end, a field that makes no sense) looks for the next one that
does, so only the damaged part is lost: at the top level the next record whose length
fits and is followed by another (the next chunk), and inside an uncompressed chunk the
next message record of a known channel, stamped within the chunk's time range, that is
followed by another (a bundled bag is one chunk, so skipping whole chunks alone would lose
it all). A compressed chunk that does not decompress is skipped whole. A record cut short
by the end of the file ends the walk. A chunk whose CRC is set and does not match its
records is left out whole (one CRC per chunk cannot tell which of its messages is damaged);
the messages it holds, as far as they can be listed, are in ``RecoveryReport.crc_failed``.
``RecoveryReport`` says what was skipped.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ['CrcFailedChunk', 'McapMessage', 'RecoveryReport', 'recover_mcap']

MAGIC = b'\x89MCAP0\r\n'
OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_FOOTER, OP_DATA_END = 0x03, 0x04, 0x05, 0x06, \
    0x02, 0x0F
OP_MESSAGE_INDEX = 0x07
KNOWN_OPCODES = frozenset(range(0x01, 0x10))   # header .. data end (MCAP v0)
MESSAGE_HEADER = 22                            # channel id, sequence, log and publish times
COMPRESSIONS = ('', 'lz4', 'zstd')


@dataclass
class McapMessage:
    topic: str
    msgtype: str
    log_time: int  # ns
    data: bytes


@dataclass
class CrcFailedChunk:
    """A chunk left out because its records do not match its CRC: where it is, its time
    range, and (topic, log time) of the messages in it: from the message index records that
    follow the chunk (outside it, so not damaged with it) when the file has them, else from
    the chunk's own records as far as they parse (``listed_all`` False when they do not
    all parse)."""

    offset: int
    start_ns: int
    end_ns: int
    compression: str
    messages: list[tuple[str, int]] = field(default_factory=list)
    listed_all: bool = True
    indexed: list[tuple[int, int]] = field(default_factory=list)   # (channel id, log time)

    def resolve_index(self, channels: dict[int, tuple[str, int]]) -> None:
        """Take the message index's listing (channel ids named by ``channels``)."""
        if self.indexed:
            self.messages = sorted((channels.get(channel, (f'channel {channel}', 0))[0], stamp)
                                   for channel, stamp in self.indexed)
            self.listed_all = True


@dataclass
class RecoveryReport:
    messages: int = 0
    bytes_read: int = 0
    file_size: int = 0
    complete: bool = False
    stopped_because: str = ''
    skipped: list[tuple[int, int]] = field(default_factory=list)   # (file offset, bytes)
    crc_failed: list[CrcFailedChunk] = field(default_factory=list)

    def skipped_summary(self) -> str:
        """One line: how much was skipped where ('' when nothing was)."""
        if not self.skipped:
            return ''
        places = ', '.join(f'{length} at byte {offset}' for offset, length in self.skipped[:5])
        more = f' and {len(self.skipped) - 5} more' if len(self.skipped) > 5 else ''
        return (f'{len(self.skipped)} damaged place(s), {sum(n for _, n in self.skipped)} '
                f'bytes skipped ({places}{more})')


def _string(buf: bytes, pos: int) -> tuple[str, int]:
    (length,) = struct.unpack_from('<I', buf, pos)
    end = pos + 4 + length
    if end > len(buf):
        raise ValueError('string runs past its record')
    return buf[pos + 4:end].decode('utf-8', 'replace'), end


def _decompress(data: bytes, compression: str, size: int) -> bytes:
    if compression == '':
        return data
    if compression == 'lz4':
        import lz4.frame
        return lz4.frame.decompress(data)
    if compression == 'zstd':
        try:
            from compression import zstd  # Python 3.14
        except ImportError:
            from backports import zstd
        return zstd.decompress(data)
    raise ValueError(f'unsupported chunk compression {compression!r}')


class _Walker:
    def __init__(self, report: RecoveryReport):
        self.report = report
        self.schemas: dict[int, str] = {}
        self.channels: dict[int, tuple[str, int]] = {}
        self.last_failed: CrcFailedChunk | None = None   # the chunk just read, if it failed

    def records(self, buf: bytes, pos: int, end: int, top_level: bool,
                offset: int = 0, times: tuple[int, int] | None = None) -> Iterator[McapMessage]:
        """The messages of the records in ``buf[pos:end]``. ``offset``: where ``buf`` starts
        in the file (0 at the top level; None inside a decompressed chunk, where damage is
        not looked for); ``times``: the enclosing chunk's message time range."""
        while pos < end:
            if pos + 9 > end:
                raise EOFError(f'record header cut off at byte {pos}')
            opcode = buf[pos]
            (length,) = struct.unpack_from('<Q', buf, pos + 1)
            body_start, body_end = pos + 9, pos + 9 + length
            if opcode not in KNOWN_OPCODES or (body_end > end and not self._at_file_end(
                    buf, pos, top_level)):
                pos = self._resync(buf, pos, end, top_level, offset, times)
                continue
            if body_end > end and opcode == OP_CHUNK and top_level:
                # A chunk whose length field is damaged but whose records fit: read them and
                # go on after them.
                inner_end = self._chunk_records_end(buf, body_start, end)
                if inner_end is not None:
                    self.report.skipped.append((offset + pos + 1, 0))
                    yield from self._chunk(buf[body_start:inner_end], offset + body_start)
                    pos = inner_end
                    self.report.bytes_read = pos
                    continue
            if body_end > end:
                cut = (f'record (opcode 0x{opcode:02x}) at byte {pos} needs {length} bytes, '
                       f'{end - body_start} are there')
                if opcode == OP_CHUNK and top_level:
                    # An uncompressed chunk cut short still holds whole records up to the cut.
                    yield from self._partial_chunk(buf[body_start:end], body_start)
                raise EOFError(cut)
            body = buf[body_start:body_end]
            try:
                messages = list(self._record(opcode, body, offset + body_start
                                             if offset is not None else None))
            except (ValueError, struct.error, EOFError, RuntimeError, LookupError):
                if offset is None:
                    raise
                if top_level:      # the framing holds: skip this record whole
                    self.report.skipped.append((offset + pos, body_end - pos))
                    pos = body_end
                else:
                    pos = self._resync(buf, pos, end, top_level, offset, times)
                continue
            yield from messages
            pos = body_end
            if top_level:
                self.report.bytes_read = pos
                if opcode in (OP_DATA_END, OP_FOOTER):
                    self.report.complete = True
                    return

    def _chunk_records_end(self, buf: bytes, body_start: int, end: int) -> int | None:
        """Where the records of the chunk whose body starts at ``body_start`` end, when its
        header parses and they fit in the file and something plausible follows; else None."""
        try:
            compression, pos = _string(buf[body_start:end], 28)
            (records_length,) = struct.unpack_from('<Q', buf, body_start + pos)
        except (ValueError, struct.error):
            return None
        records_end = body_start + pos + 8 + records_length
        if compression not in COMPRESSIONS or records_end > end:
            return None
        if records_end == end or self._plausible(buf, records_end, end, True, None):
            return records_end
        return None

    def _at_file_end(self, buf: bytes, pos: int, top_level: bool) -> bool:
        """A top-level record running past the end of the file is a cut, not damage, when
        its header is plausible: a chunk or message (what a recorder was writing)."""
        return top_level and buf[pos] in (OP_CHUNK, OP_MESSAGE)

    def _plausible(self, buf: bytes, pos: int, end: int, top_level: bool,
                   times: tuple[int, int] | None) -> bool:
        """Whether a record that parses starts at ``pos`` and another (or the end) follows."""
        if pos + 9 > end or buf[pos] not in KNOWN_OPCODES:
            return False
        (length,) = struct.unpack_from('<Q', buf, pos + 1)
        after = pos + 9 + length
        if after > end:
            return False
        if not top_level:
            # Inside a chunk rosbag2 writes schemas, channels and messages: a message must
            # be of a known channel and stamped within the chunk.
            if buf[pos] != OP_MESSAGE or length < MESSAGE_HEADER:
                return False
            channel, _, log_time = struct.unpack_from('<HIQ', buf, pos + 9)
            if channel not in self.channels or (times is not None and not
                                                times[0] <= log_time <= times[1]):
                return False
        elif buf[pos] == OP_CHUNK:
            try:
                compression, _ = _string(buf[pos + 9:after], 28)
            except (ValueError, struct.error):
                return False
            if compression not in COMPRESSIONS:
                return False
        return after == end or (after + 9 <= end and buf[after] in KNOWN_OPCODES)

    def _resync(self, buf: bytes, pos: int, end: int, top_level: bool, offset: int | None,
                times: tuple[int, int] | None) -> int:
        """The next position after ``pos`` where a plausible record starts (``end`` if
        none); the bytes passed over are noted as skipped."""
        if offset is None:
            raise ValueError(f'damaged record at byte {pos} of a decompressed chunk')
        start = pos
        pos += 1
        while pos < end and not self._plausible(buf, pos, end, top_level, times):
            pos += 1
        self.report.skipped.append((offset + start, pos - start))
        return pos

    def _record(self, opcode: int, body: bytes, offset: int | None) -> Iterator[McapMessage]:
        if opcode == OP_SCHEMA:
            (schema_id,) = struct.unpack_from('<H', body, 0)
            name, _ = _string(body, 2)
            self.schemas[schema_id] = name
        elif opcode == OP_CHANNEL:
            channel_id, schema_id = struct.unpack_from('<HH', body, 0)
            topic, _ = _string(body, 4)
            self.channels[channel_id] = (topic, schema_id)
        elif opcode == OP_MESSAGE:
            channel_id, _, log_time, _ = struct.unpack_from('<HIQQ', body, 0)
            topic, schema_id = self.channels.get(channel_id, ('', 0))
            if topic:
                self.report.messages += 1
                yield McapMessage(topic, self.schemas.get(schema_id, ''), log_time, body[22:])
        elif opcode == OP_CHUNK:
            yield from self._chunk(body, offset)
        elif opcode == OP_MESSAGE_INDEX and self.last_failed is not None:
            channel_id, size = struct.unpack_from('<HI', body, 0)
            if 6 + size > len(body) or size % 16:
                raise ValueError('message index runs past its record')
            self.last_failed.indexed.extend((channel_id, log_time) for log_time, _ in
                                            struct.iter_unpack('<QQ', body[6:6 + size]))

    def _partial_chunk(self, body: bytes, offset: int) -> Iterator[McapMessage]:
        try:
            start, end_time = struct.unpack_from('<QQ', body, 0)
            compression, pos = _string(body, 28)
        except (ValueError, struct.error):
            return
        if compression != '':
            return  # a compressed stream cut short cannot be decoded
        try:
            yield from self.records(body, pos + 8, len(body), top_level=False, offset=offset,
                                    times=(start, end_time))
        except (EOFError, ValueError, struct.error):
            return  # the last record is the one cut short

    def _chunk(self, body: bytes, offset: int | None) -> Iterator[McapMessage]:
        start, end_time, size, crc = struct.unpack_from('<QQQI', body, 0)
        compression, pos = _string(body, 28)
        (records_length,) = struct.unpack_from('<Q', body, pos)
        records_start = pos + 8
        if records_start + records_length > len(body):
            raise ValueError('chunk records run past the chunk')
        self.last_failed = None
        if crc and offset is not None and not self._crc_matches(
                body[records_start:records_start + records_length], compression, crc):
            self.last_failed = self._list_failed(body, records_start, records_length,
                                                 compression, offset, (start, end_time))
            self.report.crc_failed.append(self.last_failed)
            return
        if compression == '':
            # Damage inside is looked for record by record (offsets: the file's).
            yield from self.records(body, records_start, records_start + records_length,
                                    top_level=False, offset=offset, times=(start, end_time))
            return
        try:
            records = _decompress(body[records_start:records_start + records_length],
                                  compression, size)
        except Exception as error:   # zstd, lz4: each its own error type; ours: unsupported
            raise ValueError(f'chunk does not decompress: {error}') from None
        yield from self.records(records, 0, len(records), top_level=False)

    @staticmethod
    def _crc_matches(records: bytes, compression: str, crc: int) -> bool:
        try:
            raw = _decompress(records, compression, 0)
        except Exception:   # zstd, lz4: each its own error type; ours: unsupported
            return False
        return zlib.crc32(raw) == crc

    def _list_failed(self, body: bytes, records_start: int, records_length: int,
                     compression: str, offset: int, times: tuple[int, int]) -> CrcFailedChunk:
        """The chunk that failed its CRC at file offset ``offset`` (its body's), with the
        messages its records hold as far as they parse; none of them is given."""
        failed = CrcFailedChunk(offset - 9, times[0], times[1], compression)
        lister = _Walker(RecoveryReport())
        lister.schemas, lister.channels = dict(self.schemas), dict(self.channels)
        try:
            if compression == '':
                found = lister.records(body, records_start, records_start + records_length,
                                       top_level=False, offset=offset, times=times)
            else:
                records = _decompress(body[records_start:records_start + records_length],
                                      compression, 0)
                found = lister.records(records, 0, len(records), top_level=False)
            for message in found:
                failed.messages.append((message.topic, message.log_time))
        except Exception:   # damaged past listing (or not decompressing): what was listed
            failed.listed_all = False
        if lister.report.skipped:
            failed.listed_all = False
        # schemas and channels the chunk defines still name the messages of later chunks
        for channel, known in lister.channels.items():
            self.channels.setdefault(channel, known)
        for schema, name in lister.schemas.items():
            self.schemas.setdefault(schema, name)
        return failed


def recover_mcap(path: str | Path, report: RecoveryReport) -> Iterator[McapMessage]:
    """Messages of the MCAP file at ``path`` in file order, up to where it is cut.

    Fills ``report`` as it goes; never raises on a short or damaged tail (it stops there
    and says why in ``report.stopped_because``). ValueError if it is not MCAP at all.
    """
    data = Path(path).read_bytes()
    report.file_size = len(data)
    if not data.startswith(MAGIC):
        raise ValueError(f'{path}: not an MCAP file')
    walker = _Walker(report)
    try:
        yield from walker.records(data, len(MAGIC), len(data), top_level=True)
        if not report.complete:
            report.stopped_because = 'the file ends without its footer'
    except (EOFError, ValueError, struct.error) as error:
        report.stopped_because = str(error)
    if any(chunk.indexed for chunk in report.crc_failed):
        _summary_channels(data, report.bytes_read, walker.channels)
        for chunk in report.crc_failed:
            chunk.resolve_index(walker.channels)


def _summary_channels(data: bytes, pos: int, channels: dict[int, tuple[str, int]]) -> None:
    """Channels of the summary section after ``pos`` (the data section's end) that the
    data section did not define (e.g. only inside a chunk that failed its CRC)."""
    while pos + 9 <= len(data):
        opcode = data[pos]
        (length,) = struct.unpack_from('<Q', data, pos + 1)
        if opcode not in KNOWN_OPCODES or pos + 9 + length > len(data):
            return
        if opcode == OP_CHANNEL:
            try:
                channel_id, schema_id = struct.unpack_from('<HH', data, pos + 9)
                topic, _ = _string(data[pos + 9:pos + 9 + length], 4)
            except (ValueError, struct.error):
                return
            channels.setdefault(channel_id, (topic, schema_id))
        if opcode == OP_FOOTER:
            return
        pos += 9 + length
