"""Compiled loops of the path touch model (numba), used only by touch_paths.py.

Why compiled: the model walks each fingertip's path in steps of a fifth of a cell and keeps,
per finger, the visits of the last few seconds; every step looks at its visit and updates
one cell. That is sequential state per finger, which numpy cannot express without a
Python loop per step. The maths is described in touch_paths.py.

The per-sample and per-step helpers (``_advance``, ``_fit``, ``_walk``, ``_visit_step``,
``_enter``) are compiled into the entry points (``_inlined``): as calls, each took and
dropped a reference on every array of the state tuples it was passed, about 30% of the
time (perf); inlined, ``bench_mapping``'s fingertip stream runs 1.3x faster, the map the
same to the bit, for 8 s more of compiling on a cold cache (``compile_kernels``).

Inlined, they still took those references: numba binds each argument to a name of the
inlined body, and a state tuple bound is an atomic increment (and later decrement) of every
array in it, about a hundred per sample, four fifths of the time (perf). The kernels
therefore run without reference counting (``_uncounted``): they allocate nothing (the
steps pass positions as scalars rather than (3,) arrays), and every array they index, or
view, belongs to the caller for the whole call. ``bench_mapping``'s stream runs 5x faster,
the map the same to the bit.

The stream is processed sample by sample, in the order given, and every decision (a
sample's speed is settled, a track has ended, a visit is new) is taken at a sample of the
stream, never at the end of a call: the map therefore does not depend on how the stream was
cut into calls.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from inhand_common.array_types import CellFloats, FingerIds, Floats, Indices, Points, Times
from inhand_mapping.occupancy_kernels import (
    CellArrays,
    GridGeometry,
    _add_position,
    _inlined,
    _refresh_probability,
    _uncounted,
)

__all__ = ['PathCounts', 'PathModel', 'PathTracks', 'PathVisits', 'add_points', 'end_tracks',
           'push_samples']

# Cells whose probability waits for a refresh, at most: beyond it they are refreshed at once.
CHANGED_BUFFER = 1 << 16


class PathModel(NamedTuple):
    """The path model's parameters, in the kernel's units (see touch_paths.py)."""

    transit_speed: float   # m/s: above it the finger is taken to be in the air
    transit_falloff: float  # faster than that, evidence scales as (transit_speed / speed)^this
    speed_context: float   # s: the fastest speed within +- this judges a moment
    speed_window: float    # s: half-width of the local linear fit giving the velocity
    track_gap: float       # s: a longer gap between two samples of a finger ends its track
    pass_time: float       # s: a slide that takes this long to cross a cell earns a second touch
    pass_gap: float        # s: out of a cell for less than this (noise) does not end a pass
    return_share: float    # what a visit that leaves where it came in loses of its touch
    visit_gap: float       # s: one finger back in a cell within this is the same visit
    stay_radius: float     # m: a finger whose path stays within this of a point is at one place
    step: float            # m: the path is walked in steps of at most this
    max_steps: int         # steps of one segment, at most (an absurd jump is walked coarsely)
    log_odds_per_touch: float  # -log P(Z | not O): eq. 4 for a touch inside the cell
    prior: float           # prior log-odds
    l_min: float           # log-odds clamps
    l_max: float


class PathTracks(NamedTuple):
    """Each finger's current track (rows): the samples still needed, oldest first."""

    t: Floats          # (F, B) s
    p: Floats          # (F, B, 3) m
    speed: Floats      # (F, B) |velocity| of the local fit, m/s, once settled
    smooth: Floats     # (F, B, 3) the local fit's position at the sample, once settled
    context: Floats    # (F, B) fastest speed within +- speed_context, once settled
    peaks: Indices     # (F, B) the samples of the context window that no later one of it is
                       # as fast as, in order (their speeds fall): the first is the fastest
    peaks_from: Indices  # (F,) where they start in ``peaks``
    peaks_to: Indices  # (F,) where they end
    entered: Indices   # (F,) leading samples that have entered the context window
    fit_lo: Indices    # (F,) the last fit's window, its first sample
    fit_hi: Indices    # (F,) and its last (before the two neighbours are added)
    held: Indices      # (F,) samples in the buffer; 0: no open track
    known: Indices     # (F,) leading samples whose speed is settled
    walked: Indices    # (F,) leading samples whose context is settled and path walked to
    newest: Floats     # (F,) time of the finger's newest sample; -inf: none yet


