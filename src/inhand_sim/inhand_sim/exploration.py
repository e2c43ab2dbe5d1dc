"""Exploration the way a person does it: fingertips following contours in strokes.

The thumb, index and middle fingertips each alternate between

* **strokes**: the fingertip slides over the surface along a continuous path at a few cm/s
  (2-5 cm/s, varying within the stroke) for a few seconds (2-6 s). A stroke follows a
  contour: a horizontal loop around the object (``contour``), a line up or down its side
  (``meridian``) or a wandering path (``free``), with a slowly drifting heading. It ends
  early where the fingertip cannot go: the region the other hand holds, the table, a
  crease too narrow for a fingertip;
* **transits**: the fingertip leaves the surface and moves through the air, around the
  object, to the start of the next stroke (0.3-1.2 s). The next place is chosen near the
  finger's current place, on the finger's side of the object (thumb on one side, index and
  middle opposite) and preferably not explored yet;
* **dwells**: now and then the fingertip rests at the start of a stroke for a moment;
* **involuntary lifts**: sporadically during a stroke the fingertip lifts 1-3 cm off the
  surface and comes back to the same place; sometimes it does so 2-5 times in a row at one
  place (the paper's case of off-surface movements repeated in one region, which can
  survive the probabilistic map);
* **away phases** (re-grasps of hand-held objects): every fingertip leaves the object,
  withdraws briskly 15-22 cm (out of the other hand's way), drifts there while the other
  hand turns the object, and comes back.

Every sample is either a contact (exactly on the surface) or an off-surface sample at
least ``clearance`` (6 mm) from it: the lift-off and touch-down of a fingertip through the
first few millimetres are taken to happen between two tracker frames (at 15 Hz they do; at
240 Hz this is a simplification that keeps the two kinds apart in the ground truth).

The fingertip sensor is taken to sit at the contact point, as the paper assumes.
Everything is generated in the OBJECT frame, except the away phases, which are planned in
the tracker frame (the hand withdraws in the room while the object turns) and converted.
Deterministic: all randomness comes from the numpy Generator passed in.

Stroke geometry is integrated for a pool of candidate strokes at once (one vectorised
step for all of them per 2 mm of path), and samples are placed along the chosen strokes
by arc length and projected onto the surface in one batch, so there is no Python loop per
sample.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from inhand_common.rotations import quaternion_conjugate, rotate_vectors

from inhand_sim.objects import HeldRegion, ObjectModel

__all__ = [
    'CONTACT',
    'FINGERS',
    'SAMPLE_KINDS',
    'STRAY',
    'Exploration',
    'ExplorationSettings',
    'TrackerNoise',
    'explore',
]

FINGERS = ('thumb', 'index', 'middle')
CONTACT = 1
STRAY = 0
SAMPLE_KINDS = ('transit', 'stroke', 'dwell', 'lift', 'away')

# The side of the object each finger prefers (object frame): thumb opposing the others.
_FINGER_SIDES = {'thumb': (0.0, -1.0, 0.0), 'index': (0.25, 1.0, 0.0),
                 'middle': (-0.25, 1.0, 0.0)}
_MODES = ('contour', 'meridian', 'free')


@dataclass(frozen=True)
class ExplorationSettings:
    """How the hand explores. Lengths in metres, times in seconds."""
    speed_range: tuple = (0.02, 0.05)            # sliding speed of a stroke, m/s
    speed_variation: float = 0.3                 # relative speed modulation within a stroke
    stroke_duration_range: tuple = (2.0, 6.0)    # planned stroke duration (shorter at obstacles)
    min_stroke_length: float = 0.01              # candidate strokes shorter than this are dropped
    stroke_step: float = 0.002                   # integration step along the surface
    mode_probabilities: tuple = (0.45, 0.25, 0.30)  # contour, meridian, free
    fingertip_radius: float = 0.007              # a fingertip ball of this radius ...
    fingertip_fit: float = 0.6                   # ... must fit this much at a contact (no narrow creases)
    max_turns: int = 8                           # a stroke turns aside at obstacles this often, then ends
    table_reach: float = 0.02                    # static: downward faces this close to the table are out of reach
    clearance: float = 0.006                     # every off-surface sample at least this far
    transit_height_range: tuple = (0.01, 0.02)   # how high a finger lifts to move elsewhere
    transit_speed: float = 0.35                  # mean speed of a transit, m/s
    transit_duration_range: tuple = (0.25, 0.9)  # s
    transit_end_speed: float = 0.3               # speed at lift-off / touch-down, relative to the mean
    slide_reach: float = 0.03                    # a next stroke this close is reached by sliding
    neighbourhood: float = 0.04                  # preferred distance to the next stroke (decay length)
    side_preference: float = 0.8                 # strength of each finger's preferred side
    explored_weight: float = 0.15                # weight of a stroke start already explored
    lift_rate: float = 1.0 / 15.0                # involuntary lift episodes per second of stroke
    lift_height_range: tuple = (0.01, 0.03)
    lift_duration_range: tuple = (0.3, 0.7)
    repeated_lift_probability: float = 0.3       # an episode repeats at the same place ...
    repeated_lift_count: tuple = (2, 5)          # ... this many times
    dwell_probability: float = 0.15
    dwell_duration_range: tuple = (0.3, 1.2)
    away_distance_range: tuple = (0.15, 0.22)    # withdrawal during a re-grasp
    pool_size: int = 300                         # candidate strokes per grip


@dataclass(frozen=True)
class TrackerNoise:
    """Tracker noise on fingertip positions: Gaussian per axis plus rare outliers."""
    sigma: float = 0.001                 # m, per axis
    outlier_fraction: float = 0.002
    outlier_range: tuple = (0.01, 0.02)  # outlier offset length, m, random direction

    def sample(self, shape: tuple, rng: np.random.Generator) -> np.ndarray:
        """Offsets of shape ``shape + (3,)``."""
        offsets = rng.normal(0.0, self.sigma, size=(*shape, 3)) if self.sigma > 0 else np.zeros((*shape, 3))
        flat = offsets.reshape(-1, 3)
        outlier = rng.random(len(flat)) < self.outlier_fraction
        k = int(outlier.sum())
        if k:
            direction = rng.normal(size=(k, 3))
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            flat[outlier] += direction * rng.uniform(*self.outlier_range, size=(k, 1))
        return offsets


@dataclass
class Exploration:
    """What the fingertips did, noise-free, at every tracker frame (object frame).

    ``positions[f, k]`` is finger ``FINGERS[f]`` at ``times[k]``; ``contact[f, k]`` says
    whether it was on the surface; ``stroke[f, k]`` numbers the finger's strokes (contacts
    of one stroke form a continuous path; -1 off the surface and during dwells);
    ``grip[k]`` is the index of the held region in force; ``held_regions`` lists them;
    ``kind[f, k]`` indexes SAMPLE_KINDS.
    """
    times: np.ndarray
    positions: np.ndarray
    contact: np.ndarray
    stroke: np.ndarray
    grip: np.ndarray
    held_regions: list
    kind: np.ndarray = None     # (3, T) int8: index into SAMPLE_KINDS of what the finger was doing
    events: list = field(default_factory=list)  # (finger, kind, t_start, t_end)


# --- helpers -----------------------------------------------------------------------------

def _normalize(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def _min_jerk(u):
    u = np.clip(u, 0.0, 1.0)
    return u ** 3 * (10.0 - 15.0 * u + 6.0 * u ** 2)


def _polyline_at(points: np.ndarray, fraction: np.ndarray) -> np.ndarray:
    """Points at arc-length fractions (0..1) along a polyline."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    if cum[-1] <= 0:
        return np.repeat(points[:1], len(fraction), axis=0)
    s = np.clip(fraction, 0.0, 1.0) * cum[-1]
    return np.stack([np.interp(s, cum, points[:, k]) for k in range(3)], axis=1)


