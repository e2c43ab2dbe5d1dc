"""Check the CRCs an MCAP file carries, and a sqlite3 bag's page structure: damage inside
the messages must not be read without a word.

MCAP has two: each Chunk record's ``uncompressed_crc`` (CRC-32 of the chunk's records after
decompression; 0 = not set) and the DataEnd record's ``data_section_crc`` (CRC-32 of the
file from its magic to the end of the data section; 0 = not set). rosbags checks a chunk's
CRC when it reads that chunk and then stops reading with an error; it never checks the data
section's. :func:`check_mcap` checks both up front, in one pass over the file mapped into
memory (zlib's CRC-32 over memoryviews, no copies for uncompressed chunks; compressed ones
are decompressed as rosbags would): a few hundred milliseconds for a 100 MB file.

Not every writer sets them: ``ros2 bag record`` (the mcap storage plugin) writes chunk CRCs;
rosbags' writer writes none, and damage inside a message of such a bag cannot be detected.
:func:`stamp_crcs` writes both into an existing file in place: ``bag_record`` and the
simulated sessions (with them the bundled bags) call it when their bag is closed.

sqlite3 bags have no checksums at all: :func:`check_sqlite3` runs ``PRAGMA quick_check``,
which finds a damaged page structure (b-tree pages, cell pointers, overflow chains, the
free list), not changed bytes inside a message's data.

No rclpy, no rosbags: a plain module.
"""

from __future__ import annotations

import mmap
import os
import sqlite3
import struct
import time
import zlib
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ['McapIntegrity', 'SqliteIntegrity', 'check_mcap', 'check_sqlite3', 'describe_messages',
           'stamp_bag_crcs', 'stamp_crcs']

MAGIC = b'\x89MCAP0\r\n'
OP_FOOTER, OP_CHUNK, OP_DATA_END = 0x02, 0x06, 0x0F
# the spec's records, and the range it leaves to private records (skipped like any other)
KNOWN_OPCODES = frozenset(range(0x01, 0x10)) | frozenset(range(0x80, 0x100))
CHUNK_FIXED = 28   # message start and end time, uncompressed size, uncompressed CRC


@dataclass
class BadChunk:
    offset: int          # file offset of the chunk record (its opcode)
    start_ns: int        # the chunk's message time range, from its header
    end_ns: int
    compression: str
    reason: str          # 'CRC mismatch', 'does not decompress: ...', ...


@dataclass
class McapIntegrity:
    """What :func:`check_mcap` found. ``data_crc``: 'match', 'mismatch', 'not set' or
    'not reached' (no DataEnd record: a file cut short, or framing damage before it)."""

    path: Path
    chunks: int = 0
    chunks_with_crc: int = 0
    bad_chunks: list[BadChunk] = field(default_factory=list)
    data_crc: str = 'not reached'
    stopped: str | None = None    # why the walk over the records stopped early
    seconds: float = 0.0

    @property
    def data_section_only(self) -> bool:
        """The data section CRC fails while every chunk CRC passes: damage outside chunks."""
        return self.data_crc == 'mismatch' and not self.bad_chunks

    @property
    def damaged(self) -> bool:
        return bool(self.bad_chunks) or self.data_crc == 'mismatch'

    def checked(self) -> str:
        """One line: what could be checked and what it showed."""
        if not self.chunks_with_crc and self.data_crc != 'match' and self.data_crc != 'mismatch':
            return ('no CRCs in this MCAP file (its writer set none): damage inside messages '
                    'cannot be detected')
        parts = [f'{self.chunks_with_crc - len(self.bad_chunks)} of {self.chunks_with_crc} '
                 'chunk CRCs match' if self.chunks_with_crc else 'no chunk CRCs',
                 f'data section CRC: {self.data_crc}']
        return '; '.join(parts)

    def data_section_said(self) -> str:
        """One line for a data section CRC that fails (without chunk damage to explain it)."""
        if self.chunks_with_crc == self.chunks and self.chunks:
            return (f'the data section CRC does not match although all {self.chunks} chunk '
                    'CRCs do: damage outside the chunks (a header, schema, channel, index or '
                    'metadata record, or between chunks); the messages themselves check out')
        if self.chunks_with_crc:
            return (f'the data section CRC does not match; the {self.chunks_with_crc} chunks '
                    f'with a CRC check out, the other {self.chunks - self.chunks_with_crc} '
                    'have none: their messages may be damaged')
        return ('the data section CRC does not match and the chunks carry no CRCs to tell '
                'where: any message may be damaged')