class PathVisits(NamedTuple):
    """Each finger's recent visits (rows): a ring in the order they were entered. A visit
    entered again moves to the front, so the ring is also in order of the last time spent
    in each, and the visits of the finger's current stay are the newest. ``slot_of`` finds
    a cell's visit in the ring (``_enter``)."""

    cell: Indices      # (F, R) flat cell index; -1: a slot moved to the front, or empty
    last: Floats       # (F, R) last time the finger was in the cell (s)
    through: Floats    # (F, R) how far through the cell the visit's finished passes went, at most (cells)
    pass_entry: Floats  # (F, R, 3) where the current pass entered the cell (smoothed path)
    pass_through: Floats  # (F, R) how far through the cell the current pass is, entry to now
    dwell: Floats      # (F, R) time spent in the cell (s)
    g_dwell: Floats    # (F, R) sum of the slide factor times the time
    v_dwell: Floats    # (F, R) sum of the fitted speed times the time (m)
    worth: Floats      # (F, R) measurements the visit has given so far
    stay: Indices      # (F, R) the finger's stay (place) when it was last in the cell
    anchor: Floats     # (F, 3) where the finger's current stay began; NaN: none yet
    stay_id: Indices   # (F,) the current stay's number
    head: Indices      # (F,) slots ever written (the next one is head % R)
    current: Indices   # (F,) slot of the visit the finger is in now; -1: none
    slot_of: np.ndarray  # (F, n^3) int32: the slot each cell's visit was last written to


class PathCounts(NamedTuple):
    """What the kernels keep between calls besides tracks and visits: scalars as
    one-element arrays, and the cells whose evidence changed since the surface layer
    (surface_layer.py) was last applied."""

    clock: Floats      # (1,) newest time of any finger
    overwritten: Indices  # (1,) visits within the gap dropped because a ring was full
    dirty_mark: np.ndarray  # (n^3,) bool: the cell is in ``dirty``
    dirty: Indices     # (n^3,) flat indices of the cells whose evidence changed
    n_dirty: Indices   # (1,) how many of ``dirty`` are in use


@_inlined
def _clamp(value: float, low: float, high: float) -> float:
    return min(max(value, low), high)


@_uncounted
def push_samples(points: Points, times: Times, fingers: FingerIds, geometry: GridGeometry,
                 model: PathModel, cells: CellArrays, evidence: CellFloats, tracks: PathTracks,
                 visits: PathVisits, counts: PathCounts, changed: Indices
                 ) -> tuple[int, int, int, float]:
    """Take timed samples in stream order: count each in its cell (hits, first touch), and
    walk every path segment whose ends' speeds became settled. Returns (integrated,
    outside, invalid, earliest step or sample time)."""
    inv_res, n, origin = geometry.inv_res, geometry.n, geometry.origin
    integrated = 0
    outside = 0
    invalid = 0
    earliest = np.inf
    n_changed = 0
    n_fingers = tracks.held.shape[0]
    for i in range(points.shape[0]):
        t = times[i]
        f = fingers[i]
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)
                and math.isfinite(t)):
            invalid += 1
            continue
        # The end of tracks: a gap, time going back (a new stream: its visits are new too),
        # or another finger's time far past this finger's newest sample.
        if tracks.held[f] > 0 and (t > tracks.newest[f] + model.track_gap
                                    or t < tracks.newest[f]):
            earliest, n_changed = _end_track(f, geometry, model, cells, evidence, tracks,
                                             visits, counts, changed, earliest, n_changed)
        if t < tracks.newest[f]:
            _forget_visits(f, visits)
        for g in range(n_fingers):
            if g != f and tracks.held[g] > 0 and t > tracks.newest[g] + model.track_gap:
                earliest, n_changed = _end_track(g, geometry, model, cells, evidence,
                                                 tracks, visits, counts, changed, earliest,
                                                 n_changed)
        counts.clock[0] = max(counts.clock[0], t)
        x = (px - origin[0]) * inv_res
        y = (py - origin[1]) * inv_res
        z = (pz - origin[2]) * inv_res
        if x < 0.0 or y < 0.0 or z < 0.0 or x >= n or y >= n or z >= n:
            outside += 1     # still part of the path: it may come back into the grid
        else:
            c = (int(x) * n + int(y)) * n + int(z)
            cells.hits[c] += 1
            _add_position(cells.contact_sum, c, px, py, pz)
            if not (cells.first_touch[c] <= t):
                cells.first_touch[c] = t
            earliest = min(earliest, t)
            integrated += 1
        if tracks.held[f] == tracks.t.shape[1] and not _compact(f, model, tracks):
            # Faster than the buffer holds (kHz): the track ends here rather than lose a sample.
            earliest, n_changed = _end_track(f, geometry, model, cells, evidence, tracks,
                                             visits, counts, changed, earliest, n_changed)
        k = tracks.held[f]
        tracks.t[f, k] = t
        tracks.p[f, k, 0] = px
        tracks.p[f, k, 1] = py
        tracks.p[f, k, 2] = pz
        tracks.held[f] = k + 1
        tracks.newest[f] = t
        earliest, n_changed = _advance(f, False, geometry, model, cells, evidence, tracks,
                                       visits, counts, changed, earliest, n_changed)
    _refresh_probability(cells, n, 0, changed, n_changed)
    return integrated, outside, invalid, earliest


