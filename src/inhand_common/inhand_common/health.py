"""A node's health as diagnostics report it: level, message and key values, and the
bookkeeping every node needs to fill them (counts per interval, when to warn in the log).

No rclpy here: :mod:`inhand_common.ros_diagnostics` turns a :class:`Health` into a
diagnostic_msgs/DiagnosticArray and the log lines. The levels are DiagnosticStatus's.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

__all__ = ['ERROR', 'OK', 'STALE', 'WARN', 'Health', 'IntervalCounts', 'Problems',
           'SimClockWatch', 'WarningLog']

OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: 'OK', WARN: 'WARN', ERROR: 'ERROR', STALE: 'STALE'}


@dataclass
class Health:
    """One status of one node: what ``diagnostics`` carries about it.

    ``reasons`` names the kinds of problem behind a WARN or ERROR (e.g. ``dropped``); the
    log repeats a warning when they change, not every time its numbers do."""

    level: int
    message: str
    values: dict[str, str] = field(default_factory=dict)
    reasons: tuple[str, ...] = ()


class Problems:
    """Collects what is wrong during one interval; the worst level and all the messages
    become one :class:`Health`."""

    def __init__(self) -> None:
        self._found: list[tuple[int, str, str]] = []

    def add(self, level: int, reason: str, message: str) -> None:
        self._found.append((level, reason, message))

    def health(self, ok_message: str, values: Mapping[str, object]) -> Health:
        """OK with ``ok_message`` when nothing was added, else the worst level with every
        message, the worst first."""
        text = {key: str(value) for key, value in values.items()}
        if not self._found:
            return Health(OK, ok_message, text)
        found = sorted(self._found, key=lambda item: -item[0])
        return Health(found[0][0], '; '.join(message for _, _, message in found), text,
                      tuple(reason for _, reason, _ in found))


class IntervalCounts:
    """Counters' increase since the previous call, and their rates.

    ``step(now, counts)`` returns ``(elapsed, increases)`` where ``increases`` maps every
    key of ``counts`` to how much it grew since the last step (all of it on the first)."""

    def __init__(self, now: float) -> None:
        self._then = now
        self._previous: dict[str, int] = {}

    def step(self, now: float, counts: Mapping[str, int]) -> tuple[float, dict[str, int]]:
        elapsed = max(now - self._then, 1e-9)
        increases = {key: int(value) - self._previous.get(key, 0)
                     for key, value in counts.items()}
        self._then = now
        self._previous = {key: int(value) for key, value in counts.items()}
        return elapsed, increases


class WarningLog:
    """When a status should also go to the log.

    A node's diagnostics come about once a second; its log should say the moment something
    goes wrong, but not the same thing every second. A WARN or ERROR is logged when its
    reasons differ from the last logged (something new went wrong), and again every
    ``repeat`` seconds while it lasts; the return to OK is logged once."""

    def __init__(self, repeat: float = 10.0) -> None:
        self.repeat = repeat
        self._reasons: tuple[str, ...] = ()
        self._logged_at: float | None = None
        self._bad = False

    def line(self, now: float, health: Health) -> tuple[int, str] | None:
        """``(level, text)`` to log now, or None."""
        if health.level == OK:
            if not self._bad:
                return None
            self._bad, self._reasons, self._logged_at = False, (), None
            return OK, f'back to normal: {health.message}'
        new = set(health.reasons) - set(self._reasons)
        due = self._logged_at is None or now - self._logged_at >= self.repeat
        self._bad = True
        self._reasons = health.reasons
        if not new and not due:
            return None
        self._logged_at = now
        return health.level, health.message


class SimClockWatch:
    """Says when a node's ROS time stands still while its data keeps coming.

    Under ``use_sim_time`` a node's time is what ``/clock`` says; with nothing publishing
    it (a replay without ``--clock``), the time stays at zero. The nodes keep working
    (their timers run on the steady clock), but everything they stamp with their own time
    is stamped 0 and anything that waits on ROS time waits for ever. Fed once per interval
    with the node's time and whether data arrived, :meth:`stalled` gives the seconds of
    wall time the ROS time has not moved while data arrived (0 while all is well)."""

    def __init__(self, wall_now: float) -> None:
        self._ros_ns: int | None = None
        self._since = wall_now

    def stalled(self, wall_now: float, ros_ns: int, data_arrived: bool) -> float:
        if ros_ns != self._ros_ns or not data_arrived:
            self._ros_ns, self._since = ros_ns, wall_now
            return 0.0
        return wall_now - self._since
