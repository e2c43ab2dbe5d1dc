"""Registration: fingertip positions re-expressed in the object (map) frame.

The paper's eq. (1), done properly. The tracker reports the object sensor at
``(R_o(t), t_o(t))`` and a fingertip at ``p(t)``, all in the tracker source frame. For a
rigid object the point touched, in the object sensor's own frame, is::

    p_obj = R_o(t)^T (p(t) - t_o(t))

That frame moves with the object, so it is the same frame at every time; the map frame
``object`` is defined as the sensor's frame at its first pose, which is also where the map
sits in the tracker frame (:attr:`Registrar.first_object_pose`), so anything measured in the
tracker frame before the exploration (camera texture, for one) can be brought into the map.

The position registered is where the finger pad touches: the sensor's position moved by
the finger's tip offset in the sensor's own frame at the same stamp to the pad's centre,
then by the pad's radius to its surface, along the normal of the sheet the pad centres
have traced (tip_offsets.py, pad_normals.py; both zero by default, then the sensor's
position itself).

In ``static`` mode there is no object sensor: the object is fixed and the map frame is the
tracker frame, so points pass through unchanged (invalid ones are still rejected).

Pairing a fingertip with an object pose
---------------------------------------
* Same stamp: the driver gives every station of one tracker frame the same stamp, so a
  fingertip stamped like an object pose uses that pose exactly. Stamps are compared exactly;
  they are built the same way from the same integer stamps.
* Between two object poses: the object pose is interpolated (position linearly, orientation
  by slerp), but only when the two bracketing poses are at most ``max_gap`` apart. Across a
  longer gap (lost frames, sensor out of range) nothing is known about the motion, so the
  fingertip is dropped (``dropped_gap``).
* Later than the newest object pose: it waits in the buffer for a later object pose and is
  never extrapolated. Topics are delivered independently, so a fingertip often arrives
  before the object pose of its own tracker frame.
* Earlier than the first object pose ever received: dropped (``dropped_before_object``).

Order and bounded memory
------------------------
Each topic is delivered in order, but the topics are not ordered with respect to each
other: a fast replay can deliver one finger's stream seconds of sensor time ahead of
another's. Registered points are therefore released in time order up to a watermark: the
oldest of the newest stamps of the finger streams (no stream can still deliver anything
older). Downstream (the occupancy update) then sees one time-ordered stream, whatever
the delivery order, which is what makes the live map equal ``build_map``'s.

Object poses arrive in time order; a duplicate or older one is ignored
(``object_out_of_order``). Only the object poses that can still be needed are kept: back to
the watermark, the oldest waiting fingertip or ``HISTORY_SECONDS`` before the newest pose,
whichever is oldest.

Waiting is bounded in wall-clock time, when the caller gives it (``now``, seconds of a
monotonic clock; the node does, ``build_map`` does not need to): a fingertip that has
waited ``max_pending`` seconds for an object pose is dropped (``dropped_gap``, or
``dropped_before_object`` while no object pose has arrived at all), so an unplugged object
sensor cannot make the buffer grow without end; and a finger stream that has been silent
for ``max_pending`` seconds no longer holds the watermark back. A finger stream the caller
expects (``fingers``) that has not delivered anything yet holds the watermark at its start,
for ``max_pending`` seconds from the first data: otherwise, when a fast replay's first
finger messages come after seconds of object poses, those poses would already be trimmed
and the fingers' first seconds dropped.

Time going back
---------------
A stamp more than ``STREAM_RESTART`` (1 s) before the newest one starts a new stream: a
bag replayed again into a running graph, ``bag_replay --loop``, a clock stepped back. In
tracked mode the object sensor's stream decides (its poses arrive in time order): what
is pending is registered against the old history as at the end of an input, the history
and the finger streams start afresh, and the map frame stays the first pose ever (the
object's body frame is the same frame in every stream). Fingertips of the old stream
that are still in flight when the object's new stream has begun (later than its newest
pose by more than ``STREAM_RESTART``) cannot be paired any more and are counted apart
(``dropped_old_stream``). In static mode a finger's own stream going back starts a new
stream. ``restarts`` counts them; the touch models downstream restart a finger's track
when its time goes back (dwell.py, touch_paths.py), so the map goes on.

Every fingertip received ends up in exactly one counter::

    received == registered + dropped_gap + dropped_before_object + dropped_invalid
                + dropped_old_stream + pending

All the work is vectorised with numpy (``searchsorted`` over the object time array): no
Python loop per point.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import NamedTuple, TypeAlias

import numpy as np
from numpy.typing import ArrayLike

from inhand_common.array_types import (
    Bools,
    Counts,
    Matrices,
    Matrix3,
    Points,
    Quaternions,
    Rows,
    StationIds,
    Times,
    Vector3,
)
from inhand_common.rotations import quaternion_to_matrix, slerp
from inhand_mapping.pad_normals import PadNormals
from inhand_mapping.tip_offsets import TipOffsets

__all__ = ['MODES', 'STREAM_RESTART', 'ObjectPoseAt', 'Registrar', 'RegistrationStats']

MODES = ('tracked', 'static')

# Object poses always kept behind the newest one (sensor seconds), whatever the streams say:
# covers the ordinary delivery skew of a finger stream not seen yet.
HISTORY_SECONDS = 1.0

# A stamp this much (s) before the newest one starts a new stream (see the module doc):
# far above any delivery skew, far below a replay's or a loop's length.
STREAM_RESTART = 1.0

# Stamps per block when computing object poses (cache-sized temporaries).
_BLOCK = 16384

_IDENTITY_POSE = (np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))

# Registered fingertips: (points (M, 3) in the map frame, times (M,), fingers (M,)).
Registered: TypeAlias = tuple[Points, Times, StationIds]


@dataclass
class RegistrationStats:
    """Counters. The fingertip ones add up to ``received`` (see the module docstring)."""

    received: int = 0  # fingertip positions given
    registered: int = 0  # returned as registered points
    dropped_gap: int = 0  # object-pose gap around t longer than max_gap, or history gone
    dropped_before_object: int = 0  # earlier than the first object pose
    dropped_invalid: int = 0  # NaN/inf time or position
    dropped_old_stream: int = 0  # in flight from a stream that time went back from
    pending: int = 0  # waiting for an object pose at or after their time (set on each call)
    object_poses: int = 0  # object poses accepted
    object_out_of_order: int = 0  # object poses ignored: not newer than the newest one
    object_invalid: int = 0  # object poses ignored: NaN/inf or zero-norm quaternion
    restarts: int = 0  # new streams: time went back by more than STREAM_RESTART


def _empty_result() -> Registered:
    return np.empty((0, 3)), np.empty(0), np.empty(0, dtype=np.int32)


class ObjectPoseAt(NamedTuple):
    """The map frame's pose in the tracker frame at one time, by the fingertips' rules.

    ``state``: ``resolved`` (a pose at that stamp, or interpolated between two poses at most
    ``max_gap`` apart; ``rotation`` and ``position`` are set), ``later`` (no pose at or after
    the time yet: ask again when more have come), ``gap`` (the poses around it are too far
    apart), ``before_first`` (before the first object pose). A tracker-frame point p is
    ``rotation.T @ (p - position)`` in the map frame.
    """

    state: str
    rotation: Matrix3 | None = None
    position: Vector3 | None = None


class _Fingertips(NamedTuple):
    """Fingertip rows waiting to be registered, all N long."""

    times: Times           # (N,) sensor seconds
    positions: Points      # (N, 3) tracker frame: the sensors', or the pad centres'
    fingers: StationIds    # (N,)
    arrivals: Times        # (N,) the ``now`` they arrived at (NaN without a clock)
    facing: Points         # (N, 3) where each pad faces, tracker frame; (N, 0) without a pad

    @property
    def size(self) -> int:
        return self.times.size

    def part(self, rows: slice | Bools | Rows) -> _Fingertips:
        return _Fingertips(self.times[rows], self.positions[rows], self.fingers[rows],
                           self.arrivals[rows], self.facing[rows])


class _Stamps(NamedTuple):
    """The distinct stamps of a time-ordered batch. All stations of one tracker frame share
    a stamp, so there are several points per stamp, and everything about the object pose
    is decided once per stamp, then applied to the points."""

    times: Times          # (U,) the distinct stamps, ascending
    of_point: Rows   # (N,) each point's stamp: an index into ``times``
    points: Counts   # (U,) how many points have each stamp

    @classmethod
    def of(cls, times: Times) -> _Stamps:
        n = times.size
        new_stamp = np.empty(n, dtype=bool)
        new_stamp[0] = True
        np.not_equal(times[1:], times[:-1], out=new_stamp[1:])
        return cls(times=times[new_stamp], of_point=np.cumsum(new_stamp) - 1,
                   points=np.diff(np.append(np.flatnonzero(new_stamp), n)))


class _PoseMatch(NamedTuple):
    """Where each stamp falls in the object-pose history: one flag array per outcome, (U,).
    Every stamp is exactly one of: ``resolved`` (``exact`` or ``interpolate``), ``later``,
    ``before_first`` or ``gap``."""

    at_or_after: Rows  # the first object pose at or after the stamp (the newest if none)
    later: Bools            # newer than the newest object pose: wait for the next one
    exact: Bools            # an object pose has exactly this stamp
    interpolate: Bools      # between two object poses at most max_gap apart
    resolved: Bools         # exact or interpolate: the object pose is known
    before_first: Bools     # before the first object pose ever received
    gap: Bools              # across a longer gap, or before the history kept


class Registrar:
    """Pairs fingertip positions with object poses and returns them in the map frame.

    Feed it with :meth:`add_object_pose` and :meth:`add_fingertips` in any interleaving
    (each stream in its own time order; fingertips may come before the object poses they
    need); :meth:`drain` returns what can be registered so far, in time order, and
    :meth:`finish` ends the input. ``max_pending`` is in seconds of the ``now`` clock;
    ``fingers`` are the finger ids whose streams are expected (used with a clock only).
    Times are float seconds (``sec + nanosec * 1e-9``); at epoch scale a float64 resolves
    about 0.24 microseconds, far below the tracker period.
    """

    def __init__(self, mode: str = 'tracked', max_gap: float = 0.05,
                 max_pending: float = 1.0, fingers: Iterable[int] = (),
                 tip_offsets: TipOffsets | None = None):
        if mode not in MODES:
            raise ValueError(f"registration mode must be one of {MODES}, got {mode!r}")
        for name, value in (('max_gap', max_gap), ('max_pending', max_pending)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0.0):
                raise ValueError(f'{name} must be a positive number of seconds, got {value!r}')
        self.mode = mode
        # Sensor -> contact per finger (tip_offsets.py); None or all zero: the raw positions.
        self.tip_offsets = None if tip_offsets is None or tip_offsets.zero else tip_offsets
        # With a round pad, which way it touches: the surface its centres trace (pad_normals.py).
        self.pad_normals = PadNormals() if self.tip_offsets is not None and \
            self.tip_offsets.pad_radius > 0.0 else None
        self._facing_width = 0 if self.pad_normals is None else 3
        self.max_gap = float(max_gap)
        self.max_pending = float(max_pending)
        self.stats = RegistrationStats()
        # Object-pose history: growable arrays, the first _n_obj rows in use, time-ordered.
        capacity = 1024
        self._obj_t: Times = np.empty(capacity)
        self._obj_p: Points = np.empty((capacity, 3))
        self._obj_q: Quaternions = np.empty((capacity, 4))
        self._n_obj = 0
        self._first_pose: tuple[Vector3, Quaternions] | None = None
        self._first_t = math.nan
        self._latest_t = -math.inf
        # Fingertips waiting: chunks appended by add_fingertips, merged (time-sorted) by drain.
        self._chunks: list[_Fingertips] = []
        self._n_pending = 0
        self._pending_min_t = math.inf
        # Per finger stream: [newest stamp, arrival (now) of it or nan].
        self._streams: dict[int, list[float]] = {}
        # Finger streams expected but not heard from yet, and the clock (now) when the
        # first data of any kind was drained: see _watermark.
        self._expected = {int(finger) for finger in fingers}
        self._unheard = set(self._expected)
        self._data_since = math.nan
        self._clock: float | None = None   # the newest `now` given, for trims between drains
        # Registered by a restart, handed out by the next drain; and the newest object time
        # of the stream before (its fingertips still in flight are not paired).
        self._carried: list[Registered] = []
        self._old_stream_end = -math.inf
        # Per finger whose stream went back before the object's: its points below this
        # time are of the new stream.
        self._new_stream_below: dict[int, float] = {}

    # ------------------------------------------------------------------ inputs
    @property
    def first_object_pose(self) -> tuple[Vector3, Quaternions] | None:
        """The map frame's pose in the tracker frame: (position (3,), quaternion xyzw (4,)).

        Tracked mode: the object sensor's first pose, or None before it arrives. Static mode:
        the identity (the map frame is the tracker frame).
        """
        if self.mode == 'static':
            return _IDENTITY_POSE[0].copy(), _IDENTITY_POSE[1].copy()
        if self._first_pose is None:
            return None
        return self._first_pose[0].copy(), self._first_pose[1].copy()

    def add_object_pose(self, t: float, position: ArrayLike, quaternion_xyzw: ArrayLike) -> None:
        """Record the object sensor's pose at time ``t`` (seconds). Ignored in static mode.

        Poses must come in time order; a pose not newer than the newest one is ignored and
        counted (``object_out_of_order``), as is a non-finite one (``object_invalid``).
        """
        if self.mode == 'static':
            return
        t = float(t)
        p = np.asarray(position, dtype=float).reshape(3)
        q = np.asarray(quaternion_xyzw, dtype=float).reshape(4)
        norm = math.sqrt(float(q @ q))
        if not (math.isfinite(t) and np.isfinite(p).all() and math.isfinite(norm)
                and norm > 1e-9):
            self.stats.object_invalid += 1
            return
        if t <= self._latest_t:
            if t >= self._latest_t - STREAM_RESTART:
                self.stats.object_out_of_order += 1
                return
            self._restart()
        q = q / norm
        if self._n_obj == len(self._obj_t):
            self._make_room()
        n = self._n_obj
        self._obj_t[n] = t
        self._obj_p[n] = p
        self._obj_q[n] = q
        self._n_obj = n + 1
        self._latest_t = t
        self.stats.object_poses += 1
        if self._first_pose is None:
            self._first_pose = (p.copy(), q.copy())
        if math.isnan(self._first_t):
            self._first_t = t

    def object_pose_at(self, t: float) -> ObjectPoseAt:
        """Where the object (map) frame was at time ``t`` (see :class:`ObjectPoseAt`): what the
        stereo node needs to bring a picture taken at ``t`` into the map frame, by the same
        rules (exact stamp, slerp across short gaps, never extrapolated) as the fingertips.
        Static mode: the identity."""
        if self.mode == 'static':
            return ObjectPoseAt('resolved', np.eye(3), np.zeros(3))
        if self._n_obj == 0:
            return ObjectPoseAt('later')
        stamps = np.array([float(t)])
        match = self._match_object_poses(stamps)
        if match.resolved[0]:
            rotation, position = self._object_poses_at(stamps, match.at_or_after,
                                                       match.interpolate)
            return ObjectPoseAt('resolved', rotation[0], position[0])
        if match.later[0]:
            return ObjectPoseAt('later')
        return ObjectPoseAt('before_first' if match.before_first[0] else 'gap')

    def add_fingertips(self, t: ArrayLike, positions: ArrayLike, fingers: ArrayLike,
                       now: float | None = None, quaternions: ArrayLike | None = None) -> None:
        """Buffer fingertip positions: ``t`` (N,) seconds, ``positions`` (N, 3), ``fingers`` (N,).

        A scalar ``t`` or ``fingers`` applies to every row; one position may be given as (3,).
        Rows with a non-finite time or position are dropped here (``dropped_invalid``).
        ``now`` (monotonic wall clock, s) is when they arrived, for the waiting limits.
        ``quaternions`` (N, 4), the sensors' orientations at the same stamps, are needed when
        the registrar has tip offsets: each position is then moved to its contact point
        (tip_offsets.py), and a row whose orientation is not a rotation is dropped as invalid.
        """
        pos = np.asarray(positions, dtype=float)
        if pos.ndim == 1:
            pos = pos.reshape(1, -1)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ValueError(f'positions must have shape (N, 3), got {np.shape(positions)}')
        n = pos.shape[0]
        times = np.broadcast_to(np.asarray(t, dtype=float), (n,))
        given = np.broadcast_to(np.asarray(fingers), (n,))
        if given.size and not np.issubdtype(given.dtype, np.integer):
            raise ValueError(f'fingers must be integers (station numbers), got {given.dtype}')
        fing = given.astype(np.int32)
        if self.tip_offsets is not None and quaternions is None:
            raise ValueError("this registrar has tip offsets: add_fingertips needs the sensors' "
                             'quaternions')
        self.stats.received += n
        if n == 0:
            return
        valid = np.isfinite(times) & np.isfinite(pos).all(axis=1)
        facing = np.empty((n, self._facing_width))
        if self.tip_offsets is not None and quaternions is not None:
            pos, pad_facing, placed = self.tip_offsets.pads(pos, quaternions, fing)
            if self._facing_width:
                facing = pad_facing
            valid &= placed
        if not valid.all():
            self.stats.dropped_invalid += int(n - np.count_nonzero(valid))
            times, pos, fing, facing = times[valid], pos[valid], fing[valid], facing[valid]
            if times.size == 0:
                self._set_pending()
                return
        else:
            times = times.copy()  # decouple from the caller's (possibly broadcast) arrays
            pos = pos.copy()
        if now is not None:
            self._clock = float(now)
        keep = self._new_stream_check(times, fing, live=now is not None)
        if keep is not None:
            times, pos, fing, facing = times[keep], pos[keep], fing[keep], facing[keep]
        if times.size == 0:
            self._set_pending()
            return
        arrival = np.full(times.size, math.nan if now is None else float(now))
        self._chunks.append(_Fingertips(times, pos, fing, arrival, facing))
        self._n_pending += times.size
        self._pending_min_t = min(self._pending_min_t, float(times.min()))
        for finger in np.unique(fing).tolist():
            newest = float(times[fing == finger].max())
            self._unheard.discard(finger)
            stream = self._streams.setdefault(finger, [-math.inf, math.nan])
            if newest >= stream[0]:
                stream[0] = newest
            stream[1] = math.nan if now is None else float(now)
        self._set_pending()

    # ------------------------------------------------------------------ outputs
    def drain(self, now: float | None = None) -> Registered:
        """Registered (points (M, 3) in the map frame, times (M,), fingers (M,)), time-ordered.

        Returns every buffered fingertip up to the watermark that can be resolved now,
        drops those that never can, and keeps the ones still waiting. ``now``: see the
        module docstring.
        """
        return self._with_carried(self._resolve(final=False, now=now))

    def finish(self) -> Registered:
        """End of input: register what can be, drop the rest (nothing is extrapolated)."""
        return self._with_carried(self._resolve(final=True, now=None))

    # ------------------------------------------------------------------ new streams
    def _new_stream_check(self, times: Times, fingers: StationIds, live: bool) -> Bools | None:
        """Static mode: a finger's time going back starts a new stream. Tracked mode: the
        rows of the stream before a restart still in flight are dropped and counted, and,
        ``live`` (a clock given: topics delivered independently), a finger whose time went
        back waits for the object's new stream. Returns the rows to keep (None: all)."""
        if self.mode == 'static':
            if self._fingers_gone_back(times, fingers):
                self._restart()
            return None
        if live:
            self._new_stream_below.update(self._fingers_gone_back(times, fingers))
        if self._old_stream_end == -math.inf:
            return None
        old = (times > self._latest_t + STREAM_RESTART) & \
            (times <= self._old_stream_end + STREAM_RESTART)
        if old.any():
            self.stats.dropped_old_stream += int(np.count_nonzero(old))
            return ~old
        return None

    def _fingers_gone_back(self, times: Times, fingers: StationIds) -> dict[int, float]:
        """The fingers whose rows go back more than STREAM_RESTART before their stream's
        newest stamp, each with the time below which its rows are of a new stream."""
        gone_back = {}
        for finger in np.unique(fingers).tolist():
            stream = self._streams.get(finger)
            if stream is not None and \
                    float(times[fingers == finger].min()) < stream[0] - STREAM_RESTART:
                gone_back[finger] = stream[0] - STREAM_RESTART
        return gone_back

    def _restart(self) -> None:
        """Time went back: register what the old stream can, then start afresh (the map
        frame stays). Fingertips already waiting from the new stream wait on."""
        pending = self._take_pending()
        new = self._ahead_of_restart(pending)
        self._new_stream_below = {}
        self._keep_waiting(pending.part(~new))
        self._carried.append(self._resolve(final=True, now=self._clock))
        self._keep_waiting(pending.part(new))
        self._set_pending()
        self._old_stream_end = self._latest_t
        self._n_obj = 0
        self._first_t = math.nan     # 'before the first pose' is of this stream now
        self._latest_t = -math.inf
        self._streams = {}
        self._unheard = set(self._expected)
        self._data_since = math.nan
        self.stats.restarts += 1

    def _ahead_of_restart(self, batch: _Fingertips) -> Bools:
        """Points of fingers whose stream went back before the object's did."""
        ahead = np.zeros(batch.size, dtype=bool)
        for finger, below in self._new_stream_below.items():
            ahead |= (batch.fingers == finger) & (batch.times < below)
        return ahead

    def _with_carried(self, result: Registered) -> Registered:
        if not self._carried:
            return result
        parts = [*self._carried, result]
        self._carried = []
        points, times, fingers = (np.concatenate([part[k] for part in parts]) for k in range(3))
        return points, times, fingers

    # ------------------------------------------------------------------ internals
    def _set_pending(self) -> None:
        self.stats.pending = self._n_pending

    def _take_pending(self) -> _Fingertips:
        chunks, self._chunks = self._chunks, []
        self._n_pending = 0
        if not chunks:
            return _Fingertips(np.empty(0), np.empty((0, 3)), np.empty(0, dtype=np.int32),
                               np.empty(0), np.empty((0, self._facing_width)))
        if len(chunks) == 1:
            batch = chunks[0]
        else:
            batch = _Fingertips(*(np.concatenate(column) for column in zip(*chunks)))
        t = batch.times
        if t.size > 1 and (len(chunks) > 1 or np.any(t[1:] <= t[:-1])):
            # By time, then finger: the output order (and so the map, to the last bit of
            # its sums) does not depend on the order the topics were delivered in.
            batch = batch.part(np.lexsort((batch.fingers, t)))
        return batch

    def _keep_waiting(self, *parts: _Fingertips) -> None:
        """Keep these fingertips waiting, time-ordered."""
        kept = [part for part in parts if part.size]
        self._chunks = kept
        self._n_pending = sum(part.size for part in kept)
        self._pending_min_t = min((float(part.times.min()) for part in kept), default=math.inf)

    def _watermark(self, now: float | None) -> float:
        """Oldest newest-stamp of the finger streams still delivering (see the module doc)."""
        if (now is not None and self._unheard
                and not now - self._data_since > self.max_pending):
            # An expected finger whose first points have not come yet: they may be older
            # than anything released so far (at start-up a fast replay delivers its topics
            # unevenly), and the object poses they need must stay. Held for max_pending
            # seconds from the first data; a finger that is not tracked at all then stops
            # holding everything back.
            return -math.inf
        newest = [stamp for stamp, arrival in self._streams.values()
                  if now is None or math.isnan(arrival) or now - arrival <= self.max_pending]
        return min(newest) if newest else math.inf

    def _stale(self, arrival: Times, now: float | None) -> Bools:
        """Fingertips that have waited longer than max_pending (never, without a clock)."""
        if now is None:
            return np.zeros(arrival.size, dtype=bool)
        with np.errstate(invalid='ignore'):
            stale: Bools = now - arrival > self.max_pending
        return stale

    def _resolve(self, final: bool, now: float | None) -> Registered:
        """What drain and finish do: register what can be, keep what may still be, drop the
        rest (each counted)."""
        batch = self._take_pending()
        if now is not None:
            self._clock = float(now)
            if math.isnan(self._data_since) and (batch.size or self._n_obj):
                self._data_since = float(now)
        held = batch.part(slice(0, 0))
        if not final and batch.size:
            # Only up to the watermark: a later point may still be preceded by another's.
            cut = int(np.searchsorted(batch.times, self._watermark(now), side='right'))
            batch, held = batch.part(slice(None, cut)), batch.part(slice(cut, None))
        if batch.size == 0:
            self._keep_waiting(held)
            self._set_pending()
            self._trim_history(now)
            return _empty_result()
        if self.mode == 'static':
            # The map frame is the tracker frame: nothing to pair.
            self.stats.registered += batch.size
            self._keep_waiting(held)
            self._set_pending()
            return self._touching(batch.positions, batch), batch.times, batch.fingers
        if self._n_obj == 0:
            self._wait_for_first_object_pose(batch, held, final, now)
            return _empty_result()
        return self._register_tracked(batch, held, final, now)

    def _wait_for_first_object_pose(self, batch: _Fingertips, held: _Fingertips, final: bool,
                                    now: float | None) -> None:
        """No object pose yet: everything waits, except what has waited too long, or
        everything at the end of the input (it was before the object)."""
        waiting = np.zeros(batch.size, dtype=bool) if final else ~self._stale(batch.arrivals, now)
        self.stats.dropped_before_object += int(batch.size - np.count_nonzero(waiting))
        self._keep_waiting(batch.part(waiting), held)
        self._set_pending()

    def _register_tracked(self, batch: _Fingertips, held: _Fingertips, final: bool,
                          now: float | None) -> Registered:
        """Pair a time-ordered batch with the object poses: register the resolved points,
        keep the later ones waiting, drop and count the rest."""
        ahead = self._ahead_of_restart(batch)
        if ahead.any():
            # A finger's stream went back before the object's did: those points wait for
            # the object's new stream (see "Time going back"), as long as a later point.
            new_stream, batch = batch.part(ahead), batch.part(~ahead)
            stale = np.ones(new_stream.size, dtype=bool) if final else \
                self._stale(new_stream.arrivals, now)
            self.stats.dropped_gap += int(np.count_nonzero(stale))
            held = _Fingertips(*(np.concatenate([a, b]) for a, b in
                                 zip(held, new_stream.part(~stale))))
            if batch.size == 0:
                self._keep_waiting(held)
                self._set_pending()
                return _empty_result()
        stamps = _Stamps.of(batch.times)
        match = self._match_object_poses(stamps.times)
        # Before the first pose ever, before the history kept, or across a long gap: these
        # will never resolve.
        self.stats.dropped_before_object += int(stamps.points[match.before_first].sum())
        self.stats.dropped_gap += int(stamps.points[match.gap].sum())
        out = self._to_object_frame(batch, stamps, match)
        self._keep_later_waiting(batch, held, match.later[stamps.of_point], final, now)
        self._trim_history(now)
        return out

    def _match_object_poses(self, stamps: Times) -> _PoseMatch:
        """Where each stamp (ascending) falls among the object poses kept (see the module
        docstring: same stamp, between two close poses, later, before the first, a gap)."""
        n_obj = self._n_obj
        obj_t = self._obj_t[:n_obj]
        after = np.searchsorted(obj_t, stamps, side='left')
        later = after == n_obj
        at_or_after = np.minimum(after, n_obj - 1)
        t_after = obj_t[at_or_after]
        exact = t_after == stamps  # never true for `later` ones (t_after < stamp there)
        t_before = obj_t[np.maximum(after - 1, 0)]
        interpolate = ~exact & ~later & (after > 0) & (t_after - t_before <= self.max_gap)
        resolved = exact | interpolate
        before_first = stamps < self._first_t
        return _PoseMatch(at_or_after=at_or_after, later=later, exact=exact,
                          interpolate=interpolate, resolved=resolved, before_first=before_first,
                          gap=~later & ~resolved & ~before_first)

    def _to_object_frame(self, batch: _Fingertips, stamps: _Stamps, match: _PoseMatch
                         ) -> Registered:
        """The points whose stamp resolved, in the object (map) frame: R_o^T (p - t_o), with
        the object pose at each stamp exact or interpolated (lerp + slerp)."""
        resolvable = np.flatnonzero(match.resolved)
        if resolvable.size == 0:
            return _empty_result()
        rot, pos = self._object_poses_at(stamps.times[resolvable], match.at_or_after[resolvable],
                                         match.interpolate[resolvable])
        # Row vectors: (R^T d)^T = d^T R.
        n, n_stamps = batch.size, stamps.times.size
        per_stamp = n // n_stamps
        if (resolvable.size == n_stamps and per_stamp * n_stamps == n
                and np.all(stamps.points == per_stamp)):
            # The usual case: every stamp resolves and has the same number of stations,
            # so the points reshape to (stamps, stations, 3) and nothing is gathered.
            d = batch.positions.reshape(n_stamps, per_stamp, 3) - pos[:, None, :]
            points = (d @ rot).reshape(n, 3)
            taken = batch
            if self._facing_width:
                taken = batch._replace(facing=(batch.facing.reshape(n_stamps, per_stamp, 3)
                                               @ rot).reshape(n, 3))
        else:
            # Each point's row in rot / pos, or -1 where its stamp did not resolve.
            slot = np.full(n_stamps, -1)
            slot[resolvable] = np.arange(resolvable.size)
            which = slot[stamps.of_point]
            take = np.flatnonzero(which >= 0)
            which = which[take]
            taken = batch.part(take)
            d = taken.positions - pos[which]
            points = (d[:, None, :] @ rot[which])[:, 0, :]
            if self._facing_width:
                taken = taken._replace(facing=(taken.facing[:, None, :] @ rot[which])[:, 0, :])
        self.stats.registered += points.shape[0]
        return self._touching(points, taken), taken.times, taken.fingers

    def _touching(self, centres: Points, batch: _Fingertips) -> Points:
        """With a round pad, the contacts one radius from the registered pad ``centres``
        (map frame; ``batch.facing`` in the same frame), the way the surface the pads have
        traced says (pad_normals.py); otherwise the points as they are."""
        if self.pad_normals is None or self.tip_offsets is None:
            return centres
        return self.pad_normals.contacts(centres, batch.facing, batch.times,
                                         self.tip_offsets.pad_radius)

    def _keep_later_waiting(self, batch: _Fingertips, held: _Fingertips, later: Bools,
                            final: bool, now: float | None) -> None:
        """Points later than the newest object pose wait for the next one, unless the input
        has ended or the point has waited longer than max_pending (the object stream
        stalled): then they are dropped as across a gap. ``held`` (past the watermark) waits
        too."""
        wait = later
        if final:
            self.stats.dropped_gap += int(np.count_nonzero(wait))
            wait[:] = False
        else:
            stalled = wait & self._stale(batch.arrivals, now)
            self.stats.dropped_gap += int(np.count_nonzero(stalled))
            wait &= ~stalled
        self._keep_waiting(batch.part(wait), held)
        self._set_pending()

    def _object_poses_at(self, times: Times, k: Rows, interpolate: Bools
                         ) -> tuple[Matrices, Points]:
        """Rotation matrices (U, 3, 3) and positions (U, 3) of the object at ``times``.

        ``k`` is the object pose at or after each time; where ``interpolate`` is False it is
        exactly at that time and used as is, elsewhere the pose is interpolated between
        ``k - 1`` and ``k``. Done in blocks so that the temporaries of slerp and the matrix
        conversion stay in cache: about twice as fast as one pass over a million stamps.
        """
        obj_t, obj_p, obj_q = self._obj_t, self._obj_p, self._obj_q
        rot = np.empty((times.size, 3, 3))
        pos = np.empty((times.size, 3))
        for start in range(0, times.size, _BLOCK):
            block = slice(start, start + _BLOCK)
            kb = k[block]
            q = obj_q[kb]
            pos[block] = obj_p[kb]
            between = np.flatnonzero(interpolate[block])
            if between.size:
                k1 = kb[between]
                k0 = k1 - 1
                t0 = obj_t[k0]
                frac = (times[block][between] - t0) / (obj_t[k1] - t0)
                q[between] = slerp(obj_q[k0], obj_q[k1], frac)
                p0 = obj_p[k0]
                pos[start + between] = p0 + frac[:, None] * (obj_p[k1] - p0)
            rot[block] = quaternion_to_matrix(q)
        return rot, pos

    def _keep_from(self, now: float | None) -> float:
        """Oldest object time that can still be needed (see the module docstring)."""
        return min(self._watermark(now), self._pending_min_t, self._latest_t - HISTORY_SECONDS)

    def _trim_history(self, now: float | None = None) -> None:
        """Forget object poses no fingertip can need, keeping one bracketing the boundary."""
        n = self._n_obj
        if n < 2:
            return
        start = int(np.searchsorted(self._obj_t[:n], self._keep_from(now), side='right')) - 1
        if start <= 0:
            return
        keep = n - start
        self._obj_t[:keep] = self._obj_t[start:n]
        self._obj_p[:keep] = self._obj_p[start:n]
        self._obj_q[:keep] = self._obj_q[start:n]
        self._n_obj = keep
        # Shrink a buffer that grew for a burst, so a long run does not hold it forever.
        capacity = len(self._obj_t)
        if capacity > 4096 and keep < capacity // 4:
            self._resize(max(1024, 2 * keep))

    def _make_room(self) -> None:
        # Object poses come without a clock; the last one given decides what is stale (an
        # expected finger not heard yet keeps the poses its first points will need).
        self._trim_history(self._clock)
        if self._n_obj > 3 * len(self._obj_t) // 4:
            self._resize(2 * len(self._obj_t))

    def _resize(self, capacity: int) -> None:
        n = self._n_obj
        for name, shape in (('_obj_t', (capacity,)), ('_obj_p', (capacity, 3)),
                            ('_obj_q', (capacity, 4))):
            old = getattr(self, name)
            new = np.empty(shape)
            new[:n] = old[:n]
            setattr(self, name, new)
