"""Open any rosbag2 bag, list its topics, iterate its raw messages; a progress line.

No rclpy here, so bag checks run before the ROS runtime loads; used by ``build_map``,
``map_metrics`` and the bag tools alike.

``BagSource`` opens MCAP and sqlite3 bags with rosbags (a bag folder, or a bare ``.mcap`` /
``.db3`` file). An MCAP file that rosbags cannot open because it was cut short (a recorder
that died, a copy that stopped), or that it stops reading at a damaged record, is read
record by record with :mod:`inhand_common.mcap_recovery`, which skips only the damaged
parts; ``problem`` says what was read and skipped, in one line.

Damage inside the messages is looked for on open (:mod:`inhand_common.mcap_integrity`):
the CRC of every MCAP chunk and of the data section, where the writer set them, and
``PRAGMA quick_check`` of a sqlite3 database. The messages of a chunk whose CRC fails are
left out (one CRC per chunk cannot tell which of them is damaged), and ``problem`` names
them in one line: topics, message count per topic and time span (seconds into the bag).
``checked`` says what could be checked (an MCAP file without CRCs: nothing).
"""

from __future__ import annotations

import sqlite3
import struct
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from inhand_common.mcap_recovery import RecoveryReport

__all__ = ['BagError', 'BagSource', 'BagTopic', 'Progress', 'relative_name']


class BagError(ValueError):
    """A bag that cannot be used, with a message for the user."""


@cache
def _read_errors() -> tuple[type[BaseException], ...]:
    """What opening or reading a file that is not a bag, or a damaged one, raises: rosbags'
    own errors, the file system's, and what surfaces from below rosbags' checks: a record cut
    short (struct, EOF), a length field past the end (Overflow), a compressed chunk that does
    not decompress (zstd, lz4's RuntimeError). Imported on first use: rosbags is slow to
    import, and the commands check their arguments before they open a bag."""
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Rosbag1ReaderError
    from rosbags.rosbag2 import ReaderError as Rosbag2ReaderError
    try:
        from compression import zstd  # type: ignore[import-not-found]  # Python 3.14
    except ImportError:
        from backports import zstd
    # a damaged sqlite3 page met while reading: rosbags reads sqlite3 bags through apsw
    import apsw
    return (AnyReaderError, Rosbag1ReaderError, Rosbag2ReaderError, OSError, struct.error,
            EOFError, OverflowError, ValueError, RuntimeError, zstd.ZstdError, apsw.Error,
            sqlite3.DatabaseError)


def relative_name(topic: str) -> str:
    """The topic without its leading '/': relative, so namespaces and remapping apply."""
    return topic.lstrip('/')


@dataclass
class BagTopic:
    """One topic of a bag. ``qos`` is the recorded offered QoS (rosbags ``Qos``), maybe []."""

    name: str  # relative
    msgtype: str
    count: int = 0
    qos: list = field(default_factory=list)
    connections: list = field(default_factory=list)