@_uncounted
def end_tracks(geometry: GridGeometry, model: PathModel, cells: CellArrays,
               evidence: CellFloats, tracks: PathTracks, visits: PathVisits,
               counts: PathCounts, changed: Indices) -> float:
    """The end of the stream: every open track is walked to its last sample. Returns the
    earliest step time."""
    earliest = np.inf
    n_changed = 0
    for f in range(tracks.held.shape[0]):
        if tracks.held[f] > 0:
            earliest, n_changed = _end_track(f, geometry, model, cells, evidence, tracks,
                                             visits, counts, changed, earliest, n_changed)
    _refresh_probability(cells, geometry.n, 0, changed, n_changed)
    return earliest


@_uncounted
def add_points(points: Points, geometry: GridGeometry, model: PathModel, cells: CellArrays,
               evidence: CellFloats, counts: PathCounts, changed: Indices
               ) -> tuple[int, int, int]:
    """Untimed points: each is one touch of its cell (no path, no visits). Returns
    (integrated, outside, invalid)."""
    inv_res, n, origin = geometry.inv_res, geometry.n, geometry.origin
    integrated = 0
    outside = 0
    invalid = 0
    n_changed = 0
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
            invalid += 1
            continue
        x = (px - origin[0]) * inv_res
        y = (py - origin[1]) * inv_res
        z = (pz - origin[2]) * inv_res
        if x < 0.0 or y < 0.0 or z < 0.0 or x >= n or y >= n or z >= n:
            outside += 1
            continue
        c = (int(x) * n + int(y)) * n + int(z)
        cells.hits[c] += 1
        _add_position(cells.contact_sum, c, px, py, pz)
        integrated += 1
        n_changed = _add_evidence(c, 1.0, model, cells, evidence, changed, n_changed, n)
        _mark_dirty(c, counts)
    _refresh_probability(cells, n, 0, changed, n_changed)
    return integrated, outside, invalid


