"""What the live view's page shows, kept up to date from the graph (plain numpy, no ROS).

The node hands every decoded message to a :class:`ViewState` (from the executor thread); the
page's HTTP thread asks it for a :meth:`ViewState.snapshot` as JSON-ready data. One lock
guards both sides. What it holds:

* the latest map (``occupancy/cloud``): the cells with evidence (probability above the
  prior, or hit at least once; at most ``max_cells``, the most probable first), their
  probability, the most explored region (:func:`inhand_tools.map_regions.regions`: the
  ``explored_fraction`` of the hit cells with the most hits, as ``render_map`` draws it),
  and the camera's colour of each cell ``occupancy/textured`` colours;
* the fingertips (``registration/points``): each finger's last ``trail_seconds`` of path;
* the frames (:class:`~inhand_view.frame_tree.FrameTree`), as poses in the map's frame
  (``object``) and in the tracker's (``polhemus_source``: the parent of the map's frame);
* counters: cells, occupied cells, fingertip points, messages and rates per topic, the
  latest ``diagnostics`` statuses and the answers of the reset and save calls.

Positions go to the page as integers in tenths of a millimetre and probabilities in
thousandths: a map of 100,000 cells is then about 3 MB of JSON, sent only when it changed
(the page says which map version it has). A whole 70^3 grid takes 53 ms here to take in
and as long to send.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from inhand_common.packed_rgb import colours_of_rgb
from inhand_common.ros_names import MAP_FRAME, TRACKER_FRAME
from inhand_tools.map_regions import regions
from inhand_view.frame_tree import FrameTree, Transform

__all__ = ['POSITION_UNIT', 'ViewSettings', 'ViewState', 'cell_keys']

POSITION_UNIT = 1e-4          # m per unit of the positions sent to the page (0.1 mm)
PRIOR = 0.5                   # a cell at or below this with no hit has no evidence of a surface
TRAIL_POINTS = 400            # at most this many points of each trail go to the page
TRAIL_KEEP = 20000            # at most this many points of each trail are kept
RATE_WINDOW = 3.0             # s over which message rates are measured
DEFAULT_RESOLUTION = 0.005    # m: a map of one cell does not say its cell size


@dataclass(frozen=True)
class ViewSettings:
    trail_seconds: float = 3.0
    explored_fraction: float = 0.1
    max_cells: int = 100_000
    finger_labels: tuple[str, ...] = ('thumb', 'index', 'middle')
    page_rate: float = 5.0


def cell_keys(centres: np.ndarray) -> np.ndarray:
    """One int64 per cell centre (N, 3), equal for equal centres: each coordinate rounded
    to 0.1 mm in 21 bits (+-104 m)."""
    units = np.rint(np.asarray(centres, dtype=np.float64) / POSITION_UNIT).astype(np.int64)
    units += 1 << 20
    return (units[:, 0] << 42) | (units[:, 1] << 21) | units[:, 2]


def _lattice_step(values: np.ndarray) -> float:
    """The smallest spacing between distinct coordinates: the map's cell edge."""
    distinct = np.unique(np.round(values.astype(np.float64), 6))
    steps = np.diff(distinct)
    steps = steps[steps > 1e-6]
    return float(steps.min()) if len(steps) else DEFAULT_RESOLUTION


def _units(points: np.ndarray) -> list[int]:
    units: list[int] = np.rint(np.asarray(points, dtype=np.float64).reshape(-1)
                               / POSITION_UNIT).astype(np.int64).tolist()
    return units


def _pose_list(pose: np.ndarray) -> list[float]:
    """A 4x4 pose as [R row-major (9), t (3)], rounded for the page."""
    return [round(float(v), 6) for v in (*pose[:3, :3].reshape(-1), *pose[:3, 3])]


def _no_cells() -> dict[str, Any]:
    return {'resolution': DEFAULT_RESOLUTION, 'position': [], 'probability': [], 'hits': [],
            'explored': []}


class _MapCells(NamedTuple):
    keys: np.ndarray          # (N,) cell_keys, ascending
    centres: np.ndarray       # (N, 3) m
    probability: np.ndarray   # (N,)
    hits: np.ndarray          # (N,) int64
    first_touch: np.ndarray   # (N,) s, NaN where unknown

    @classmethod
    def empty(cls) -> _MapCells:
        return cls(np.empty(0, dtype=np.int64), np.empty((0, 3)), np.empty(0),
                   np.empty(0, dtype=np.int64), np.empty(0))


@dataclass
class _Trail:
    times: np.ndarray = field(default_factory=lambda: np.empty(0))
    points: np.ndarray = field(default_factory=lambda: np.empty((0, 3), dtype=np.float32))