class BagSource:
    """The topics and raw messages of a bag, in time order; ``problem`` if it is damaged.

    Use as a context manager. ``messages()`` can be called again (``--loop``).
    """

    def __init__(self, bag: Path):
        self.bag = Path(bag)
        self.topics: dict[str, BagTopic] = {}
        self.start_ns = 0
        self.end_ns = 0
        self.problem: str | None = None
        self.checked: list[str] = []   # what the integrity check could check, per file
        self._opened_problem: str | None = None
        self._reader: Any = None
        self._recovered: list[tuple[str, int, bytes]] | None = None

    def __enter__(self) -> BagSource:
        if not self.bag.exists():
            raise BagError(f'{self.bag}: no such bag')
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
        try:
            self._reader = AnyReader([self.bag], default_typestore=get_typestore(
                Stores.ROS2_JAZZY))
            self._reader.open()
        except _read_errors() as error:
            self._reader = None
            self._recover(error)
            self._opened_problem = self.problem
            return self
        for connection in self._reader.connections:
            name = relative_name(connection.topic)
            topic = self.topics.setdefault(name, BagTopic(name, connection.msgtype))
            if connection.msgtype != topic.msgtype:
                raise BagError(f'{self.bag}: topic {connection.topic} has two types, '
                               f'{topic.msgtype} and {connection.msgtype}')
            topic.count += connection.msgcount
            topic.qos.extend(getattr(connection.ext, 'offered_qos_profiles', None) or [])
            topic.connections.append(connection)
        if any(t.count for t in self.topics.values()):
            self.start_ns, self.end_ns = self._reader.start_time, self._reader.end_time
            # rosbags' end_time is one past the last message
            self.end_ns = max(self.start_ns, self.end_ns - 1)
        self._check_integrity()
        self._opened_problem = self.problem
        return self

    def _storage_files(self, suffix: str) -> list[Path]:
        if self.bag.is_file():
            return [self.bag] if self.bag.suffix == suffix else []
        return sorted(self.bag.glob(f'*{suffix}'))

    def _add_problem(self, said: str) -> None:
        self.problem = said if not self.problem else f'{self.problem}; {said}'

    def _check_integrity(self) -> None:
        """After rosbags opened the bag: the CRCs of its MCAP files and the page structure
        of its sqlite3 databases. A chunk that fails its CRC: its messages are left out
        (the bag is then read record by record) and ``problem`` names them."""
        from inhand_common.mcap_integrity import check_mcap, check_sqlite3
        crc_failed = False
        for path in self._storage_files('.mcap'):
            try:
                report = check_mcap(path)
            except (OSError, ValueError):
                continue    # rosbags read it; reading it will say what is wrong
            self.checked.append(f'{path.name}: {report.checked()}')
            if report.bad_chunks:
                crc_failed = True
            elif report.data_crc == 'mismatch':
                self._add_problem(f'{path.name}: {report.data_section_said()}')
            if report.stopped:   # rosbags reads through the summary; the records break
                self._add_problem(f'{path.name}: {report.stopped}; the data section after it '
                                  'is not checked')
        for path in self._storage_files('.db3'):
            sqlite = check_sqlite3(path)
            self.checked.append(f'{path.name}: sqlite3 quick_check '
                                f'{"fails" if sqlite.damaged else "ok"}')
            if sqlite.damaged:
                self._add_problem(sqlite.said())
        if not crc_failed:
            return
        mcap = self._mcap_file()
        if mcap is None:   # more than one file: rosbags stops at the damaged chunk
            self._add_problem('a chunk fails its CRC; more than one MCAP file, so '
                              'the messages after it are not read')
            return
        messages, recovery = self._read_record_by_record(mcap)
        for topic in self.topics.values():
            topic.count = 0
        for name, _, _, msgtype in messages:
            self.topics.setdefault(name, BagTopic(name, msgtype)).count += 1
        self._recovered = [(name, log_time, data) for name, log_time, data, _ in messages]
        self._reader.close()
        self._reader = None
        said = self._crc_failed_said(recovery)
        if not recovery.complete or recovery.skipped:
            said += f'; {self._recovery_said(recovery, len(messages))}'
        self._add_problem(said)

    def _mcap_file(self) -> Path | None:
        if self.bag.suffix == '.mcap' and self.bag.is_file():
            return self.bag
        found = sorted(self.bag.glob('*.mcap')) if self.bag.is_dir() else []
        return found[0] if len(found) == 1 else None

    def _recover(self, error: Exception) -> None:
        refused = f'{self.bag}: cannot open as a rosbag2 bag (MCAP or sqlite3): {error}'
        from inhand_common.mcap_integrity import check_sqlite3
        for database in self._storage_files('.db3'):
            sqlite = check_sqlite3(database)
            if sqlite.damaged:
                refused += f' ({sqlite.said()})'
        mcap = self._mcap_file()
        if mcap is None:
            raise BagError(refused) from None
        try:
            messages, report = self._read_record_by_record(mcap)
        except ValueError as not_mcap:
            raise BagError(f'{refused} ({not_mcap})') from None
        if not messages and not report.complete:
            raise BagError(f'{refused} (no whole message in its first {report.bytes_read} '
                           'bytes)') from None
        for name, _, _, msgtype in messages:
            topic = self.topics.setdefault(name, BagTopic(name, msgtype))
            topic.count += 1
        self._recovered = [(name, log_time, data) for name, log_time, data, _ in messages]
        if messages:
            self.start_ns, self.end_ns = messages[0][1], messages[-1][1]
        if report.crc_failed:
            first = min(chunk.start_ns for chunk in report.crc_failed)
            self.start_ns = min(self.start_ns, first) if messages else first
            self.end_ns = max(self.end_ns, max(chunk.end_ns for chunk in report.crc_failed))
        if not report.complete or report.skipped:
            self.problem = (f'{str(error).rstrip(".")}; '
                            f'{self._recovery_said(report, len(messages))}, recorded QoS '
                            'is not')
        if report.crc_failed:
            self._add_problem(self._crc_failed_said(report))

    def _crc_failed_said(self, report: RecoveryReport) -> str:
        """One line: the chunks that failed their CRC and the messages left out with them
        (topic: count and time span, seconds into the bag)."""
        from inhand_common.mcap_integrity import describe_messages
        chunks = report.crc_failed
        listed = [m for chunk in chunks for m in chunk.messages]
        every = all(chunk.listed_all for chunk in chunks)
        where = ', '.join(f'byte {chunk.offset}' for chunk in chunks[:5]) + \
            (f' and {len(chunks) - 5} more' if len(chunks) > 5 else '')
        said = (f'{len(chunks)} chunk{"s" if len(chunks) != 1 else ""} '
                f'fail{"s" if len(chunks) == 1 else ""} {"its" if len(chunks) == 1 else "their"}'
                f' CRC (at {where}); left out {"" if every else "at least "}{len(listed)} '
                f'message{"s" if len(listed) != 1 else ""}')
        if listed:
            said += f': {describe_messages(listed, self.start_ns)}'
        unlisted = [chunk for chunk in chunks if not chunk.listed_all]
        if unlisted:
            said += ' (and what else ' + ', '.join(
                f'the chunk at byte {chunk.offset} held from '
                f'{(chunk.start_ns - self.start_ns) * 1e-9:.2f} to '
                f'{(chunk.end_ns - self.start_ns) * 1e-9:.2f} s' for chunk in unlisted[:3]) + \
                ': too damaged to list)'
        return said

    @staticmethod
    def _read_record_by_record(mcap: Path) -> tuple[list[tuple[str, int, bytes, str]],
                                                     RecoveryReport]:
        """(relative topic, log time, data, type) of every readable message in time order,
        and the RecoveryReport. ValueError if the file is not MCAP."""
        from inhand_common.mcap_recovery import RecoveryReport, recover_mcap
        report = RecoveryReport()
        messages = [(relative_name(m.topic), m.log_time, m.data, m.msgtype)
                    for m in recover_mcap(mcap, report)]
        messages.sort(key=lambda m: m[1])  # file order is time order for rosbag2
        return messages, report

    @staticmethod
    def _recovery_said(report, messages: int) -> str:
        said = 'read the file record by record'
        if not report.complete:
            said += (f' up to byte {report.bytes_read} of {report.file_size} '
                     f'({report.stopped_because or "end of data"})')
        said += f': {messages} messages are readable'
        if report.skipped:
            said += f'; {report.skipped_summary()}'
        return said

    @property
    def duration(self) -> float:
        return (self.end_ns - self.start_ns) * 1e-9

    def messages(self, topics: set[str], start_ns: int | None = None
                 ) -> Iterator[tuple[str, int, bytes]]:
        """(relative topic, log time ns, raw CDR bytes) of ``topics`` in time order."""
        if self._recovered is not None:
            for item in self._recovered:
                if item[0] in topics and (start_ns is None or item[1] >= start_ns):
                    yield item
            return
        connections = [c for name in sorted(topics) for c in self.topics[name].connections]
        if not connections:
            return
        last, at_last = None, 0   # the last stamp given and how many had it
        given = 0
        try:
            for connection, timestamp, raw in self._reader.messages(connections=connections,
                                                                    start=start_ns):
                at_last = at_last + 1 if timestamp == last else 1
                last = timestamp
                given += 1
                yield relative_name(connection.topic), timestamp, raw
        except _read_errors() as error:  # a damaged bag: the rest, record by record
            yield from self._rest_record_by_record(error, topics, start_ns, last, at_last)
            return
        listed = sum(c.msgcount for c in connections)
        if start_ns is None and given < listed:
            # Damage rosbags did not notice: it ended the chunk early.
            yield from self._rest_record_by_record(
                EOFError(f'{given} of the {listed} messages its summary lists were read'),
                topics, start_ns, last, at_last)

    def _rest_record_by_record(self, error: BaseException, topics: set[str],
                               start_ns: int | None, last: int | None, at_last: int
                               ) -> Iterator[tuple[str, int, bytes]]:
        """After rosbags stopped at a damaged record: the messages after the ones given
        (stamps above ``last``, and those at ``last`` past the first ``at_last``)."""
        problem = f'{type(error).__name__}: {error}'
        self.problem = self._opened_problem   # what opening found, then this pass's
        mcap = self._mcap_file()
        if mcap is None:
            self._add_problem(problem)
            return
        try:
            messages, report = self._read_record_by_record(mcap)
        except ValueError:
            self._add_problem(problem)
            return
        wanted = [m for m in messages if m[0] in topics and (start_ns is None or m[1] >= start_ns)]
        self._add_problem(f'{problem}; {self._recovery_said(report, len(wanted))}')
        if report.crc_failed:
            self._add_problem(self._crc_failed_said(report))
        seen_at_last = 0
        for name, log_time, data, _ in wanted:
            if last is not None and log_time < last:
                continue
            if log_time == last and seen_at_last < at_last:
                seen_at_last += 1
                continue
            yield name, log_time, data

    def __exit__(self, *exc) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None