# ---------------------------------------------------------------------------- tracks
@_inlined
def _advance(f: int, final: bool, geometry: GridGeometry, model: PathModel, cells: CellArrays,
             evidence: CellFloats, tracks: PathTracks, visits: PathVisits, counts: PathCounts,
             changed: Indices, earliest: float, n_changed: int) -> tuple[float, int]:
    """Settle what finger ``f``'s samples now allow (everything if ``final``: its track has
    ended), and walk the path to each sample whose context speed is settled."""
    count = tracks.held[f]
    t = tracks.t
    newest = t[f, count - 1]
    window, context = model.speed_window, model.speed_context
    # A sample's velocity needs the samples within +- window and at least one on each side.
    k = tracks.known[f]
    while k < count and (final or (newest > t[f, k] + window and k + 1 < count)):
        speed, sx, sy, sz = _fit(tracks, f, k, count, window)
        tracks.speed[f, k] = speed
        tracks.smooth[f, k, 0] = sx
        tracks.smooth[f, k, 1] = sy
        tracks.smooth[f, k, 2] = sz
        k += 1
    tracks.known[f] = k
    # Its context speed needs the speeds within +- context: the fastest of the window,
    # which slides along the track, is kept as it slides (a monotonic queue, ``peaks``)
    # rather than found again among the 2 x 0.25 s of samples of every step (a quarter of
    # the time). The window is the samples with times in [t - context, t + context] (the
    # times of a track never fall), and its maximum the same value however it is found.
    w = tracks.walked[f]
    while w < count and (final or newest > t[f, w] + context + window):
        j = tracks.entered[f]
        while j < count and t[f, j] <= t[f, w] + context:
            last = tracks.peaks_to[f]
            while last > tracks.peaks_from[f] and \
                    tracks.speed[f, tracks.peaks[f, last - 1]] <= tracks.speed[f, j]:
                last -= 1      # never the fastest again: j is as fast and stays longer
            tracks.peaks[f, last] = j
            tracks.peaks_to[f] = last + 1
            j += 1
        tracks.entered[f] = j
        first = tracks.peaks_from[f]
        while first < tracks.peaks_to[f] - 1 and \
                tracks.t[f, tracks.peaks[f, first]] < t[f, w] - context:
            first += 1         # left the window
        tracks.peaks_from[f] = first
        tracks.context[f, w] = max(0.0, tracks.speed[f, tracks.peaks[f, first]])
        if w > 0:
            earliest, n_changed = _walk(f, w - 1, w, geometry, model, cells, evidence, tracks,
                                        visits, counts, changed, earliest, n_changed)
        w += 1
    tracks.walked[f] = w
    return earliest, n_changed


@_inlined
def _fit(tracks: PathTracks, f: int, k: int, count: int, window: float
         ) -> tuple[float, float, float, float]:
    """|velocity| at sample k of finger ``f``, and its position (x, y, z) on the line: the
    least-squares line through the samples within +- window of it, and at least its two
    neighbours (a single 240 Hz step would turn 1 mm of tracker noise into 0.24 m/s).

    Scalars rather than (3,) arrays: the kernels allocate nothing (``_uncounted``). The
    finger's rows are views (free without reference counting), so the loops index one
    dimension less. The sums are the same, in the same order."""
    t, p = tracks.t[f], tracks.p[f]
    # The window's ends only move forwards as k does (a track's times never fall): each
    # starts where the previous fit's stopped (``fit_lo``, ``fit_hi``) instead of searching
    # out from k again (2 x 24 steps at 240 Hz). The first sample at or after t[k] - window,
    # and the last at or before t[k] + window: the ends a search out from k finds.
    lo = tracks.fit_lo[f]
    while t[lo] < t[k] - window:
        lo += 1
    tracks.fit_lo[f] = lo
    hi = max(tracks.fit_hi[f], k)
    while hi + 1 < count and t[hi + 1] <= t[k] + window:
        hi += 1
    tracks.fit_hi[f] = hi
    lo = max(0, min(lo, k - 1))
    hi = min(count - 1, max(hi, k + 1))
    m = hi - lo + 1
    mean_t = 0.0
    mean_x = mean_y = mean_z = 0.0
    for j in range(lo, hi + 1):
        mean_t += t[j]
        mean_x += p[j, 0]
        mean_y += p[j, 1]
        mean_z += p[j, 2]
    mean_t /= m
    mean_x /= m
    mean_y /= m
    mean_z /= m
    var = 0.0
    cov_x = cov_y = cov_z = 0.0
    for j in range(lo, hi + 1):
        dt = t[j] - mean_t
        var += dt * dt
        cov_x += dt * (p[j, 0] - mean_x)
        cov_y += dt * (p[j, 1] - mean_y)
        cov_z += dt * (p[j, 2] - mean_z)
    if not var > 0.0:
        return 0.0, mean_x, mean_y, mean_z
    at = t[k] - mean_t
    return (math.sqrt(cov_x ** 2 + cov_y ** 2 + cov_z ** 2) / var,
            mean_x + cov_x / var * at, mean_y + cov_y / var * at, mean_z + cov_z / var * at)


