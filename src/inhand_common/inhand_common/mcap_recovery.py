"""Read the messages of a truncated MCAP file (a recorder that died, a copy cut short).

rosbags needs the MCAP footer and summary to open a file, so a file cut short cannot be
opened at all. MCAP is a sequence of length-prefixed records, though, so everything before
the cut is readable: this reader walks the records in file order, decompresses chunks
(none, lz4 or zstd, as rosbag2 writes them), and stops cleanly at the first incomplete
record, saying where and why.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

__all__ = ['McapMessage', 'RecoveryReport', 'recover_mcap']

MAGIC = b'\x89MCAP0\r\n'
OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_FOOTER, OP_DATA_END = 0x03, 0x04, 0x05, 0x06, \
    0x02, 0x0F


@dataclass
class McapMessage:
    topic: str
    msgtype: str
    log_time: int  # ns
    data: bytes


@dataclass
class RecoveryReport:
    messages: int = 0
    bytes_read: int = 0
    file_size: int = 0
    complete: bool = False
    stopped_because: str = ''


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

    def records(self, buf: bytes, pos: int, end: int, top_level: bool) -> Iterator[McapMessage]:
        while pos < end:
            if pos + 9 > end:
                raise EOFError(f'record header cut off at byte {pos}')
            opcode = buf[pos]
            (length,) = struct.unpack_from('<Q', buf, pos + 1)
            body_start, body_end = pos + 9, pos + 9 + length
            if body_end > end:
                cut = (f'record (opcode 0x{opcode:02x}) at byte {pos} needs {length} bytes, '
                       f'{end - body_start} are there')
                if opcode == OP_CHUNK and top_level:
                    # An uncompressed chunk cut short still holds whole records up to the cut.
                    yield from self._partial_chunk(buf[body_start:end])
                raise EOFError(cut)
            body = buf[body_start:body_end]
            yield from self._record(opcode, body)
            pos = body_end
            if top_level:
                self.report.bytes_read = pos
                if opcode in (OP_DATA_END, OP_FOOTER):
                    self.report.complete = True
                    return

    def _record(self, opcode: int, body: bytes) -> Iterator[McapMessage]:
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
            yield from self._chunk(body)

    def _partial_chunk(self, body: bytes) -> Iterator[McapMessage]:
        try:
            compression, pos = _string(body, 28)
        except (ValueError, struct.error):
            return
        if compression != '':
            return  # a compressed stream cut short cannot be decoded
        try:
            yield from self.records(body, pos + 8, len(body), top_level=False)
        except (EOFError, ValueError, struct.error):
            return  # the last record is the one cut short

    def _chunk(self, body: bytes) -> Iterator[McapMessage]:
        _, _, size, _ = struct.unpack_from('<QQQI', body, 0)
        compression, pos = _string(body, 28)
        (records_length,) = struct.unpack_from('<Q', body, pos)
        records = _decompress(body[pos + 8:pos + 8 + records_length], compression, size)
        yield from self.records(records, 0, len(records), top_level=False)


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