class Progress:
    """A progress line on stderr: redrawn in place on a terminal, every 10% otherwise.

    Shows the time into the bag, the percentage, messages and the achieved rate.
    """

    def __init__(self, prog: str, start_ns: int, end_ns: int, stream=None, prefix: str = ''):
        self.prog, self.prefix = prog, prefix
        self.start_ns, self.span = start_ns, max(end_ns - start_ns, 1)
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty()
        self._last_decile = -1
        self._last_draw = 0.0
        self._drawn = False
        self._last_messages = -1

    def update(self, bag_ns: int, messages: int, first_ns: int, wall: float,
               force: bool = False, pass_messages: int | None = None) -> None:
        """At bag time ``bag_ns``, ``messages`` published in all; this pass started at bag
        time ``first_ns`` ``wall`` seconds ago and has published ``pass_messages``."""
        fraction = min(max((bag_ns - self.start_ns) / self.span, 0.0), 1.0)
        # the last decile is left to the final forced line (messages sharing the last stamp)
        decile = min(int(fraction * 10 + 1e-9), 9)
        now = time.monotonic()
        if self.tty:
            if not force and now - self._last_draw < 0.1:
                return
        elif (decile <= self._last_decile and not force) or messages == self._last_messages:
            return
        self._last_draw, self._last_decile, self._last_messages = now, decile, messages
        played = (bag_ns - first_ns) * 1e-9
        measured = wall >= 0.05
        factor = f'{played / wall:6.2f}x' if measured else '     - '
        done = messages if pass_messages is None else pass_messages
        rate = f'{done / wall:>9,.0f}' if measured else '        -'
        line = (f'{self.prog}: {self.prefix}{(bag_ns - self.start_ns) * 1e-9:8.2f} / '
                f'{self.span * 1e-9:.2f} s [{"#" * int(fraction * 20):<20}] {fraction:6.1%} '
                f'{messages:>9,} msgs {rate} msg/s {factor} real time')
        if self.tty:
            self.stream.write('\r' + line)
            self._drawn = True
        else:
            self.stream.write(line + '\n')
        self.stream.flush()

    def close(self) -> None:
        if self.tty and self._drawn:
            self.stream.write('\n')
            self.stream.flush()
            self._drawn = False