def _decompress(data: memoryview, compression: str) -> bytes:
    if compression == 'lz4':
        import lz4.frame  # type: ignore[import-untyped]
        return bytes(lz4.frame.decompress(data))
    if compression == 'zstd':
        try:
            from compression import zstd  # type: ignore[import-not-found]  # Python 3.14
        except ImportError:
            from backports import zstd  # type: ignore[import-not-found,no-redef,unused-ignore]
        return bytes(zstd.decompress(data))
    raise ValueError(f'unsupported chunk compression {compression!r}')


def _chunk_crc(view: memoryview, body: int, body_end: int) -> tuple[int, int, int, int, str,
                                                                     memoryview]:
    """(start, end, uncompressed size, CRC, compression, records) of the chunk whose body
    spans ``view[body:body_end]``. ValueError / struct.error if its header does not parse."""
    start, end, size, crc = struct.unpack_from('<QQQI', view, body)
    (name_length,) = struct.unpack_from('<I', view, body + CHUNK_FIXED)
    name_end = body + CHUNK_FIXED + 4 + name_length
    if name_end + 8 > body_end:
        raise ValueError('chunk header runs past the chunk')
    compression = bytes(view[body + CHUNK_FIXED + 4:name_end]).decode('utf-8', 'replace')
    (records_length,) = struct.unpack_from('<Q', view, name_end)
    records_start = name_end + 8
    if records_start + records_length > body_end:
        raise ValueError('chunk records run past the chunk')
    return start, end, size, crc, compression, view[records_start:records_start + records_length]


def _check_chunk(records: memoryview, compression: str, size: int, crc: int) -> str | None:
    """Why the chunk's records fail their CRC (None if they pass)."""
    if compression == '':
        if len(records) != size:
            return f'records are {len(records)} bytes, its header says {size}'
        return None if zlib.crc32(records) == crc else 'CRC mismatch'
    try:
        raw = _decompress(records, compression)
    except Exception as error:   # zstd, lz4: each its own error type; ours: unsupported
        return f'does not decompress ({compression}: {error})'
    if len(raw) != size:
        return f'decompresses to {len(raw)} bytes, its header says {size}'
    return None if zlib.crc32(raw) == crc else 'CRC mismatch'


def _walk(view: memoryview, report: McapIntegrity, stamp: bytearray | None = None) -> None:
    """The top-level records of the data section; fills ``report`` (and, with ``stamp``, a
    copy of the file, writes the CRCs into it)."""
    size = len(view)
    pos = len(MAGIC)
    while pos + 9 <= size:
        opcode = view[pos]
        (length,) = struct.unpack_from('<Q', view, pos + 1)
        body, body_end = pos + 9, pos + 9 + length
        if opcode not in KNOWN_OPCODES or body_end > size:
            report.stopped = (f'the record at byte {pos} does not parse'
                              if opcode not in KNOWN_OPCODES else
                              f'the record at byte {pos} runs past the end of the file')
            return
        if opcode == OP_CHUNK:
            report.chunks += 1
            try:
                start, end, chunk_size, crc, compression, records = _chunk_crc(view, body,
                                                                               body_end)
            except (ValueError, struct.error) as error:
                report.stopped = f'the chunk at byte {pos} does not parse: {error}'
                return
            if stamp is not None:
                raw = records if compression == '' else _decompress(records, compression)
                struct.pack_into('<I', stamp, body + 24, zlib.crc32(raw))
            elif crc:
                report.chunks_with_crc += 1
                reason = _check_chunk(records, compression, chunk_size, crc)
                if reason is not None:
                    report.bad_chunks.append(BadChunk(pos, start, end, compression, reason))
        elif opcode == OP_DATA_END:
            if length < 4:
                report.stopped = f'the DataEnd record at byte {pos} is too short'
                return
            if stamp is not None:
                struct.pack_into('<I', stamp, body, zlib.crc32(stamp[:pos]))
                return
            (crc,) = struct.unpack_from('<I', view, body)
            if not crc:
                report.data_crc = 'not set'
            elif zlib.crc32(view[:pos]) == crc or zlib.crc32(view[len(MAGIC):pos]) == crc:
                # the spec's "all bytes in the data section": with the leading magic as the
                # reference writers compute it, or without it
                report.data_crc = 'match'
            else:
                report.data_crc = 'mismatch'
            return
        elif opcode == OP_FOOTER:
            return   # a file without a DataEnd record
        pos = body_end
    report.stopped = 'the file ends before its DataEnd record'