@_uncounted
def _compact(f: int, model: PathModel, tracks: PathTracks) -> bool:
    """Drop the oldest samples of finger ``f``'s full buffer that nothing still needs;
    False if none can go."""
    t = tracks.t[f]
    known, walked = tracks.known[f], tracks.walked[f]
    keep = min(walked - 1, known - 1)
    if walked < tracks.held[f]:
        j = walked
        while j > 0 and t[j - 1] >= t[walked] - model.speed_context:
            j -= 1
        keep = min(keep, j)
    if known < tracks.held[f]:
        j = known
        while j > 0 and t[j - 1] >= t[known] - model.speed_window:
            j -= 1
        keep = min(keep, j)
    if keep <= 0:
        return False
    count = tracks.held[f]
    # The context window's queue (samples in order): those dropped leave it, the others move.
    size = 0
    for q in range(tracks.peaks_from[f], tracks.peaks_to[f]):
        if tracks.peaks[f, q] >= keep:
            tracks.peaks[f, size] = tracks.peaks[f, q] - keep
            size += 1
    tracks.peaks_from[f] = 0
    tracks.peaks_to[f] = size
    tracks.entered[f] -= keep
    tracks.fit_lo[f] = max(0, tracks.fit_lo[f] - keep)   # the next fit's window is all kept
    tracks.fit_hi[f] = max(0, tracks.fit_hi[f] - keep)
    for j in range(keep, count):
        tracks.t[f, j - keep] = tracks.t[f, j]
        tracks.speed[f, j - keep] = tracks.speed[f, j]
        tracks.context[f, j - keep] = tracks.context[f, j]
        for a in range(3):
            tracks.p[f, j - keep, a] = tracks.p[f, j, a]
            tracks.smooth[f, j - keep, a] = tracks.smooth[f, j, a]
    tracks.held[f] = count - keep
    tracks.known[f] = known - keep
    tracks.walked[f] = walked - keep
    return True


@_uncounted
def _end_track(f: int, geometry: GridGeometry, model: PathModel, cells: CellArrays,
               evidence: CellFloats, tracks: PathTracks, visits: PathVisits,
               counts: PathCounts, changed: Indices, earliest: float, n_changed: int
               ) -> tuple[float, int]:
    """Walk finger ``f``'s track to its end and close it: the finger is in no cell now."""
    earliest, n_changed = _advance(f, True, geometry, model, cells, evidence, tracks, visits,
                                   counts, changed, earliest, n_changed)
    tracks.held[f] = 0
    tracks.known[f] = 0
    tracks.walked[f] = 0
    tracks.entered[f] = 0
    tracks.fit_lo[f] = 0
    tracks.fit_hi[f] = 0
    tracks.peaks_from[f] = 0
    tracks.peaks_to[f] = 0
    visits.current[f] = -1
    return earliest, n_changed


# ---------------------------------------------------------------------------- the walk
@_inlined
def _walk(f: int, a: int, b: int, geometry: GridGeometry, model: PathModel, cells: CellArrays,
          evidence: CellFloats, tracks: PathTracks, visits: PathVisits, counts: PathCounts,
          changed: Indices, earliest: float, n_changed: int) -> tuple[float, int]:
    """The straight segment from sample ``a`` to ``b`` of finger ``f``, in equal steps of
    at most ``model.step``; each step is a moment of contact at its midpoint. The raw path
    says which cell; the smoothed one (the local fits) how far through it the finger went."""
    inv_res, n, origin = geometry.inv_res, geometry.n, geometry.origin
    ta, tb = tracks.t[f, a], tracks.t[f, b]
    ca, cb = tracks.context[f, a], tracks.context[f, b]
    va, vb = tracks.speed[f, a], tracks.speed[f, b]
    # Scalars, not (3,) arrays: see _fit.
    pax, pay, paz = tracks.p[f, a, 0], tracks.p[f, a, 1], tracks.p[f, a, 2]
    sax, say, saz = tracks.smooth[f, a, 0], tracks.smooth[f, a, 1], tracks.smooth[f, a, 2]
    dx, dy, dz = tracks.p[f, b, 0] - pax, tracks.p[f, b, 1] - pay, tracks.p[f, b, 2] - paz
    dsx = tracks.smooth[f, b, 0] - sax
    dsy = tracks.smooth[f, b, 1] - say
    dsz = tracks.smooth[f, b, 2] - saz
    chord2 = 0.0 + dx ** 2 + dy ** 2 + dz ** 2
    smooth2 = 0.0 + dsx ** 2 + dsy ** 2 + dsz ** 2
    steps = max(1, min(model.max_steps, int(math.ceil(math.sqrt(chord2) / model.step))))
    duration = (tb - ta) / steps
    length = math.sqrt(smooth2) / steps
    for s in range(steps):
        frac = (s + 0.5) / steps
        smooth_x, smooth_y, smooth_z = sax + frac * dsx, say + frac * dsy, saz + frac * dsz
        _follow_stay(f, smooth_x, smooth_y, smooth_z, model, visits)
        x = (pax + frac * dx - origin[0]) * inv_res
        y = (pay + frac * dy - origin[1]) * inv_res
        z = (paz + frac * dz - origin[2]) * inv_res
        if x < 0.0 or y < 0.0 or z < 0.0 or x >= n or y >= n or z >= n:
            visits.current[f] = -1
            continue
        c = (int(x) * n + int(y)) * n + int(z)
        time = ta + frac * (tb - ta)
        if not (cells.first_touch[c] <= time):
            cells.first_touch[c] = time
        earliest = min(earliest, time)
        context = ca + frac * (cb - ca)
        slide = (1.0 if context <= model.transit_speed
                 else (model.transit_speed / context) ** model.transit_falloff)
        delta = _visit_step(f, c, smooth_x, smooth_y, smooth_z, length, time, duration,
                            slide, va + frac * (vb - va), geometry, model, visits, counts)
        n_changed = _add_evidence(c, delta, model, cells, evidence, changed, n_changed, n)
        _mark_dirty(c, counts)
    return earliest, n_changed


