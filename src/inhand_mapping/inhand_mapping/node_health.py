"""What the mapping nodes say about themselves in ``diagnostics`` (and their logs): the
state, the rates in and out, the counters, and what went wrong in the last interval.

Plain functions of the libraries' counters, no rclpy: the nodes call them about once a
second through :class:`inhand_common.ros_diagnostics.NodeDiagnostics`. Each takes the
counters' increases since the previous report (:class:`inhand_common.health.IntervalCounts`)
so a warning says what happened *now*, not since start.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from inhand_common.health import WARN, IntervalCounts, Problems
from inhand_mapping.occupancy import IntegrationCounts
from inhand_mapping.registration import RegistrationStats

__all__ = ['OccupancyActivity', 'OccupancyHealth', 'RegistrationActivity', 'RegistrationHealth']


def _per_second(count: int, elapsed: float) -> str:
    return f'{count / elapsed:.1f}'


@dataclass
class RegistrationActivity:
    """The registration node's own counters beside the registrar's."""

    published: int = 0      # registered points published
    unheard: int = 0        # of which while registration/points had no subscriber
    subscribers: int = 0    # readers of registration/points now


class RegistrationHealth:
    """Reports of a registration node registering ``fingers`` against ``object_topic``
    (None in static mode)."""

    def __init__(self, now: float, object_topic: str | None, max_gap: float,
                 max_pending: float):
        self.object_topic = object_topic
        self.max_gap = max_gap
        self.max_pending = max_pending
        self._interval = IntervalCounts(now)

    def report(self, now: float, stats: RegistrationStats, activity: RegistrationActivity,
               problems: Problems) -> tuple[str, dict[str, object]]:
        counts = {**asdict(stats), 'points_published': activity.published,
                  'points_unheard': activity.unheard}
        elapsed, new = self._interval.step(now, counts)
        window = f'in the last {elapsed:.1f} s'
        tracked = self.object_topic is not None
        if stats.received == 0:
            state = 'waiting for fingertip poses'
        elif tracked and stats.object_poses == 0:
            state = f'waiting for {self.object_topic}'
        elif new['received']:
            state = 'registering'
        else:
            state = 'idle (no fingertip poses)'
        if tracked and new['received'] and not new['object_poses']:
            problems.add(WARN, 'object_silent',
                         f"{self.object_topic} silent while {new['received']} fingertip "
                         f'positions arrived {window}: they wait {self.max_pending:g} s '
                         '(max_pending) for an object pose, then are dropped')
        if new['dropped_before_object']:
            problems.add(WARN, 'before_object',
                         f"{new['dropped_before_object']} fingertip positions dropped {window}: "
                         f'no pose from {self.object_topic} at or before their stamps')
        if new['dropped_gap']:
            problems.add(WARN, 'object_gap',
                         f"{new['dropped_gap']} fingertip positions dropped {window}: no object "
                         f'pose within max_gap ({self.max_gap:g} s) on both sides of their stamps')
        if new['restarts']:
            problems.add(WARN, 'restart',
                         f"time went back {window} ({new['restarts']} time(s)): a new stream "
                         '(a second replay, a loop, a clock stepped back); registering goes '
                         'on into the same map')
        if new['dropped_old_stream']:
            problems.add(WARN, 'old_stream',
                         f"{new['dropped_old_stream']} fingertip positions of the stream before "
                         f'the time went back arrived after it {window}: dropped')
        if new['dropped_invalid']:
            problems.add(WARN, 'invalid', f"{new['dropped_invalid']} fingertip positions with "
                         f'NaN or infinite values dropped {window}')
        if new['object_out_of_order'] or new['object_invalid']:
            problems.add(WARN, 'object_ignored',
                         f"{new['object_out_of_order']} object poses out of order and "
                         f"{new['object_invalid']} invalid ignored {window}")
        if new['points_unheard']:
            problems.add(WARN, 'no_subscriber',
                         f"{new['points_unheard']} registered points published {window} while "
                         'nothing subscribed to registration/points: they are lost')
        values: dict[str, object] = {
            'state': state, 'mode': 'tracked' if tracked else 'static',
            'fingertips_in_hz': _per_second(new['received'], elapsed),
            'object_poses_in_hz': _per_second(new['object_poses'], elapsed),
            'points_out_hz': _per_second(new['points_published'], elapsed),
            **counts, 'subscribers': activity.subscribers}
        return (f"{state}: {values['fingertips_in_hz']} fingertip positions/s in, "
                f"{values['points_out_hz']} points/s out"), values


@dataclass
class OccupancyActivity:
    """The occupancy node's own counters beside the grid's."""

    received: int = 0        # registered points received
    messages: int = 0        # in how many registration/points messages
    publications: int = 0    # map publications
    pending: int = 0         # samples the touch model holds back (grid.pending)
    publishers: int = 0      # writers of registration/points matched now
    touched_cells: int = 0   # in the latest published map
    occupied_cells: int = 0
    occupied_on_faces: int = 0   # occupied cells in the grid's outermost layer
    vision_cells: int = 0    # cells of the latest vision map (0: none)
    textured: bool = False   # colours of occupancy/textured held for the save


def outside_note(outside: int, points: int, occupied_on_faces: int, where: str) -> str:
    """What the points outside the workspace mean. With the occupied cells clear of the
    workspace's faces the object lies inside it, and those points are fingertips away from
    the object (lifts, the carry between strokes, a re-grasp): counted, not a problem. With
    occupied cells on its faces the map may be cut off."""
    workspace = f'the workspace {where}'.rstrip()
    if not occupied_on_faces:
        return (f'{outside} of {points} points outside {workspace}: fingertips away from '
                'the object (its occupied cells keep clear of the faces)')
    return (f'{outside} of {points} points fell outside {workspace} and '
            f'{occupied_on_faces} occupied cells lie on its faces: the object may be cut off '
            '(workspace_size or workspace_centre too small for this object?)')


class OccupancyHealth:
    """Reports of an occupancy node with ``workspace`` (its cube, for the messages)."""

    def __init__(self, now: float, workspace: str):
        self.workspace = workspace
        self._interval = IntervalCounts(now)

    def report(self, now: float, counts: IntegrationCounts, activity: OccupancyActivity,
               problems: Problems) -> tuple[str, dict[str, object]]:
        totals = {'points_received': activity.received, 'messages': activity.messages,
                  **asdict(counts), 'map_publications': activity.publications}
        elapsed, new = self._interval.step(now, totals)
        window = f'in the last {elapsed:.1f} s'
        if activity.received == 0:
            state = ('waiting for registration/points' if activity.publishers == 0
                     else 'waiting for points')
        elif new['points_received']:
            state = 'mapping'
        else:
            state = 'idle (no points)'
        if new['outside'] and activity.occupied_on_faces:
            problems.add(WARN, 'outside', outside_note(new['outside'], new['points_received'],
                                                       activity.occupied_on_faces,
                                                       f'{window} ({self.workspace})'))
        if new['invalid']:
            problems.add(WARN, 'invalid', f"{new['invalid']} points with NaN or infinite values "
                         f'ignored {window}')
        values: dict[str, object] = {
            'state': state,
            'points_in_hz': _per_second(new['points_received'], elapsed),
            'map_publications_hz': _per_second(new['map_publications'], elapsed),
            **totals, 'pending': activity.pending, 'touched_cells': activity.touched_cells,
            'occupied_cells': activity.occupied_cells, 'vision_cells': activity.vision_cells,
            'textured': str(activity.textured).lower(), 'publishers': activity.publishers}
        return (f"{state}: {values['points_in_hz']} points/s in, {activity.occupied_cells} "
                f'occupied of {activity.touched_cells} touched cells'), values