class ViewState:
    """Thread-safe: the node's callbacks write, the page's requests read."""

    def __init__(self, settings: ViewSettings, clock: Callable[[], float] = time.monotonic):
        self.settings = settings
        self.clock = clock
        self.lock = threading.Lock()
        self.map_version = 0
        self._cells: dict[str, Any] = _no_cells()
        self._grid = _MapCells.empty()       # every cell of the latest map, sorted by key
        self._map_dirty = False               # _cells, _map_keys, _map_counts behind _grid
        self._map_frame = MAP_FRAME
        self._map_keys = np.empty(0, dtype=np.int64)     # keys of the shown cells
        self._map_counts = {'cells': 0, 'shown_cells': 0, 'hit_cells': 0, 'explored_cells': 0,
                            'explored_min_hits': None}
        self._texture: tuple[np.ndarray, np.ndarray] | None = None   # sorted keys, rgb ints
        self._occupied: int | None = None
        self._trails: dict[int, _Trail] = {}
        self._points = 0
        self._frames = FrameTree()
        self._arrivals: dict[str, deque[float]] = {}
        self._messages: dict[str, int] = {}
        self._diagnostics: dict[str, dict[str, Any]] = {}
        self._services: dict[str, bool] = {}
        self._calls: dict[str, dict[str, Any]] = {}
        self._topics = 0
        self._foxglove: dict[str, Any] = {}
        self._shape: dict[str, Any] | None = None
        self._exploration: dict[str, Any] | None = None

    # ------------------------------------------------------------------ map
    def set_map(self, cells: np.ndarray, frame: str = MAP_FRAME) -> None:
        """The latest ``occupancy/cloud``: any structured array with ``x y z intensity hits``
        (and ``first_touch``)."""
        centres = np.stack([cells['x'], cells['y'], cells['z']], axis=1).astype(np.float64)
        names = cells.dtype.names or ()
        first_touch = (np.asarray(cells['first_touch'], dtype=float) if 'first_touch' in names
                       else np.full(len(centres), np.nan))
        keys = cell_keys(centres)
        order = np.argsort(keys)
        grid = _MapCells(keys[order], centres[order],
                         np.asarray(cells['intensity'], dtype=np.float64)[order],
                         np.asarray(cells['hits'], dtype=np.int64)[order], first_touch[order])
        with self.lock:
            self._grid = grid
            self._map_frame = frame
            self._map_dirty = True
            self.map_version += 1

    def apply_updates(self, cells: np.ndarray, frame: str = MAP_FRAME) -> None:
        """An ``occupancy/updates`` message (map_updates.py): the cells whose probability
        changed, and the provisional cells where the fingertips are now, merged into the
        latest map so the page follows a finger between whole maps."""
        if not len(cells):
            return
        centres = np.stack([cells['x'], cells['y'], cells['z']], axis=1).astype(np.float64)
        keys = cell_keys(centres)
        probability = np.asarray(cells['intensity'], dtype=np.float64)
        hits = np.asarray(cells['hits'], dtype=np.int64)
        with self.lock:
            grid = self._grid
            at = np.minimum(np.searchsorted(grid.keys, keys), max(len(grid.keys) - 1, 0))
            known = (grid.keys[at] == keys) if len(grid.keys) else np.zeros(len(keys), bool)
            grid.probability[at[known]] = probability[known]
            grid.hits[at[known]] = hits[known]
            new = ~known
            if new.any():
                merged = _MapCells(np.concatenate([grid.keys, keys[new]]),
                                   np.concatenate([grid.centres, centres[new]]),
                                   np.concatenate([grid.probability, probability[new]]),
                                   np.concatenate([grid.hits, hits[new]]),
                                   np.concatenate([grid.first_touch,
                                                   np.full(int(new.sum()), np.nan)]))
                order = np.argsort(merged.keys, kind='stable')
                self._grid = _MapCells(*(part[order] for part in merged))
            self._map_frame = frame
            self._map_dirty = True
            self.map_version += 1

    def _encode_map(self) -> None:
        """What the page gets of the map (under the lock, once per map version asked for)."""
        grid = self._grid
        probability, hits = grid.probability, grid.hits
        most, _, hit_cut, _ = regions(hits, grid.first_touch, self.settings.explored_fraction)
        shown = np.flatnonzero((probability > PRIOR) | (hits > 0))
        if len(shown) > self.settings.max_cells:
            keep = np.argpartition(-probability[shown], self.settings.max_cells - 1)
            shown = np.sort(shown[keep[:self.settings.max_cells]])
        centres = grid.centres
        resolution = _lattice_step(centres[shown, 0]) if len(shown) > 1 else DEFAULT_RESOLUTION
        self._map_keys = grid.keys[shown]
        self._map_counts = {'cells': int(len(hits)), 'shown_cells': int(len(shown)),
                            'hit_cells': int(np.count_nonzero(hits)),
                            'explored_cells': int(np.count_nonzero(most)),
                            'explored_min_hits': None if math.isnan(hit_cut) else int(hit_cut)}
        self._cells = {
            'resolution': round(resolution, 6),
            'position': _units(centres[shown]),
            'probability': np.rint(probability[shown] * 1000).astype(np.int64).tolist(),
            'hits': hits[shown].tolist(),
            'explored': most[shown].astype(np.int8).tolist(),
        }
        self._map_dirty = False

    def set_occupied(self, count: int) -> None:
        """How many cells ``occupancy/occupied`` holds."""
        with self.lock:
            self._occupied = int(count)

    def set_textured(self, cells: np.ndarray) -> None:
        """The latest ``occupancy/textured``: ``x y z rgb textured`` of the occupied cells."""
        seen = np.asarray(cells['textured']).astype(bool)
        centres = np.stack([cells['x'], cells['y'], cells['z']], axis=1)[seen]
        colours = colours_of_rgb(np.asarray(cells['rgb'])[seen]).astype(np.int64)
        rgb = (colours[:, 0] << 16) | (colours[:, 1] << 8) | colours[:, 2]
        keys = cell_keys(centres)
        order = np.argsort(keys)
        with self.lock:
            self._texture = (keys[order], rgb[order])
            self.map_version += 1

    def _cell_colours(self) -> list[int] | None:
        """The camera's colour (0xRRGGBB) of each shown cell, -1 where it has none."""
        if self._texture is None or not len(self._map_keys):
            return None
        keys, rgb = self._texture
        if not len(keys):
            return None
        at = np.minimum(np.searchsorted(keys, self._map_keys), len(keys) - 1)
        found = keys[at] == self._map_keys
        colours: list[int] = np.where(found, rgb[at], -1).tolist()
        return colours

    # ------------------------------------------------------------------ fingertips
    def add_registered(self, points: np.ndarray, fingers: np.ndarray, times: np.ndarray) -> None:
        """A ``registration/points`` batch: (N, 3) positions in ``object``, finger indices,
        stamps (s)."""
        points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        fingers = np.asarray(fingers)
        times = np.asarray(times, dtype=np.float64)
        with self.lock:
            self._points += len(points)
            for finger in np.unique(fingers).tolist():
                mine = fingers == finger
                trail = self._trails.setdefault(int(finger), _Trail())
                new_times = times[mine]
                if len(trail.times) and new_times[0] < trail.times[-1] - 1.0:
                    trail = self._trails[int(finger)] = _Trail()   # time went back: a new run
                trail.times = np.concatenate([trail.times, new_times])[-TRAIL_KEEP:]
                trail.points = np.concatenate([trail.points, points[mine]])[-TRAIL_KEEP:]
                recent = trail.times >= trail.times[-1] - self.settings.trail_seconds
                trail.times, trail.points = trail.times[recent], trail.points[recent]

    def _fingers(self) -> list[dict[str, Any]]:
        labels = self.settings.finger_labels
        out = []
        for finger, trail in sorted(self._trails.items()):
            if not len(trail.points):
                continue
            step = max(1, math.ceil(len(trail.points) / TRAIL_POINTS))
            path = trail.points[::-1][::step][::-1]           # keeps the newest point
            out.append({'index': finger,
                        'label': labels[finger] if finger < len(labels) else f'finger {finger}',
                        'tip': _units(trail.points[-1]), 'trail': _units(path)})
        return out

    # ------------------------------------------------------------------ frames
    def add_transform(self, transform: Transform) -> bool:
        with self.lock:
            return self._frames.add(transform)

    def _frame_poses(self) -> dict[str, Any]:
        """Every known frame's pose in the map's frame (the map cloud's ``frame_id``) and in
        its parent, the tracker's frame (from the map frame's latest transform), so a frame
        prefix (``left_hand/object``) needs no setting."""
        to_map = self._frames.latest(self._map_frame)
        tracker = to_map.parent if to_map is not None else None

        def poses(frame: str | None) -> dict[str, list[float]]:
            found = self._frames.poses_in(frame) if frame else {}
            return {name: _pose_list(pose) for name, pose in found.items()}
        return {'map_frame': self._map_frame, 'tracker_frame': tracker or TRACKER_FRAME,
                'map': poses(self._map_frame), 'tracker': poses(tracker)}

    # ------------------------------------------------------------------ counters
    def message_arrived(self, topic: str) -> None:
        now = self.clock()
        with self.lock:
            arrivals = self._arrivals.setdefault(topic, deque())
            arrivals.append(now)
            while arrivals and arrivals[0] < now - RATE_WINDOW:
                arrivals.popleft()
            self._messages[topic] = self._messages.get(topic, 0) + 1

    def _rates(self) -> dict[str, dict[str, float | int]]:
        now = self.clock()
        out = {}
        for topic, arrivals in sorted(self._arrivals.items()):
            while arrivals and arrivals[0] < now - RATE_WINDOW:
                arrivals.popleft()
            out[topic] = {'messages': self._messages[topic],
                          'rate': round(len(arrivals) / RATE_WINDOW, 2)}
        return out

    def set_topics(self, count: int, foxglove: dict[str, Any]) -> None:
        """How many topics the node forwards, and the Foxglove server's address."""
        with self.lock:
            self._topics = count
            self._foxglove = dict(foxglove)

    def set_diagnostics(self, statuses: Sequence[dict[str, Any]]) -> None:
        """Statuses of a ``diagnostics`` message (name, level, message, values as pairs);
        the latest of each name is kept."""
        with self.lock:
            for status in statuses:
                self._diagnostics[status['name']] = dict(status)

    def set_shape(self, items: Sequence[tuple[str, str, np.ndarray, Sequence[float]]],
                  frame: str = MAP_FRAME) -> None:
        """The shape_node's parts and grasps (``shape/parts``): (name, kind ``triangles`` or
        ``lines``, points (N, 3) m, rgba 0-1) each, in ``frame``."""
        with self.lock:
            self._shape = {'frame': frame, 'items': [
                {'name': name, 'kind': kind, 'points': _units(points),
                 'rgba': [round(float(c), 3) for c in rgba]} for name, kind, points, rgba in items]}
            # sent with the map, when the page's version is behind (it changes on request)
            self.map_version += 1

    def set_uncertainty(self, points: np.ndarray, std: np.ndarray, frame: str = MAP_FRAME) -> None:
        """The exploration node's predicted surface (``exploration/uncertainty``): its vertices
        (N, 3) m and their standard deviations (m), in ``frame``."""
        with self.lock:
            touches = (self._exploration or {}).get('touches', [])
            self._exploration = {'frame': frame, 'points': _units(points), 'touches': touches,
                                 'std_um': np.rint(np.asarray(std, dtype=np.float64) * 1e6)
                                 .astype(np.int64).tolist()}
            self.map_version += 1

    def set_next_touches(self, arrows: Sequence[tuple[np.ndarray, np.ndarray]],
                         frame: str = MAP_FRAME) -> None:
        """The exploration node's ranked next touches (``exploration/next_touches``): each an
        arrow (start, end on the surface) in m, best first, in ``frame``."""
        with self.lock:
            current = self._exploration or {'points': [], 'std_um': []}
            self._exploration = dict(current, frame=frame, touches=[
                _units(np.stack([start, end])) for start, end in arrows])
            self.map_version += 1

    def set_services(self, available: dict[str, bool]) -> None:
        with self.lock:
            self._services = dict(available)

    def record_call(self, name: str, success: bool, message: str) -> None:
        with self.lock:
            self._calls[name] = {'success': bool(success), 'message': message,
                                 'time': time.time()}

    # ------------------------------------------------------------------ the page's view
    def snapshot(self, since: int | None = None) -> dict[str, Any]:
        """Everything the page shows; the map's cells (and the shape node's parts) only when
        ``since`` is not the current map version."""
        with self.lock:
            if self._map_dirty:
                self._encode_map()
            counts = dict(self._map_counts)
            counts.update(occupied_cells=self._occupied, fingertip_points=self._points,
                          transforms=self._frames.received,
                          refused_transforms=self._frames.refused, topics=self._topics)
            state: dict[str, Any] = {
                'map_version': self.map_version,
                'map_frame': self._map_frame,
                'counts': counts,
                'rates': self._rates(),
                'fingers': self._fingers(),
                'frames': self._frame_poses(),
                'diagnostics': [self._diagnostics[k] for k in sorted(self._diagnostics)],
                'services': dict(self._services),
                'calls': dict(self._calls),
                'foxglove': dict(self._foxglove),
                'settings': {'page_rate': self.settings.page_rate,
                             'trail_seconds': self.settings.trail_seconds,
                             'explored_fraction': self.settings.explored_fraction,
                             'position_unit': POSITION_UNIT},
            }
            if since != self.map_version:
                state['map'] = dict(self._cells, colour=self._cell_colours())
                state['shape'] = self._shape
                state['exploration'] = self._exploration
        return state