class _Surroundings:
    """Distances to everything a fingertip must keep clear of: the object, and in static
    sessions the table (a half-space below ``table_z``)."""

    def __init__(self, obj: ObjectModel, table: bool):
        self.obj = obj
        self.table = table

    def sdf_grad(self, p):
        d, g = self.obj.sdf_grad(p)
        if self.table:
            dt = p[:, 2] - self.obj.table_z
            below = dt < d
            d = np.where(below, dt, d)
            g = np.where(below[:, None], np.array([0.0, 0.0, 1.0]), g)
        return d, g

    def push_out(self, p: np.ndarray, clearance: float, iterations: int = 12) -> np.ndarray:
        """Move points closer than ``clearance`` out along the gradient until they are not."""
        p = p.copy()
        target = clearance + 2e-4
        for _ in range(iterations):
            d, g = self.sdf_grad(p)
            bad = d < clearance
            if not bad.any():
                break
            gg = g[bad]
            g2 = np.maximum(np.sum(gg * gg, axis=1), 1e-300)
            p[bad] += ((target - d[bad]) / g2)[:, None] * gg
        return p


# --- strokes -----------------------------------------------------------------------------

@dataclass
class _StrokePool:
    paths: np.ndarray     # (S, K+1, 3)
    normals: np.ndarray   # (S, K+1, 3)
    lengths: np.ndarray   # (S,) number of valid steps
    arclen: np.ndarray    # (S,) path length
    starts: np.ndarray    # (S, 3)
    start_normals: np.ndarray
    used: np.ndarray      # (S,) bool


