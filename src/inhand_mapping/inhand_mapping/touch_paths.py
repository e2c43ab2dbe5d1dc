"""The path touch model: evidence from the fingertip's path through the cells, per visit.

A tracker samples a fingertip at 15-240 Hz, but the finger slid along a path between the
samples: at 15 Hz and 15 cm/s the samples are 10 mm apart and skip the 5 mm cells between
them. Counting samples (the paper, and dwell.py) makes evidence depend on the rate and the
speed. This model counts what the finger did instead.

1. **The path.** Each finger's samples, in time order, form tracks (a gap over
   ``TRACK_GAP`` ends one). The path is the straight segments between consecutive *raw*
   samples (a smoothed path cuts inside a curved surface at 15 Hz), walked in equal steps
   of at most a fifth of a cell; each step is a moment in the cell under its midpoint.
2. **Sliding or flying.** A slide over the surface is slow; a transit between strokes, a
   lift-off and a touch-down reach ballistic speeds. The velocity at each sample is the
   slope of a least-squares line through the samples within +-``SPEED_WINDOW`` (and at
   least its two neighbours, so 1 mm of noise over one 240 Hz step is not 0.24 m/s); the
   moment's *context speed* ``v`` is the fastest of these within +-``speed_context``, so
   the slow ends of a transit count as the transit. The slide factor is

       g = min(1, (transit_speed / v)^transit_falloff).

3. **Visits.** The steps of one finger in one cell form a visit; the finger back in the
   cell less than ``visit_gap`` after it was last there continues the visit. A visit has
   its time in the cell ``dwell``, its mean slide factor ``g`` (weighted by time), and its
   *through-ness* ``through = min(1, |exit - entry| / cell)``, the distance from where it
   first entered the cell to where it last was, in cells: a stroke across the cell gives
   1; a lift that comes back down where it went up, a hover, a finger that rests and
   jitters give about 0. Its worth, in measurements, is

       worth = g * (1 - RETURN_SHARE * (1 - through) + min(1, through * dwell / pass_time)):

   a touch (1 if the finger went through the cell, 1/2 if it left where it came in), plus
   up to one more for a slow pass: sliding through a cell for ``pass_time`` or longer is
   two measurements, as two samples at the paper's 15 Hz would be.
4. **The update.** A cell's log-odds are eq. 4 with the touches at distance 0 (eq. 3 gives
   L = 1 inside the cell): ``l = clamp(l0 + sum(worth) * log(1 / c))``, with the clamp on
   the sum (the touch map only ever gains evidence, so clamping once is clamping after
   every update). One touch: p = 0.69, under the 0.7 of the paper's noise threshold; a
   slow pass, or two independent touches: 0.83, over 0.8.

5. **The surface layer** (surface_layer.py): the map read keeps ``layer_factor`` of the
   evidence of a cell that has less than the cell one step along the local surface normal
   (the layer above the surface, where lift-offs, set-downs and hovers pass), and counts
   ``sheet_gain`` times the evidence of a cell of a flat sheet. The kernels
   mark the cells whose evidence changed (``PathCounts.dirty``); :meth:`TouchPaths.apply_layer`
   brings their neighbourhoods up to date when the grid is read.

The paper's concern holds: repeated involuntary movements at one place, off the surface,
are one visit of small through-ness, whatever their number, so they stay under 0.8.

Streaming: a sample's context speed needs ``speed_context + SPEED_WINDOW`` of the finger's
future, so each finger's newest samples wait (``pending``) until that has arrived, its
track ends (a gap, another finger's time moving on past the gap), or the stream is
flushed. A visit's worth is recomputed at each of its steps and its change added to the
cell, so the map always shows the path walked so far. Every decision is taken at a sample
of the stream, so the map does not depend on how the stream is cut into calls. Time going
back for a finger starts a new stream for it (its visits are forgotten).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from inhand_common.array_types import CellFloats, FingerIds, Points, Times
from inhand_mapping import path_kernels as kernels
from inhand_mapping import surface_layer
from inhand_mapping.occupancy_kernels import CellArrays, GridGeometry

__all__ = ['RETURN_SHARE', 'SPEED_WINDOW', 'STEPS_PER_CELL', 'TRACK_GAP', 'TouchPaths']

SPEED_WINDOW = 0.1    # s: half-width of the local fit (three samples at 15 Hz, 49 at 240)
TRACK_GAP = 0.25      # s: a longer silence of a finger (lost tracking) breaks its path
STEPS_PER_CELL = 5    # the path is walked in steps of at most a fifth of a cell
PASS_GAP = 0.5       # s: out of a cell shorter than this (noise, a wobble) is one pass
RETURN_SHARE = 0.65   # what a visit that leaves where it came in loses of its touch
STAY_CELLS = 2        # a finger within two cells (1 cm) of where it was is still at one place
SAMPLES_HELD = 4096   # per finger: the track's samples the speeds still need (0.6 s at 240 Hz: 150)
VISITS_KEPT = 4096    # per finger: recent visits; more within visit_gap are forgotten early


class TouchPaths:
    """The path model's state over a grid's cell arrays (see the module docstring).

    ``evidence`` (n^3,) is each cell's sum of visit worths, in measurements; the grid's
    log-odds follow it. Finger rows are added as finger ids appear.
    """

    def __init__(self, geometry: GridGeometry, cells: CellArrays, *, p_z_given_not_occupied: float,
                 prior: float, clamp_min: float, clamp_max: float, transit_speed: float,
                 transit_falloff: float, speed_context: float, pass_time: float,
                 visit_gap: float, layer_factor: float, sheet_gain: float):
        self.geometry = geometry
        self.layer_factor = layer_factor
        self.sheet_gain = sheet_gain
        self.cells = cells
        step = geometry.resolution / STEPS_PER_CELL
        # A segment longer than the grid's diagonal, twice, is a glitch: walked coarsely.
        max_steps = int(math.ceil(2.0 * math.sqrt(3.0) * geometry.n * geometry.resolution / step))
        self.model = kernels.PathModel(
            transit_speed=transit_speed, transit_falloff=transit_falloff,
            speed_context=speed_context, speed_window=SPEED_WINDOW,
            track_gap=TRACK_GAP, pass_time=pass_time, pass_gap=PASS_GAP,
            return_share=RETURN_SHARE,
            visit_gap=visit_gap, stay_radius=STAY_CELLS * geometry.resolution, step=step, max_steps=max_steps,
            log_odds_per_touch=-math.log(p_z_given_not_occupied),
            prior=math.log(prior / (1.0 - prior)),
            l_min=math.log(clamp_min / (1.0 - clamp_min)),
            l_max=math.log(clamp_max / (1.0 - clamp_max)))
        self.evidence: CellFloats = np.zeros(geometry.n ** 3)
        self._changed = np.empty(min(kernels.CHANGED_BUFFER, geometry.n ** 3), dtype=np.int64)
        size = geometry.n ** 3
        self.counts = kernels.PathCounts(
            clock=np.full(1, -np.inf), overwritten=np.zeros(1, dtype=np.int64),
            dirty_mark=np.zeros(size, dtype=np.bool_), dirty=np.empty(size, dtype=np.int64),
            n_dirty=np.zeros(1, dtype=np.int64))
        self._region = np.empty(size, dtype=np.int64)   # scratch of apply_layer
        # each cell's evidence after the layer rules, before its support, whether the
        # bridge applies to it, its local normal (surface_layer.py; zeros: not computed, any neighbour
        # supports it) and its evidence held to its support, before the bridge
        self.layered: CellFloats = np.zeros(size)
        self.bridgeable = np.zeros(size, dtype=np.bool_)
        self.normals = np.zeros((size, 3), dtype=np.float32)
        self.supported: CellFloats = np.zeros(size)
        self.tracks = self._new_tracks(0)
        self.visits = self._new_visits(0)

    # ------------------------------------------------------------------ stream
    def push(self, points: Points, times: Times, fingers: FingerIds) -> tuple[int, int, int, float]:
        """Timed samples in stream order. Returns (integrated, outside, invalid, earliest
        time touched)."""
        if len(fingers):
            self._grow(int(fingers.max()) + 1)
        result: tuple[int, int, int, float] = kernels.push_samples(
            points, times, fingers, self.geometry, self.model, self.cells, self.evidence,
            self.tracks, self.visits, self.counts, self._changed)
        return result

    def add_points(self, points: Points) -> tuple[int, int, int]:
        """Untimed points, each one touch of its cell."""
        result: tuple[int, int, int] = kernels.add_points(
            points, self.geometry, self.model, self.cells, self.evidence, self.counts,
            self._changed)
        return result

    def flush(self) -> float:
        """The end of the stream: every open track is walked to its end. Returns the
        earliest time touched."""
        return float(kernels.end_tracks(self.geometry, self.model, self.cells, self.evidence,
                                        self.tracks, self.visits, self.counts, self._changed))

    def apply_layer(self) -> int:
        """Bring the cells around every cell whose evidence changed since the last call up
        to date with the surface layer (surface_layer.py): their log-odds and probability.
        Returns how many cells were recomputed."""
        counts = self.counts
        n_dirty = int(counts.n_dirty[0])
        if n_dirty == 0:
            return 0
        done = int(surface_layer.apply_layer(
            self.evidence, self.geometry.n, self.layer_factor, self.sheet_gain, self.model,
            counts.dirty, n_dirty, counts.dirty_mark, self._region, self.layered,
            self.bridgeable, self.normals, self.supported, self.cells.log_odds,
            self.cells.probability))
        counts.n_dirty[0] = 0
        return done

    @property
    def pending(self) -> int:
        """Samples taken whose path has not been walked to yet."""
        return int((self.tracks.held - self.tracks.walked).sum())

    def held_points(self) -> Points:
        """(M, 3) positions of the samples taken whose path is not walked yet: where the
        fingertips are now, before their speeds settle (a live view shows these cells at
        once; their evidence comes a look-ahead later)."""
        tracks = self.tracks
        slot = np.arange(tracks.t.shape[1])
        held = (slot >= tracks.walked[:, None]) & (slot < tracks.held[:, None])
        points: Points = tracks.p[held]
        return points

    @property
    def overwritten_visits(self) -> int:
        """Visits dropped within their gap because a finger's ring of visits was full."""
        return int(self.counts.overwritten[0])

    def reset(self) -> None:
        """Forget the tracks, the visits and the evidence (the cells are the grid's)."""
        self.evidence.fill(0.0)
        self.layered.fill(0.0)
        self.bridgeable.fill(False)
        self.normals.fill(0.0)
        self.supported.fill(0.0)
        self.counts.clock.fill(-np.inf)
        self.counts.overwritten.fill(0)
        self._clear_dirty()
        fingers = len(self.tracks.held)
        self.tracks = self._new_tracks(fingers)
        self.visits = self._new_visits(fingers)

    def follow(self, log_odds: ArrayLike) -> None:
        """Evidence that gives these log-odds (a map loaded or set directly): touches go on
        from there. Clamped cells keep only the evidence of their clamp."""
        self.evidence[...] = ((np.asarray(log_odds, dtype=float).reshape(-1) - self.model.prior)
                              / self.model.log_odds_per_touch)
        self.layered[...] = self.evidence    # as shown: a neighbour's support and bridge
        self.supported[...] = self.evidence
        self.bridgeable.fill(False)
        self.normals.fill(0.0)
        self._clear_dirty()     # the log-odds given are the map shown

    def restore(self, evidence: ArrayLike) -> None:
        """Evidence saved with a map whose log-odds the grid holds (map_io): touches go on
        from it as they would have."""
        self.evidence[...] = np.asarray(evidence, dtype=float).reshape(-1)
        # ``layered`` and ``supported`` stay the evidence of the log-odds shown (``follow``):
        # the saved map is the map read, and a cell next to later touches lends them its
        # support and bridge as shown
        self._clear_dirty()

    def _clear_dirty(self) -> None:
        self.counts.dirty_mark.fill(False)
        self.counts.n_dirty[0] = 0

    # ------------------------------------------------------------------ state
    def take_state(self, other: TouchPaths) -> None:
        """Become a copy of ``other``'s tracks, visits and evidence (a grid's settled copy,
        occupancy.py); the cells are this one's own."""
        self.evidence[...] = other.evidence
        self.layered[...] = other.layered
        self.bridgeable[...] = other.bridgeable
        self.normals[...] = other.normals
        self.supported[...] = other.supported
        self.tracks = kernels.PathTracks._make(field.copy() for field in other.tracks)
        self.visits = kernels.PathVisits._make(field.copy() for field in other.visits)
        self.counts = kernels.PathCounts._make(field.copy() for field in other.counts)

    def _grow(self, fingers: int) -> None:
        have = len(self.tracks.held)
        if fingers <= have:
            return
        tracks, visits = self._new_tracks(fingers), self._new_visits(fingers)
        for old, new in ((self.tracks, tracks), (self.visits, visits)):
            for name in old._fields:
                getattr(new, name)[:have] = getattr(old, name)
        self.tracks, self.visits = tracks, visits

    @staticmethod
    def _new_tracks(fingers: int) -> kernels.PathTracks:
        held = SAMPLES_HELD
        return kernels.PathTracks(
            t=np.zeros((fingers, held)), p=np.zeros((fingers, held, 3)),
            speed=np.zeros((fingers, held)), smooth=np.zeros((fingers, held, 3)),
            context=np.zeros((fingers, held)), peaks=np.zeros((fingers, held), dtype=np.int64),
            peaks_from=np.zeros(fingers, dtype=np.int64), peaks_to=np.zeros(fingers, dtype=np.int64),
            entered=np.zeros(fingers, dtype=np.int64), fit_lo=np.zeros(fingers, dtype=np.int64),
            fit_hi=np.zeros(fingers, dtype=np.int64),
            held=np.zeros(fingers, dtype=np.int64), known=np.zeros(fingers, dtype=np.int64),
            walked=np.zeros(fingers, dtype=np.int64), newest=np.full(fingers, -np.inf))

    def _new_visits(self, fingers: int) -> kernels.PathVisits:
        kept, cells = VISITS_KEPT, self.geometry.n ** 3
        return kernels.PathVisits(
            cell=np.full((fingers, kept), -1, dtype=np.int64),
            last=np.full((fingers, kept), -np.inf), through=np.zeros((fingers, kept)),
            pass_entry=np.zeros((fingers, kept, 3)), pass_through=np.zeros((fingers, kept)),
            dwell=np.zeros((fingers, kept)), g_dwell=np.zeros((fingers, kept)),
            v_dwell=np.zeros((fingers, kept)), worth=np.zeros((fingers, kept)),
            stay=np.zeros((fingers, kept), dtype=np.int64), anchor=np.full((fingers, 3), np.nan),
            stay_id=np.zeros(fingers, dtype=np.int64),
            head=np.zeros(fingers, dtype=np.int64), current=np.full(fingers, -1, dtype=np.int64),
            # a slot per finger and cell: a cell's visit found at once, not by scanning the
            # ring (4 B a cell and finger; the grid keeps about 70 B a cell)
            slot_of=np.zeros((fingers, cells), dtype=np.int32))
