"""Group station records into tracker frames and count the frames the host never saw.

The Liberty sends every enabled station once per frame, back to back. A frame is complete
when every expected station has arrived; a record that belongs to another frame (a new
frame counter, or station numbers starting over when the list has no counter) closes the
current one early, and it is published with the stations it has (counted incomplete).

Dropped frames come from the device's frame counter (item 9) when the output list has it,
otherwise from gaps in its millisecond timestamp (item 8); without either they cannot be
detected, which the driver's diagnostics say.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from polhemus_liberty.protocol import StationRecord

__all__ = ['Frame', 'FrameAssembler', 'FrameCounters']


@dataclass
class Frame:
    """The records of one tracker frame and the host time its first byte arrived."""

    receipt_time: float
    frame_count: int | None
    timestamp_ms: int | None
    records: dict[int, StationRecord] = field(default_factory=dict)


@dataclass
class FrameCounters:
    frames: int = 0
    dropped: int = 0
    incomplete: int = 0
    counter_resets: int = 0
    unmapped_records: int = 0


class FrameAssembler:
    def __init__(self, expected_stations, frame_rate: float):
        self.expected = frozenset(expected_stations)
        self.period_ms = 1000.0 / frame_rate
        self.counters = FrameCounters()
        self._current: Frame | None = None
        self._last_count: int | None = None
        self._last_timestamp: int | None = None

    def add(self, record: StationRecord, receipt_time: float) -> list[Frame]:
        """Take one record; returns the frames it completed (zero, one or two)."""
        if record.station not in self.expected:
            self.counters.unmapped_records += 1
            return []
        done: list[Frame] = []
        current = self._current
        if current is not None and self._starts_new_frame(current, record):
            done.append(self._close())
            current = None
        if current is None:
            current = self._current = Frame(receipt_time, record.frame_count, record.timestamp_ms)
        current.records[record.station] = record
        if len(current.records) == len(self.expected):
            done.append(self._close())
        return done

    def flush(self) -> Frame | None:
        """Close a partial frame (the stream went quiet or the port closed)."""
        return self._close() if self._current is not None else None

    def restart(self) -> None:
        """Forget the counter baseline (after a device reset or reconnection)."""
        self._current = None
        self._last_count = None
        self._last_timestamp = None

    @staticmethod
    def _starts_new_frame(current: Frame, record: StationRecord) -> bool:
        if record.frame_count is not None and current.frame_count is not None:
            return record.frame_count != current.frame_count
        if record.timestamp_ms is not None and current.timestamp_ms is not None and \
                record.timestamp_ms != current.timestamp_ms:
            return True
        return record.station in current.records or record.station < max(current.records)

    def _close(self) -> Frame:
        frame = self._current
        self._current = None
        counters = self.counters
        counters.frames += 1
        if len(frame.records) < len(self.expected):
            counters.incomplete += 1
        if frame.frame_count is not None:
            if self._last_count is not None:
                gap = frame.frame_count - self._last_count
                if gap > 1:
                    counters.dropped += gap - 1
                elif gap <= 0:
                    counters.counter_resets += 1
            self._last_count = frame.frame_count
        elif frame.timestamp_ms is not None:
            if self._last_timestamp is not None:
                gap = (frame.timestamp_ms - self._last_timestamp) / self.period_ms
                if gap < 0:
                    counters.counter_resets += 1
                elif round(gap) > 1:
                    counters.dropped += int(round(gap)) - 1
            self._last_timestamp = frame.timestamp_ms
        return frame