def check_mcap(path: str | Path) -> McapIntegrity:
    """Check every chunk CRC and the data section CRC of the MCAP file at ``path``.

    ValueError if it is not an MCAP file; OSError if it cannot be read. Damage that breaks
    the record framing stops the walk (``stopped``): the chunks after it are not checked.
    """
    started = time.perf_counter()
    report = McapIntegrity(Path(path))
    with open(path, 'rb') as file:
        if file.read(len(MAGIC)) != MAGIC:
            raise ValueError(f'{path}: not an MCAP file')
        with mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
            view = memoryview(mapped)
            try:
                _walk(view, report)
            finally:
                view.release()
    report.seconds = time.perf_counter() - started
    return report


def stamp_bag_crcs(bag: str | Path) -> None:
    """:func:`stamp_crcs` on every MCAP file of a rosbag2 bag folder (or an .mcap file)."""
    bag = Path(bag)
    for path in [bag] if bag.is_file() else sorted(bag.glob('*.mcap')):
        stamp_crcs(path)


def stamp_crcs(path: str | Path) -> None:
    """Write every chunk's CRC and the data section CRC into the MCAP file at ``path``, as
    ``ros2 bag record`` would have (for a file rosbags wrote, which has none). The file
    must be whole (a DataEnd record)."""
    original = Path(path).read_bytes()
    if not original.startswith(MAGIC):
        raise ValueError(f'{path}: not an MCAP file')
    data = bytearray(original)
    report = McapIntegrity(Path(path))
    _walk(memoryview(original), report, stamp=data)
    if report.stopped:
        raise ValueError(f'{path}: {report.stopped}')
    # Only the CRC fields change, written in place: a crash half way leaves some CRCs set
    # and the others 0 (not checked), never a wrong one or a half-written file.
    changed = np.flatnonzero(np.frombuffer(original, np.uint8) != np.frombuffer(data, np.uint8))
    with open(path, 'r+b') as file:
        for start in changed[np.r_[True, np.diff(changed) > 4]] if len(changed) else ():
            file.seek(int(start))
            file.write(data[int(start):int(start) + 4])
        file.flush()
        os.fsync(file.fileno())


def _seconds(ns: int, start_ns: int) -> str:
    return f'{(ns - start_ns) * 1e-9:.2f}'


def describe_messages(messages: Iterable[tuple[str, int]], start_ns: int) -> str:
    """'topic: N messages at T s; ...' (or 'from T0 to T1 s') of (topic, log time ns) pairs,
    times relative to ``start_ns``; topics sorted."""
    times: dict[str, list[int]] = {}
    for topic, log_time in messages:
        times.setdefault(topic.lstrip('/'), []).append(log_time)
    parts = []
    for topic in sorted(times):
        stamps = times[topic]
        first, last = min(stamps), max(stamps)
        count = f'{len(stamps)} message{"s" if len(stamps) != 1 else ""}'
        when = (f'at {_seconds(first, start_ns)} s' if first == last else
                f'from {_seconds(first, start_ns)} to {_seconds(last, start_ns)} s')
        parts.append(f'{topic}: {count} {when}')
    return '; '.join(parts)


@dataclass
class SqliteIntegrity:
    path: Path
    findings: list[str] = field(default_factory=list)   # empty: quick_check said ok
    capped: bool = False     # quick_check stopped at its limit of findings
    seconds: float = 0.0

    @property
    def damaged(self) -> bool:
        return bool(self.findings)

    def said(self) -> str:
        """One line for a database that fails the check."""
        more = (f' (and {len(self.findings) - 1}{" or more" if self.capped else ""} more '
                'finding(s))' if len(self.findings) > 1 else '')
        return (f'{self.path.name} fails sqlite3 quick_check: {self.findings[0]}{more}; sqlite3 '
                'keeps no checksum per message, so which messages are damaged cannot be told')


def check_sqlite3(path: str | Path, limit: int = 20) -> SqliteIntegrity:
    """``PRAGMA quick_check`` of the sqlite3 database at ``path``, opened read-only (at most
    ``limit`` findings). What sqlite3 itself refuses to open counts as one finding."""
    started = time.perf_counter()
    report = SqliteIntegrity(Path(path))
    try:
        connection = sqlite3.connect(f'{Path(path).resolve().as_uri()}?mode=ro', uri=True)
        try:
            rows = connection.execute(f'PRAGMA quick_check({int(limit)})').fetchall()
        finally:
            connection.close()
    except sqlite3.Error as error:
        report.findings = [f'{type(error).__name__}: {error}']
    else:
        # one row per finding, though some builds give one row of lines
        found = [line.strip() for row in rows for line in str(row[0]).splitlines()]
        found = [line for line in found if line and not line.startswith('***')]
        report.findings = [] if found == ['ok'] else found
        report.capped = len(found) >= limit
    report.seconds = time.perf_counter() - started
    return report