@_inlined
def _mark_dirty(c: int, counts: PathCounts) -> None:
    """Cell ``c``'s evidence changed: the surface layer around it is out of date."""
    if not counts.dirty_mark[c]:
        counts.dirty_mark[c] = True
        counts.dirty[counts.n_dirty[0]] = c
        counts.n_dirty[0] += 1


@_inlined
def _add_evidence(c: int, delta: float, model: PathModel, cells: CellArrays,
                  evidence: CellFloats, changed: Indices, n_changed: int, n: int) -> int:
    """Cell ``c``'s touches change by ``delta`` measurements: its log-odds follow (eq. 4 at
    distance 0, clamped). Returns the new count of cells waiting for a refresh."""
    evidence[c] += delta
    cells.log_odds[c] = _clamp(model.prior + evidence[c] * model.log_odds_per_touch,
                               model.l_min, model.l_max)
    if not cells.changed_mark[c]:
        if n_changed == changed.shape[0]:
            _refresh_probability(cells, n, 0, changed, n_changed)
            n_changed = 0
        cells.changed_mark[c] = True
        changed[n_changed] = c
        n_changed += 1
    return n_changed


# ---------------------------------------------------------------------------- visits
@_inlined
def _visit_step(f: int, c: int, smooth_x: float, smooth_y: float, smooth_z: float,
                length: float, time: float, duration: float, slide: float, speed: float,
                geometry: GridGeometry, model: PathModel, visits: PathVisits,
                counts: PathCounts) -> float:
    """One step of finger ``f`` in cell ``c`` (``duration`` s at slide factor ``slide`` and
    fitted ``speed``, centred at ``smooth_*`` on the smoothed path and ``length`` m long
    there): its visit of the cell grows by the step and its worth is recomputed. Returns
    the change of the visit's worth."""
    r = visits.current[f]
    if r < 0 or visits.cell[f, r] != c:
        r = _enter(f, c, smooth_x, smooth_y, smooth_z, time, model, visits, counts)
        visits.current[f] = r
    visits.last[f, r] = time
    visits.stay[f, r] = visits.stay_id[f]
    visits.dwell[f, r] += duration
    visits.g_dwell[f, r] += slide * duration
    visits.v_dwell[f, r] += speed * duration
    moved2 = (0.0 + (smooth_x - visits.pass_entry[f, r, 0]) ** 2
              + (smooth_y - visits.pass_entry[f, r, 1]) ** 2
              + (smooth_z - visits.pass_entry[f, r, 2]) ** 2)
    # From the start of the pass's first step to the end of this one (a pass that comes
    # back out where it went in is not through); a crossing seen to within a step (steps
    # fall anywhere along the path) is a crossing.
    visits.pass_through[f, r] = min(1.0, (math.sqrt(moved2) + length)
                                    / (geometry.resolution - model.step))
    through = max(visits.through[f, r], visits.pass_through[f, r])
    dwell = visits.dwell[f, r]
    slide_mean = visits.g_dwell[f, r] / dwell if dwell > 0.0 else slide
    speed_mean = visits.v_dwell[f, r] / dwell if dwell > 0.0 else speed
    # The time a slide at the visit's mean speed takes to cross the cell.
    crossing = geometry.resolution / speed_mean if speed_mean > 0.0 else math.inf
    worth = slide_mean * (1.0 - model.return_share * (1.0 - through)
                          + through * min(1.0, crossing / model.pass_time))
    delta: float = worth - visits.worth[f, r]
    visits.worth[f, r] = worth
    return delta


