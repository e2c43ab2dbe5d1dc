"""A node's ``diagnostics``: its :class:`~inhand_common.health.Health` about once a second as
diagnostic_msgs/DiagnosticArray, the same words in its log when something goes wrong, and
the check every node needs under ``use_sim_time`` (time standing still while data arrives).

The node gives a ``report(now, problems)`` callable that fills ``problems`` and returns
the OK message and the key values; this class does the rest on a steady-clock timer, so
diagnostics keep coming whatever ``/clock`` does.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from inhand_common.health import OK, WARN, Health, Problems, SimClockWatch, WarningLog
from inhand_common.ros_clock import steady_timer, uses_sim_time

__all__ = ['DIAGNOSTICS_PERIOD', 'SIM_TIME_STALL', 'NodeDiagnostics']

DIAGNOSTICS_PERIOD = 1.0  # s (steady clock)
SIM_TIME_STALL = 3.0      # s of data with the ROS time standing still before a warning

Report = Callable[[float, Problems], tuple[str, dict[str, object]]]


class NodeDiagnostics:
    """Publishes ``diagnostics`` for ``node`` with one status named after the node.

    ``data_count`` (a running total of messages taken in) lets it tell, under sim time,
    whether data arrived while the ROS time stood still."""

    def __init__(self, node: Node, hardware_id: str, report: Report,
                 data_count: Callable[[], int] | None = None,
                 period: float = DIAGNOSTICS_PERIOD, name: str | None = None):
        self.node = node
        self.name = name or node.get_fully_qualified_name()
        self.hardware_id = hardware_id
        self._report = report
        self._data_count = data_count
        self._last_count = 0
        self._publisher = node.create_publisher(DiagnosticArray, 'diagnostics', 10)
        self._log = WarningLog()
        self._clock_watch = SimClockWatch(time.monotonic())
        self.latest: Health | None = None
        self._timer = steady_timer(node, period, self.publish)

    def publish(self) -> Health:
        """Make, publish and (when due) log the status now."""
        now = time.monotonic()
        problems = Problems()
        ok_message, values = self._report(now, problems)
        self._check_clock(now, problems, values)
        health = problems.health(ok_message, values)
        msg = DiagnosticArray()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.status = [DiagnosticStatus(
            level=bytes([health.level]), name=self.name, message=health.message,
            hardware_id=self.hardware_id,
            values=[KeyValue(key=k, value=v) for k, v in health.values.items()])]
        self._publisher.publish(msg)
        self.latest = health
        line = self._log.line(now, health)
        if line is not None:
            level, text = line
            # One call site per severity: rclpy refuses a call site that changes severity.
            logger = self.node.get_logger()
            if level == OK:
                logger.info(text)
            elif level == WARN:
                logger.warning(text)
            else:
                logger.error(text)
        return health

    def _check_clock(self, now: float, problems: Problems, values: dict[str, object]) -> None:
        if not uses_sim_time(self.node):
            return
        ros_ns = self.node.get_clock().now().nanoseconds
        values['ros_time'] = f'{ros_ns * 1e-9:.3f}'
        if self._data_count is None:
            return
        count = self._data_count()
        arrived, self._last_count = count != self._last_count, count
        stalled = self._clock_watch.stalled(now, ros_ns, arrived)
        if stalled >= SIM_TIME_STALL:
            problems.add(WARN, 'sim_time',
                         f'use_sim_time is true but the ROS time has stood at '
                         f'{ros_ns * 1e-9:.3f} s for {stalled:.0f} s while data arrived: '
                         'nothing publishes /clock (bag_replay --clock does)')