def _forbidden(obj: ObjectModel, held: HeldRegion, table: bool, settings: ExplorationSettings,
               points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    bad = held.contains(points)
    if table:
        height = points[:, 2] - obj.table_z
        bad |= height < 0.003
        bad |= (height < settings.table_reach) & (normals[:, 2] < -0.3)
    return bad


def _accessible(surroundings: _Surroundings, points, normals, radius, fit) -> np.ndarray:
    """Whether a fingertip ball touching the surface at the points fits (at least ``fit`` of
    its radius clear of everything): not in creases narrower than a fingertip."""
    d, _ = surroundings.sdf_grad(points + radius * normals)
    return d >= fit * radius


def _surface_step(obj, surroundings, held, table, settings, p, t, h):
    """One step of length ``h`` from surface points ``p`` along tangents ``t``: the new
    points on the surface, their normals, and whether the step is allowed."""
    q = obj._newton(p + h * t, 4, 1e-12)
    d, g = obj.sdf_grad(q)
    n = _normalize(g)
    ok = (np.abs(d) < 1e-7) & (np.linalg.norm(q - p, axis=1) < 2.0 * h)
    ok &= ~_forbidden(obj, held, table, settings, q, n)
    ok &= _accessible(surroundings, q, n, settings.fingertip_radius, settings.fingertip_fit)
    return q, n, ok


def _build_pool(obj: ObjectModel, held: HeldRegion, table: bool, settings: ExplorationSettings,
                rng: np.random.Generator) -> _StrokePool:
    """Integrate ``pool_size`` candidate strokes over the surface, all at once."""
    surroundings = _Surroundings(obj, table)
    st = settings
    starts = np.empty((0, 3))
    normals = np.empty((0, 3))
    while len(starts) < st.pool_size:
        p, n = obj.sample_surface(4 * st.pool_size, rng)
        ok = ~_forbidden(obj, held, table, st, p, n) & _accessible(
            surroundings, p, n, st.fingertip_radius, st.fingertip_fit)
        starts = np.concatenate([starts, p[ok]])
        normals = np.concatenate([normals, n[ok]])
    starts, normals = starts[:st.pool_size], normals[:st.pool_size]
    s_count = len(starts)
    max_len = st.stroke_duration_range[1] * st.speed_range[1] * (1.0 + st.speed_variation)
    k_steps = int(math.ceil(max_len / st.stroke_step))
    modes = rng.choice(len(_MODES), size=s_count, p=np.asarray(st.mode_probabilities))
    heading = _normalize(np.cross(normals, rng.normal(size=(s_count, 3))))
    up = np.array([0.0, 0.0, 1.0])
    turn_sigma = np.where(modes == 2, 0.10, 0.04)
    blend = np.where(modes == 2, 0.0, 0.2)

    paths = np.repeat(starts[:, None, :], k_steps + 1, axis=1)
    path_normals = np.repeat(normals[:, None, :], k_steps + 1, axis=1)
    lengths = np.zeros(s_count, dtype=int)
    turns = np.zeros(s_count, dtype=int)
    alive = np.ones(s_count, dtype=bool)
    p, t = starts.copy(), heading
    h = st.stroke_step
    for k in range(k_steps):
        idx = np.flatnonzero(alive)
        if idx.size == 0:
            break
        pk, tk = p[idx], t[idx]
        q, n, ok = _surface_step(obj, surroundings, held, table, st, pk, tk, h)
        # A fingertip meeting an obstacle turns aside (up to max_turns times) before it stops.
        retry = np.flatnonzero(~ok & (turns[idx] < st.max_turns))
        for angle in (0.5 * math.pi, -0.5 * math.pi, 0.8 * math.pi, -0.8 * math.pi):
            if retry.size == 0:
                break
            nk = _normalize(obj.sdf_grad(pk[retry])[1])
            sign = np.where(rng.random(retry.size) < 0.5, 1.0, -1.0)
            a = sign * angle
            tr = tk[retry] * np.cos(a)[:, None] + np.cross(nk, tk[retry]) * np.sin(a)[:, None]
            q2, n2, ok2 = _surface_step(obj, surroundings, held, table, st, pk[retry], tr, h)
            won = retry[ok2]
            q[won], n[won], ok[won], tk[won] = q2[ok2], n2[ok2], True, tr[ok2]
            turns[idx[won]] += 1
            retry = retry[~ok2]
        # Heading: keep it tangent, lean towards the mode's direction, drift randomly.
        tp = _normalize(tk - np.sum(tk * n, axis=1, keepdims=True) * n)
        m = modes[idx]
        contour = np.cross(up, n)
        meridian = up - n[:, 2:3] * n
        pref = np.where((m == 0)[:, None], contour, meridian)
        weak = np.linalg.norm(pref, axis=1) < 0.2
        pref = _normalize(pref)
        pref *= np.where(np.sum(pref * tp, axis=1) < 0, -1.0, 1.0)[:, None]
        bl = np.where(weak | (m == 2), 0.0, blend[idx])[:, None]
        tn = _normalize(tp + bl * (pref - tp))
        angle = rng.normal(0.0, 1.0, len(idx)) * turn_sigma[idx]
        tn = _normalize(tn * np.cos(angle)[:, None] + np.cross(n, tn) * np.sin(angle)[:, None])
        dead = idx[~ok]
        alive[dead] = False
        good = idx[ok]
        p[good] = q[ok]
        t[good] = tn[ok]
        paths[good, k + 1] = q[ok]
        path_normals[good, k + 1] = n[ok]
        lengths[good] = k + 1
    # Past its end a stroke stays at its last point.
    last = np.minimum(np.arange(k_steps + 1)[None, :], lengths[:, None])
    rows = np.arange(s_count)[:, None]
    paths, path_normals = paths[rows, last], path_normals[rows, last]
    seg = np.linalg.norm(np.diff(paths, axis=1), axis=2)
    arclen = seg.sum(axis=1)
    keep = arclen >= st.min_stroke_length
    return _StrokePool(paths[keep], path_normals[keep], lengths[keep], arclen[keep],
                       starts[keep], normals[keep], np.zeros(int(keep.sum()), dtype=bool))


# --- air paths ---------------------------------------------------------------------------

def _segment_clear(surroundings: _Surroundings, a, b, clearance: float) -> bool:
    n = max(2, int(np.linalg.norm(b - a) / 0.003) + 1)
    pts = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
    return bool(np.all(surroundings.sdf_grad(pts)[0] >= clearance))


def _air_waypoints(obj: ObjectModel, surroundings: _Surroundings, a, na, b, nb,
                   settings: ExplorationSettings, rng) -> np.ndarray:
    """Waypoints from the lifted point ``a`` to the lifted point ``b`` (object frame) that
    keep clear of the object: straight if that is clear, else over the top or around."""
    st = settings
    ha, hb = rng.uniform(*st.transit_height_range, size=2)
    a2, b2 = a + na * ha, b + nb * hb
    margin = st.clearance + 0.004
    if _segment_clear(surroundings, a2, b2, margin):
        return np.stack([a, a2, b2, b])
    lo, hi = obj.bounds
    centre = obj.centre
    top = hi[2] + 0.025
    over = [np.array([a2[0], a2[1], top]), np.array([b2[0], b2[1], top])]
    radius = 0.5 * np.linalg.norm(hi[:2] - lo[:2]) + 0.03

    def around(p):
        r = p[:2] - centre[:2]
        r = r / max(np.linalg.norm(r), 1e-9) * radius
        return np.array([centre[0] + r[0], centre[1] + r[1], p[2]])
    candidates = [
        [a2, over[0], over[1], b2],
        [a2, around(a2), around(b2), b2],
        [a2, around(a2), np.array([*around(a2)[:2], top]), np.array([*around(b2)[:2], top]),
         around(b2), b2],
    ]
    best = None
    for cand in candidates:
        if all(_segment_clear(surroundings, cand[i], cand[i + 1], margin)
               for i in range(len(cand) - 1)):
            length = sum(np.linalg.norm(cand[i + 1] - cand[i]) for i in range(len(cand) - 1))
            if best is None or length < best[0]:
                best = (length, cand)
    path = best[1] if best else candidates[0]
    return np.stack([a, *path, b])


def _timed_polyline(points: np.ndarray, times: np.ndarray, t0: float, t1: float,
                    end_speed: float = 0.0) -> np.ndarray:
    """Positions at ``times`` along a polyline traversed from t0 to t1: a minimum-jerk
    profile blended with constant speed, so that the speed at both ends is ``end_speed``
    times the mean (a finger leaves and reaches the surface already moving)."""
    u = np.clip((times - t0) / max(t1 - t0, 1e-9), 0.0, 1.0)
    return _polyline_at(points, end_speed * u + (1.0 - end_speed) * _min_jerk(u))


def _slide_path(obj: ObjectModel, surroundings, held, table, settings, a, b):
    """A path over the surface from contact ``a`` to ``b`` (the chord projected onto the
    surface), or None where it would cross an obstacle or jump."""
    st = settings
    n = max(2, int(np.ceil(np.linalg.norm(b - a) / st.stroke_step)) + 1)
    chord = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
    path = obj._newton(chord, 20, 1e-12)
    d, g = obj.sdf_grad(path)
    normals = _normalize(g)
    steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
    if (np.abs(d).max() > 1e-7 or steps.max() > 3.0 * np.linalg.norm(b - a) / (n - 1) + 1e-4
            or _forbidden(obj, held, table, st, path, normals).any()
            or not _accessible(surroundings, path, normals, st.fingertip_radius,
                               st.fingertip_fit).all()):
        return None
    return path


# --- the timeline ------------------------------------------------------------------------

@dataclass
class _Segment:
    t0: float
    t1: float
    kind: str                                   # stroke, dwell, transit, lift, away
    fn: Callable[[np.ndarray], np.ndarray]      # times -> positions (object frame)
    contact: bool
    stroke_id: int = -1


def _stroke_segments(pool: _StrokePool, index: int, t0: float, duration: float, speed: float,
                     settings: ExplorationSettings, rng, stroke_id: int,
                     limit: float) -> tuple[list, float, np.ndarray, np.ndarray]:
    """Segments of one stroke (with its involuntary lifts) starting at ``t0``, ending by
    ``limit``. Returns (segments, end time, last contact point, its normal)."""
    st = settings
    n_valid = pool.lengths[index] + 1
    path = pool.paths[index, :n_valid]
    normals = pool.normals[index, :n_valid]
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    total = cum[-1]
    omega = 2 * math.pi / rng.uniform(1.5, 4.0)
    phase = rng.uniform(0, 2 * math.pi)
    amp = st.speed_variation

    def arc(tau):
        """Arc length slid after ``tau`` s of sliding: speed v (1 + amp sin(omega tau + phase))."""
        tau = np.asarray(tau, dtype=float)
        s = speed * (tau + amp / omega * (math.cos(phase) - np.cos(omega * tau + phase)))
        return np.minimum(s, total)

    def at_arc(s):
        return np.stack([np.interp(s, cum, path[:, k]) for k in range(3)], axis=1)

    # Sliding time needed to cover the path, capped by the planned duration.
    taus = np.linspace(0.0, duration, 2000)
    active = float(taus[min(int(np.searchsorted(arc(taus), total)), len(taus) - 1)])
    # Involuntary lift episodes at random moments of the stroke.
    episodes = []
    for tau_l in np.sort(rng.uniform(0.1 * active, 0.9 * active, rng.poisson(st.lift_rate * active))):
        reps = 1
        if rng.random() < st.repeated_lift_probability:
            reps = int(rng.integers(st.repeated_lift_count[0], st.repeated_lift_count[1] + 1))
        height = rng.uniform(*st.lift_height_range)
        lateral = rng.normal(0.0, 0.002, 3)
        lifts = [(rng.uniform(*st.lift_duration_range), height + rng.normal(0.0, 0.0015),
                  rng.uniform(0.08, 0.2)) for _ in range(reps)]  # (duration, height, touch)
        episodes.append((float(tau_l), lateral, lifts))

    def slide(ta, tau_a):
        return lambda times: at_arc(arc(tau_a + (times - ta)))

    def hold(p):
        return lambda times: np.repeat(p[None], len(times), axis=0)

    segments = []
    t, tau_prev = t0, 0.0
    c = st.clearance + 0.0005
    for tau_l, lateral, lifts in episodes + [(active, None, [])]:
        tb = t + (tau_l - tau_prev)
        segments.append(_Segment(t, min(tb, limit), 'stroke', slide(t, tau_prev), True, stroke_id))
        if tb >= limit:
            t = limit
            break
        t, tau_prev = tb, tau_l
        if not lifts:
            continue
        p_l = at_arc(arc(np.array([tau_l])))[0]
        n_l = normals[min(int(np.searchsorted(cum, float(arc(tau_l)))), n_valid - 1)]
        side = lateral - np.dot(lateral, n_l) * n_l
        for dur, height, touch in lifts:
            if t + dur + touch >= limit:
                break

            def lift_fn(times, ta=t, dur=dur, height=max(height, c), p_l=p_l, n_l=n_l, side=side):
                bump = np.sin(np.pi * np.clip((times - ta) / dur, 0.0, 1.0))
                return p_l + (c + (height - c) * bump)[:, None] * n_l + bump[:, None] * side
            segments.append(_Segment(t, t + dur, 'lift', lift_fn, False))
            # back down at the same place for a moment (the arc time stays frozen)
            segments.append(_Segment(t + dur, t + dur + touch, 'stroke', hold(p_l), True,
                                     stroke_id))
            t += dur + touch
    segments = [seg for seg in segments if seg.t1 > seg.t0]
    if not segments:
        return [], t0, path[0], normals[0]
    end_point = segments[-1].fn(np.array([segments[-1].t1]))[0]
    i_end = int(np.argmin(np.linalg.norm(path - end_point, axis=1)))
    return segments, segments[-1].t1, end_point, normals[i_end]


def explore(obj: ObjectModel, duration: float, rate: float, rng: np.random.Generator,
            settings: ExplorationSettings = ExplorationSettings(), *,
            grips: Sequence[HeldRegion] | None = None,
            away_windows: Sequence[tuple[float, float]] = (),
            table: bool = True,
            object_pose: Callable | None = None) -> Exploration:
    """Simulate ``duration`` seconds of three-finger exploration sampled at ``rate`` Hz.

    ``grips``: the held regions in force, the first from the start, the next after each
    away window (static sessions: one grip, no windows). ``away_windows``: (start, end)
    times of re-grasps, when every fingertip is off the object. ``table``: the object stands
    on the table (static), which fingertips can neither touch nor pass through.
    ``object_pose(times) -> (positions (N, 3), quaternions (N, 4))``: the object's pose in the
    tracker frame, needed when there are away windows (the hand withdraws in the room).
    """
    st = settings
    grips = list(grips) if grips else [obj.static_grip]
    windows = sorted((float(a), float(b)) for a, b in away_windows)
    if windows and object_pose is None:
        raise ValueError('away windows need object_pose')
    n_frames = int(round(duration * rate))
    times = np.arange(n_frames) / rate
    surroundings = _Surroundings(obj, table)
    grip_count = len(windows) + 1
    grip_of = [grips[i % len(grips)] for i in range(grip_count)]
    pools = {}
    for gi in range(grip_count):
        key = grip_of[gi].name
        if key not in pools:
            pools[key] = _build_pool(obj, grip_of[gi], table, st, rng)
    pool_list = [pools[grip_of[gi].name] for gi in range(grip_count)]
    explored = {key: np.zeros(len(pool.starts)) for key, pool in pools.items()}

    def grip_index(t):
        return sum(1 for a, b in windows if t >= b)

    state = []
    centre = obj.centre
    for f, name in enumerate(FINGERS):
        side = _normalize(np.asarray(_FINGER_SIDES[name]))
        # The hand arrives from the finger's side, a few cm away.
        start = centre + side * (0.5 * np.linalg.norm(obj.size[:2]) + 0.05) + np.array([0, 0, 0.03])
        start = surroundings.push_out(start[None], st.clearance + 0.01)[0]
        state.append({'t': float(rng.uniform(0.0, 0.3)), 'pos': start,
                      'normal': _normalize(start - centre), 'segments': [],
                      'side': side, 'strokes': 0, 'pending': None, 'contact': None})
    # Before the first move each finger hovers where it is.
    for f in range(3):
        s = state[f]
        s['segments'].append(_Segment(-1.0, s['t'], 'transit',
                                      (lambda times, p=s['pos']: np.repeat(p[None], len(times), 0)),
                                      False))

    events = []

    def choose_stroke(f, t, pos):
        gi = grip_index(t)
        pool = pool_list[gi]
        key = grip_of[gi].name
        d = np.linalg.norm(pool.starts - pos, axis=1)
        w = np.exp(-d / st.neighbourhood)
        w *= np.exp(st.side_preference * (pool.start_normals @ state[f]['side']))
        w *= np.where(explored[key] > 0, st.explored_weight, 1.0)
        w = np.where(pool.used, 0.0, w)
        if w.sum() <= 0:
            pool.used[:] = False
            w = np.exp(-d / st.neighbourhood)
        index = int(rng.choice(len(w), p=w / w.sum()))
        pool.used[index] = True
        return gi, index

    def mark_explored(points):
        sub = points[:: max(1, len(points) // 40)]
        for key, pool in pools.items():
            d2 = np.min(np.sum((pool.starts[:, None, :] - sub[None, :, :]) ** 2, axis=2), axis=1)
            explored[key] += d2 < 0.012 ** 2

    def next_window(t):
        for a, b in windows:
            if b > t:
                return a, b
        return None

    while True:
        active = [f for f in range(3) if state[f]['t'] < duration]
        if not active:
            break
        f = min(active, key=lambda i: state[i]['t'])
        s = state[f]
        t = s['t']
        window = next_window(t)
        limit = duration + 1.0
        if window is not None:
            limit = min(limit, window[0] - rng.uniform(0.0, 0.3))
        if window is not None and t >= limit - 0.4:
            # Re-grasp: withdraw, wait while the object turns, come back to a new stroke.
            wa, wb = window
            t_back = wb + rng.uniform(0.0, 0.4)
            gi, index = choose_stroke(f, t_back, s['pos'])
            pool = pool_list[gi]
            b = pool.starts[index] + pool.start_normals[index] * (st.clearance + 0.0005)
            seg = _away_segment(obj, surroundings, s['pos'], s['normal'], t, b,
                                pool.start_normals[index], t_back, st, rng, object_pose)
            s['segments'].append(seg)
            events.append((FINGERS[f], 'away', t, t_back))
            s['t'] = t_back
            s['pos'] = b
            s['normal'] = pool.start_normals[index]
            s['contact'] = None
            s['pending'] = (gi, index)
            continue
        planned = rng.uniform(*st.stroke_duration_range)
        speed = rng.uniform(*st.speed_range)
        sid = s['strokes']
        if s['pending'] is not None:
            gi, index = s['pending']
            s['pending'] = None
            pool = pool_list[gi]
        else:
            here = s['contact'] if s['contact'] is not None else s['pos']
            gi, index = choose_stroke(f, t, here)
            pool = pool_list[gi]
            slide = None
            if (s['contact'] is not None
                    and np.linalg.norm(pool.starts[index] - s['contact']) < st.slide_reach):
                slide = _slide_path(obj, surroundings, grip_of[gi], table, st, s['contact'],
                                    pool.starts[index])
            if slide is not None:
                # Contour following goes on over the surface to the next place.
                length = float(np.sum(np.linalg.norm(np.diff(slide, axis=0), axis=1)))
                dt = length / speed
                if t + dt >= limit:
                    dt = max(limit - t, 0.0)
                s['segments'].append(_Segment(t, t + dt, 'stroke',
                                              (lambda times, w=slide, a=t, b_=t + length / speed:
                                               _polyline_at(w, (times - a) / max(b_ - a, 1e-9))),
                                              True, sid))
                events.append((FINGERS[f], 'slide', t, t + dt))
                t += dt
            else:
                # Lift off and move through the air to the lifted start of the chosen stroke.
                b = pool.starts[index] + pool.start_normals[index] * (st.clearance + 0.0005)
                waypoints = _air_waypoints(obj, surroundings, s['pos'], s['normal'], b,
                                           pool.start_normals[index], st, rng)
                length = np.sum(np.linalg.norm(np.diff(waypoints, axis=0), axis=1))
                dt = float(np.clip(length / st.transit_speed, *st.transit_duration_range))
                if t + dt > limit - 0.2 and window is not None:
                    s['t'] = limit  # wait for the re-grasp where it is
                    s['segments'].append(_Segment(t, limit, 'transit',
                                                  (lambda times, p=s['pos']: np.repeat(p[None], len(times), 0)),
                                                  False))
                    s['contact'] = None
                    pool.used[index] = False
                    continue
                s['segments'].append(_Segment(t, t + dt, 'transit',
                                              (lambda times, w=waypoints, a=t, b_=t + dt:
                                               _timed_polyline(w, times, a, b_, st.transit_end_speed)),
                                              False))
                events.append((FINGERS[f], 'transit', t, t + dt))
                t += dt
        start = pool.starts[index]
        if rng.random() < st.dwell_probability:
            dd = rng.uniform(*st.dwell_duration_range)
            if t + dd < limit:
                s['segments'].append(_Segment(t, t + dd, 'dwell',
                                              (lambda times, p=start: np.repeat(p[None], len(times), 0)),
                                              True))
                events.append((FINGERS[f], 'dwell', t, t + dd))
                t += dd
        s['strokes'] += 1
        segs, t_end, end_point, end_normal = _stroke_segments(
            pool, index, t, planned, speed, st, rng, sid, limit)
        if not segs:
            # No time for a stroke before the re-grasp: stay lifted until it.
            s['segments'].append(_Segment(t, max(limit, t), 'transit',
                                          (lambda times, p=start + pool.start_normals[index] * (st.clearance + 0.0005):
                                           np.repeat(p[None], len(times), 0)), False))
            s['t'] = max(limit, t)
            s['pos'] = start + pool.start_normals[index] * (st.clearance + 0.0005)
            s['normal'] = pool.start_normals[index]
            s['contact'] = None
            continue
        s['segments'].extend(segs)
        events.append((FINGERS[f], 'stroke', t, t_end))
        mark_explored(pool.paths[index, :pool.lengths[index] + 1])
        s['t'] = t_end
        s['pos'] = end_point + end_normal * (st.clearance + 0.0005)
        s['normal'] = end_normal
        s['contact'] = end_point

    # --- sample every segment at the tracker frames --------------------------------------
    positions = np.zeros((3, n_frames, 3))
    contact = np.zeros((3, n_frames), dtype=bool)
    stroke = np.full((3, n_frames), -1, dtype=int)
    kind = np.zeros((3, n_frames), dtype=np.int8)
    for f in range(3):
        for seg in state[f]['segments']:
            k0 = max(0, int(math.ceil(seg.t0 * rate - 1e-9)))
            k1 = min(n_frames, int(math.ceil(seg.t1 * rate - 1e-9)))
            if k1 <= k0:
                continue
            positions[f, k0:k1] = seg.fn(times[k0:k1])
            contact[f, k0:k1] = seg.contact
            stroke[f, k0:k1] = seg.stroke_id if seg.kind == 'stroke' else -1
            kind[f, k0:k1] = SAMPLE_KINDS.index(seg.kind)
    # Contacts exactly on the surface; everything else at least `clearance` off it.
    on = contact.reshape(-1)
    flat = positions.reshape(-1, 3)
    flat[on] = obj.project_to_surface(flat[on])
    off = ~on
    flat[off] = surroundings.push_out(flat[off], st.clearance)
    positions = flat.reshape(3, n_frames, 3)
    grip = np.array([grip_index(t) for t in times], dtype=int) if windows else np.zeros(n_frames, int)
    return Exploration(times=times, positions=positions, contact=contact, stroke=stroke,
                       grip=grip, held_regions=grip_of, kind=kind, events=events)


def _away_segment(obj, surroundings, a_obj, na_obj, ta, b_obj, nb_obj, tb, settings, rng,
                  object_pose) -> _Segment:
    """The fingertip withdraws from the object and comes back, planned in the tracker
    frame (the object turns meanwhile), returned in the object frame: out briskly (about
    0.5 s) to ``away_distance_range`` from where it left, drifting slowly from there to the
    point it will come back from while the other hand turns the object, and back briskly."""
    st = settings
    centre = obj.centre
    pa, qa = object_pose(np.array([ta]))
    pb, qb = object_pose(np.array([tb]))
    a_trk = pa[0] + rotate_vectors(qa[0], a_obj)
    b_trk = pb[0] + rotate_vectors(qb[0], b_obj)
    out_a = rotate_vectors(qa[0], _normalize(_normalize(a_obj - centre) + na_obj))
    out_b = rotate_vectors(qb[0], _normalize(_normalize(b_obj - centre) + nb_obj))
    ra = a_trk + out_a * rng.uniform(*st.away_distance_range)
    rb = b_trk + out_b * rng.uniform(*st.away_distance_range)
    total = max(tb - ta, 1e-3)
    leg = min(0.5, 0.3 * total)
    clearance = st.clearance
    end_speed = st.transit_end_speed

    def fn(times):
        t = np.asarray(times, dtype=float)
        u_out = np.clip((t - ta) / leg, 0.0, 1.0)
        u_mid = np.clip((t - ta - leg) / max(total - 2 * leg, 1e-9), 0.0, 1.0)
        u_back = np.clip((t - (tb - leg)) / leg, 0.0, 1.0)
        p_trk = np.where((t < ta + leg)[:, None],
                         a_trk + (end_speed * u_out + (1 - end_speed) * _min_jerk(u_out))[:, None] * (ra - a_trk),
                         np.where((t < tb - leg)[:, None],
                                  ra + _min_jerk(u_mid)[:, None] * (rb - ra),
                                  rb + (end_speed * u_back + (1 - end_speed) * _min_jerk(u_back))[:, None]
                                  * (b_trk - rb)))
        pos, quat = object_pose(t)
        p_obj = rotate_vectors(quaternion_conjugate(quat), p_trk - pos)
        return surroundings.push_out(p_obj, clearance)
    return _Segment(ta, tb, 'away', fn, False)