@_inlined
def _enter(f: int, c: int, smooth_x: float, smooth_y: float, smooth_z: float, time: float,
           model: PathModel, visits: PathVisits, counts: PathCounts) -> int:
    """Finger ``f`` enters cell ``c``: its visit of the last ``visit_gap`` seconds or of its
    current stay, moved to the front of the ring, or a new one. Returns its slot."""
    ring = visits.cell.shape[1]
    head = visits.head[f]
    new = head % ring
    # The slot the cell's visit was last written to, if it still holds the cell and the
    # visit is not over. The ring is in order of the last time spent in each visit, and the
    # stay's visits are the newest, so this is the visit a scan back from the newest finds
    # (the one that stops at the first visit older than the gap and not of the stay): the
    # same slot, without the scan (some fifty visits at a 3 s gap: bench_mapping's stream
    # took 32-35 ms with it, 27-31 without; docs/benchmarks.md).
    found = -1
    slot = visits.slot_of[f, c]
    if visits.cell[f, slot] == c and (visits.last[f, slot] >= time - model.visit_gap
                                      or visits.stay[f, slot] == visits.stay_id[f]):
        found = slot
    if found < 0 and visits.cell[f, new] >= 0 and (
            visits.last[f, new] >= time - model.visit_gap
            or visits.stay[f, new] == visits.stay_id[f]):
        counts.overwritten[0] += 1
    if found >= 0 and found != new:
        visits.last[f, new] = visits.last[f, found]
        visits.dwell[f, new] = visits.dwell[f, found]
        visits.g_dwell[f, new] = visits.g_dwell[f, found]
        visits.v_dwell[f, new] = visits.v_dwell[f, found]
        visits.worth[f, new] = visits.worth[f, found]
        visits.through[f, new] = visits.through[f, found]
        visits.pass_through[f, new] = visits.pass_through[f, found]
        for axis in range(3):
            visits.pass_entry[f, new, axis] = visits.pass_entry[f, found, axis]
        visits.cell[f, found] = -1
    elif found < 0:
        visits.dwell[f, new] = 0.0
        visits.g_dwell[f, new] = 0.0
        visits.v_dwell[f, new] = 0.0
        visits.worth[f, new] = 0.0
        visits.through[f, new] = 0.0
        visits.pass_through[f, new] = 0.0
    if found < 0 or time - visits.last[f, new] > model.pass_gap:
        # A new pass through the cell: the last one is over.
        visits.through[f, new] = max(visits.through[f, new], visits.pass_through[f, new])
        visits.pass_through[f, new] = 0.0
        visits.pass_entry[f, new, 0] = smooth_x
        visits.pass_entry[f, new, 1] = smooth_y
        visits.pass_entry[f, new, 2] = smooth_z
    visits.cell[f, new] = c
    visits.slot_of[f, c] = new
    visits.head[f] = head + 1
    return int(new)


@_inlined
def _follow_stay(f: int, x: float, y: float, z: float, model: PathModel,
                 visits: PathVisits) -> None:
    """A finger that moves farther than ``stay_radius`` from where its stay began (at
    (x, y, z)) is at a new place: its stay starts there."""
    d2 = (0.0 + (x - visits.anchor[f, 0]) ** 2 + (y - visits.anchor[f, 1]) ** 2
          + (z - visits.anchor[f, 2]) ** 2)
    if not d2 <= model.stay_radius ** 2:     # NaN anchor: the first step
        visits.stay_id[f] += 1
        visits.anchor[f, 0] = x
        visits.anchor[f, 1] = y
        visits.anchor[f, 2] = z


@_uncounted
def _forget_visits(f: int, visits: PathVisits) -> None:
    """A new stream for finger ``f``: none of its visits can be continued."""
    visits.cell[f, :] = -1
    visits.current[f] = -1
    visits.anchor[f, :] = np.nan

