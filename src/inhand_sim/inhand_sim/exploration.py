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
* **lift-off and touch-down**: a fingertip leaving the surface for a transit or a re-grasp
  rises from it along the normal (from rest, ``liftoff_duration_range`` to the hover height
  just past ``clearance``) and comes down the same way onto the next stroke's start;
* **away phases** (re-grasps of hand-held objects): every fingertip leaves the object,
  withdraws briskly 15-22 cm (out of the other hand's way), drifts there while the other
  hand turns the object, and comes back.

Every sample is either a contact (exactly on the surface) or an off-surface sample. With
``continuous_lifts`` (the default: it is what fingers do) the height above the surface is
continuous: lifts rise from 0 and come back to 0 (``sin^2`` of the lift's time, zero speed
at both ends), lift-offs and touch-downs pass through every height between the surface and
the hover height, so at 240 Hz there are off-surface samples at a fraction of a millimetre,
1, 2, 4 mm ... (never closer than ``min_height``, 0.05 mm; the ground truth's strays are
all of them). Without it (the sessions made before: ``continuous_lifts=False``) lift-off
and touch-down happen between two tracker frames and every off-surface sample is at least
``clearance`` (6 mm) off the surface.

Stroke speed: each stroke draws its mean sliding speed from ``speed_range`` (2-5 cm/s by
default; :func:`speed_range_around` gives a range around a chosen mean) and modulates it
within the stroke by ``speed_variation``.

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
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from inhand_common.rotations import quaternion_conjugate, rotate_vectors
from inhand_sim.guidance import EXPLORERS, StrokeGuide
from inhand_sim.objects import HeldRegion, SolidObject

__all__ = [
    'CONTACT',
    'FINGERS',
    'HAND_DEFAULTS',
    'SAMPLE_KINDS',
    'STRAY',
    'Exploration',
    'ExplorationSettings',
    'TrackerNoise',
    'explore',
    'parse_hand_setting',
    'speed_range_around',
]

FINGERS = ('thumb', 'index', 'middle')
CONTACT = 1
STRAY = 0
SAMPLE_KINDS = ('transit', 'stroke', 'dwell', 'lift', 'away', 'hover')

# The side of the object each finger prefers (object frame): thumb opposing the others.
_FINGER_SIDES = {'thumb': (0.0, -1.0, 0.0), 'index': (0.25, 1.0, 0.0),
                 'middle': (-0.25, 1.0, 0.0)}
_MODES = ('contour', 'meridian', 'free')
# The guided explorer's strokes lean towards its guide's direction instead (_integrate_strokes):
# this much per integration step, as a contour leans towards the horizontal.
_STEERED = len(_MODES)
_STEER_BLEND = 0.2


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
    table_reach: float = 0.02                    # static: downward faces this near the table are out of reach
    clearance: float = 0.006                     # transits and re-grasps keep this far off the surface
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
    # lift-offs, touch-downs and involuntary lifts pass through every height (False: they
    # jump past `clearance` between two frames, as sessions made before did)
    continuous_lifts: bool = True
    liftoff_duration_range: tuple = (0.08, 0.16)  # from the surface to the hover height, s
    min_height: float = 0.00005                  # off-surface samples at least this far off
    # --- how the hand moves: other hands than the default one (HAND_DEFAULTS). Each
    # default keeps the sessions made before these existed, bit for bit.
    stroke_length_range: tuple | None = None     # m: each stroke's planned length (None: by
                                                 # stroke_duration_range at its speed)
    speed_profile: str = 'wave'                  # 'wave': the speed varies by speed_variation
                                                 # within a stroke; 'bell': from rest to a
                                                 # peak and back to rest (minimum jerk)
    liftoff_height_range: tuple | None = None    # m: how far a lift-off rises (and a touch-
                                                 # down starts) off the surface (None: just
                                                 # past `clearance`)
    liftoff_speed_range: tuple | None = None     # m/s: mean speed of a lift-off or touch-down
                                                 # (None: liftoff_duration_range); a speed
                                                 # above height x rate is a flick within one frame
    liftoff_angle_range: tuple = (0.0, 0.0)      # degrees from the normal of a lift-off or
                                                 # touch-down: 0 along it, 45 oblique, 80
                                                 # nearly tangential (towards the stroke)
    hover_probability: float = 0.0               # after a stroke, the finger goes back over it
                                                 # this often, hovering close above the surface
    hover_height_range: tuple = (0.002, 0.006)   # m: how high it hovers
    tremor_amplitude: float = 0.0                # m: physiological tremor of every fingertip
    tremor_frequency: float = 10.0               # Hz
    held_scale: float = 1.0                      # the holding hand's region, scaled (radii)
    # Where a person takes an object first and keeps coming back to (its handle, the
    # paper's "most explored" and "first touched" region): each finger's first stroke
    # starts within focus_radius of focus_centre (object frame, m) and later strokes start
    # there focus_weight times as often. None: no such place.
    focus_centre: tuple | None = None
    focus_radius: float = 0.03                   # m
    focus_weight: float = 4.0
    # Who chooses where each stroke starts (inhand_sim.guidance): 'random' the person above,
    # 'guided' the predicted surface's next touches, 'greedy' the farthest from all touched.
    explorer: str = 'random'


# The hand's properties beyond the default hand, and their defaults (sessions written with
# these values leave them out of their settings, so older sessions stay byte for byte).
HAND_DEFAULTS = {name: getattr(ExplorationSettings(), name) for name in (
    'stroke_length_range', 'speed_profile', 'liftoff_height_range', 'liftoff_speed_range',
    'liftoff_angle_range', 'hover_probability', 'hover_height_range', 'tremor_amplitude',
    'tremor_frequency', 'held_scale', 'focus_centre', 'focus_radius', 'focus_weight',
    'explorer')}


# What each hand property takes, for command lines: (kind, low, high, unit). Ranges are two
# numbers "a,b" with low <= a <= b <= high; "none" restores a None default.
_HAND_VALUES = {
    'stroke_length_range': ('range', 0.005, 1.0, 'm'),
    'speed_profile': ('choice', ('wave', 'bell'), None, ''),
    'liftoff_height_range': ('range', 0.001, 0.2, 'm'),
    'liftoff_speed_range': ('range', 0.005, 5.0, 'm/s'),
    'liftoff_angle_range': ('range', 0.0, 85.0, 'degrees'),
    'hover_probability': ('number', 0.0, 1.0, ''),
    'hover_height_range': ('range', 0.0005, 0.05, 'm'),
    'tremor_amplitude': ('number', 0.0, 0.01, 'm'),
    'tremor_frequency': ('number', 0.1, 50.0, 'Hz'),
    'held_scale': ('number', 0.0, 5.0, ''),
    'focus_centre': ('point', -0.5, 0.5, 'm'),
    'focus_radius': ('number', 0.005, 0.2, 'm'),
    'focus_weight': ('number', 1.0, 100.0, ''),
    'explorer': ('choice', EXPLORERS, None, ''),
    'transit_speed': ('number', 0.05, 3.0, 'm/s'),
    'speed_variation': ('number', 0.0, 0.9, ''),
}


def parse_hand_setting(text: str) -> tuple[str, object]:
    """``NAME=VALUE`` of a hand property (:data:`HAND_DEFAULTS`, ``transit_speed``,
    ``speed_variation``) as (name, typed value); ValueError naming the allowed values."""
    name, sep, value = text.partition('=')
    name, value = name.strip(), value.strip()
    if not sep or name not in _HAND_VALUES:
        raise ValueError(f'{text!r}: expected NAME=VALUE with NAME one of {", ".join(_HAND_VALUES)}')
    kind, low, high, unit = _HAND_VALUES[name]
    if kind == 'choice':
        if value not in low:
            raise ValueError(f'{name}={value}: choose one of {", ".join(low)}')
        return name, value
    if kind in ('range', 'point') and value.lower() == 'none' and HAND_DEFAULTS.get(name, 0) is None:
        return name, None
    try:
        numbers = tuple(float(v) for v in value.split(','))
    except ValueError:
        numbers = ()
    count = {'range': 2, 'point': 3}.get(kind, 1)
    if len(numbers) != count or not all(low <= v <= high for v in numbers) or (
            kind == 'range' and numbers[0] > numbers[1]):
        shape = {'range': 'two numbers a,b with a <= b', 'point': 'three numbers x,y,z'}.get(
            kind, 'a number')
        raise ValueError(f'{name}={value}: {shape} in [{low:g}, {high:g}] {unit}'.rstrip())
    return name, (numbers if count > 1 else numbers[0])


def speed_range_around(mean: float, spread: float = 0.2) -> tuple[float, float]:
    """A stroke speed range (m/s) whose mean is ``mean``: strokes vary by ``spread`` (20%)
    about it, each modulated within itself by ``speed_variation``."""
    return (mean * (1.0 - spread), mean * (1.0 + spread))


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


def _tangential(v: np.ndarray, n: np.ndarray) -> np.ndarray:
    """``v`` (N, 3) without its component along the unit normals ``n`` (N, 3)."""
    return np.asarray(v - np.sum(v * n, axis=1, keepdims=True) * n)


def _arc_length(paths: np.ndarray) -> np.ndarray:
    """Length of each path (..., K, 3) along its points."""
    return np.asarray(np.linalg.norm(np.diff(paths, axis=-2), axis=-1).sum(axis=-1))


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

    def __init__(self, obj: SolidObject, table: bool):
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

    def push_out(self, p: np.ndarray, clearance, iterations: int = 12) -> np.ndarray:
        """Move points closer than ``clearance`` (a number, or one per point) out along the
        gradient until they are not (to 0.2 mm past it, or 20% past a smaller one)."""
        p = p.copy()
        clearance = np.broadcast_to(np.asarray(clearance, dtype=float), (len(p),))
        target = clearance + np.minimum(2e-4, 0.2 * clearance)
        for _ in range(iterations):
            d, g = self.sdf_grad(p)
            bad = d < clearance
            if not bad.any():
                break
            gg = g[bad]
            g2 = np.maximum(np.sum(gg * gg, axis=1), 1e-300)
            p[bad] += ((target[bad] - d[bad]) / g2)[:, None] * gg
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


def _forbidden(obj: SolidObject, held: HeldRegion, table: bool, settings: ExplorationSettings,
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


def _max_steps(settings: ExplorationSettings) -> int:
    """Integration steps of the longest stroke the settings plan."""
    st = settings
    max_len = (st.stroke_length_range[1] if st.stroke_length_range is not None else
               st.stroke_duration_range[1] * st.speed_range[1] * (1.0 + st.speed_variation))
    return math.ceil(max_len / st.stroke_step)


def _build_pool(obj: SolidObject, held: HeldRegion, table: bool, settings: ExplorationSettings,
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
    modes = rng.choice(len(_MODES), size=s_count, p=np.asarray(st.mode_probabilities))
    heading = _normalize(np.cross(normals, rng.normal(size=(s_count, 3))))
    paths, path_normals, lengths = _integrate_strokes(obj, surroundings, held, table, st, starts,
                                                      normals, heading, modes, rng)
    arclen = _arc_length(paths)
    keep = arclen >= st.min_stroke_length
    return _StrokePool(paths[keep], path_normals[keep], lengths[keep], arclen[keep],
                       starts[keep], normals[keep], np.zeros(int(keep.sum()), dtype=bool))


def _integrate_strokes(obj: SolidObject, surroundings: _Surroundings, held: HeldRegion, table: bool,
                       settings: ExplorationSettings, starts: np.ndarray, normals: np.ndarray,
                       heading: np.ndarray, modes: np.ndarray, rng: np.random.Generator,
                       steer: Callable[[np.ndarray], np.ndarray] | None = None,
                       length: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Strokes from ``starts`` (with their ``normals``) setting off along ``heading``, each
    following its mode (an index into _MODES, or _STEERED: towards ``steer(points)``, the
    direction a guide wants the fingertips at ``points`` to go), all at once, as far as the
    longest stroke the settings plan (or ``length``, of the path). Returns their
    paths (S, K+1, 3) and normals (past its end a stroke stays at its last point) and the
    number of valid steps of each."""
    st = settings
    s_count = len(starts)
    k_steps = _max_steps(st)
    if length is not None:      # the rest of the path would not be stroked
        k_steps = min(k_steps, math.ceil(length / st.stroke_step) + 1)
    up = np.array([0.0, 0.0, 1.0])
    turn_sigma = np.where(modes == 2, 0.10, 0.04)
    blend = np.where(modes == 2, 0.0, np.where(modes == _STEERED, _STEER_BLEND, 0.2))

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
        tp = _normalize(_tangential(tk, n))
        m = modes[idx]
        contour = np.cross(up, n)
        meridian = up - n[:, 2:3] * n
        pref = np.where((m == 0)[:, None], contour, meridian)
        steered = m == _STEERED
        if steer is not None and steered.any():
            wanted = steer(pk[steered])
            pref[steered] = _tangential(wanted, n[steered])
        weak = np.linalg.norm(pref, axis=1) < 0.2
        pref = _normalize(pref)
        # a contour or meridian goes either way; a guide's direction only its own
        pref *= np.where((np.sum(pref * tp, axis=1) < 0) & ~steered, -1.0, 1.0)[:, None]
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
    return paths[rows, last], path_normals[rows, last], lengths


# --- air paths ---------------------------------------------------------------------------

def _segment_clear(surroundings: _Surroundings, a, b, clearance: float) -> bool:
    n = max(2, int(np.linalg.norm(b - a) / 0.003) + 1)
    pts = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
    return bool(np.all(surroundings.sdf_grad(pts)[0] >= clearance))


def _air_waypoints(obj: SolidObject, surroundings: _Surroundings, a, na, b, nb,
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


def _slide_path(obj: SolidObject, surroundings, held, table, settings, a, b):
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
#
# Each finger's timeline is a list of segments planned one move at a time, always for the
# finger furthest behind (so that the fingers draw from the shared random stream and stroke
# pools in time order). Only then are the segments evaluated at the tracker frames, all
# frames of a segment at once.

@dataclass
class _Segment:
    """A stretch of one finger's timeline: from ``t0`` to ``t1`` it does ``kind`` at the
    positions ``fn`` gives (contacts are projected onto the surface when sampled)."""
    t0: float
    t1: float
    kind: str                                   # stroke, dwell, transit, lift, away
    fn: Callable[[np.ndarray], np.ndarray]      # times -> positions (object frame)
    contact: bool
    stroke_id: int = -1
    near: bool = False      # off the surface from (or down to) it: kept only min_height off,
                            # not `clearance` (lifts, lift-offs, touch-downs)


def _stay_at(point: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """Positions of a fingertip resting at ``point``."""
    return lambda times: np.repeat(point[None], len(times), axis=0)


def _slide_along(path: np.ndarray, t0: float, t1: float) -> Callable[[np.ndarray], np.ndarray]:
    """Positions sliding along ``path`` at constant speed, from its start at ``t0`` to its
    end at ``t1``."""
    return lambda times: _polyline_at(path, (times - t0) / max(t1 - t0, 1e-9))


def _lift_bump(point: np.ndarray, normal: np.ndarray, side: np.ndarray, t0: float,
               duration: float, height: float, low: float) -> Callable[[np.ndarray], np.ndarray]:
    """Positions of an involuntary lift above the contact ``point``: up along ``normal`` to
    ``height`` and back down over ``duration`` from ``t0``, drifting by ``side`` at the top.
    ``low`` 0: from the surface and back in a ``sin^2`` bump (continuous, at rest at both
    ends); ``low`` > 0: a sine bump from ``low`` (its ends clear of the surface, the jump
    to it between two frames)."""
    def fn(times):
        bump = np.sin(np.pi * np.clip((times - t0) / duration, 0.0, 1.0))
        if low == 0.0:
            bump = bump * bump
        return point + (low + (height - low) * bump)[:, None] * normal + bump[:, None] * side
    return fn


def _rise(point: np.ndarray, direction: np.ndarray, t0: float, duration: float, height: float,
          down: bool = False) -> Callable[[np.ndarray], np.ndarray]:
    """A fingertip leaving the surface at ``point`` along ``direction`` (the normal, or
    oblique): from rest to ``height`` over ``duration`` from ``t0``, the distance growing as
    the square of the time (or, ``down``, the same backwards: coming down to rest on it)."""
    def fn(times):
        u = np.clip((times - t0) / duration, 0.0, 1.0)
        rise = (1.0 - u) ** 2 if down else u ** 2
        return point + (height * rise)[:, None] * direction
    return fn


# --- one stroke: sliding with involuntary lifts -------------------------------------------

class _StrokeTrack:
    """One stroke of the pool and how the fingertip slides along it: after ``tau`` s of
    sliding it has covered ``arc(tau)`` of the path, at a speed ``v (1 + amp sin(omega tau +
    phase))`` (``amp`` the settings' speed variation; period and phase drawn per stroke),
    and it stops at the path's end."""

    def __init__(self, pool: _StrokePool, index: int, speed: float, planned: float,
                 settings: ExplorationSettings, rng: np.random.Generator):
        n_valid = pool.lengths[index] + 1
        self.path = pool.paths[index, :n_valid]
        self.normals = pool.normals[index, :n_valid]
        self.cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self.path, axis=0), axis=1))])
        self.total = self.cum[-1]
        self.speed = speed
        self.omega = 2 * math.pi / rng.uniform(1.5, 4.0)
        self.phase = rng.uniform(0, 2 * math.pi)
        self.amp = settings.speed_variation
        # 'bell': the planned length (or the path, if shorter) from rest to rest at the mean
        # speed, the speed a minimum-jerk profile peaking at 1.875 times the mean.
        self.bell = settings.speed_profile == 'bell'
        self.bell_length = min(self.total, speed * planned)
        self.bell_time = self.bell_length / speed

    def arc(self, tau):
        """Arc length slid after ``tau`` s of sliding (the integral of the speed)."""
        tau = np.asarray(tau, dtype=float)
        if self.bell:
            return self.bell_length * _min_jerk(tau / max(self.bell_time, 1e-9))
        s = self.speed * (tau + self.amp / self.omega
                          * (math.cos(self.phase) - np.cos(self.omega * tau + self.phase)))
        return np.minimum(s, self.total)

    def at_arc(self, s) -> np.ndarray:
        """Points at arc lengths ``s`` along the path."""
        return np.stack([np.interp(s, self.cum, self.path[:, k]) for k in range(3)], axis=1)

    def sliding_time(self, planned: float) -> float:
        """Sliding time needed to cover the path, capped by the planned duration (resolved
        to 1/2000 of it)."""
        if self.bell:
            return min(self.bell_time, planned)
        taus = np.linspace(0.0, planned, 2000)
        return float(taus[min(int(np.searchsorted(self.arc(taus), self.total)), len(taus) - 1)])

    def sliding_from(self, t0: float, tau0: float) -> Callable[[np.ndarray], np.ndarray]:
        """Positions from ``t0`` on, the fingertip having slid ``tau0`` s by then."""
        return lambda times: self.at_arc(self.arc(tau0 + (times - t0)))

    def contact_at(self, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """Where the fingertip is after ``tau`` s of sliding, and the surface normal there
        (that of the next path point)."""
        point = self.at_arc(self.arc(np.array([tau])))[0]
        i = min(int(np.searchsorted(self.cum, float(self.arc(tau)))), len(self.path) - 1)
        return point, self.normals[i]


@dataclass
class _LiftEpisode:
    """Involuntary lifts at one place of a stroke: 1, or sometimes a few in a row."""
    tau: float              # sliding time into the stroke at which the fingertip lifts
    lateral: np.ndarray     # (3,) sideways drift at the top (its part along the normal is dropped)
    lifts: list             # (duration, height, touch-down time) of each lift, in order


def _draw_lift_episodes(active: float, settings: ExplorationSettings,
                        rng: np.random.Generator) -> list[_LiftEpisode]:
    """Lift episodes at random moments of ``active`` s of sliding (Poisson, away from the
    stroke's first and last tenth), in time order."""
    st = settings
    episodes = []
    for tau_l in np.sort(rng.uniform(0.1 * active, 0.9 * active, rng.poisson(st.lift_rate * active))):
        reps = 1
        if rng.random() < st.repeated_lift_probability:
            reps = int(rng.integers(st.repeated_lift_count[0], st.repeated_lift_count[1] + 1))
        height = rng.uniform(*st.lift_height_range)
        lateral = rng.normal(0.0, 0.002, 3)
        lifts = [(rng.uniform(*st.lift_duration_range), height + rng.normal(0.0, 0.0015),
                  rng.uniform(0.08, 0.2)) for _ in range(reps)]
        episodes.append(_LiftEpisode(float(tau_l), lateral, lifts))
    return episodes


def _lifts_in_place(track: _StrokeTrack, episode: _LiftEpisode, t: float, limit: float,
                    stroke_id: int, low: float) -> tuple[list[_Segment], float]:
    """The segments of one lift episode starting at ``t``, and the time after it: each lift
    goes off the surface and comes back down at the same place for a moment (the sliding
    time stays frozen). Lifts that would not be back before ``limit`` are left out."""
    point, normal = track.contact_at(episode.tau)
    side = episode.lateral - np.dot(episode.lateral, normal) * normal
    segments = []
    for dur, height, touch in episode.lifts:
        if t + dur + touch >= limit:
            break
        segments.append(_Segment(t, t + dur, 'lift',
                                 _lift_bump(point, normal, side, t, dur, max(height, low), low), False,
                                 near=low == 0.0))
        segments.append(_Segment(t + dur, t + dur + touch, 'stroke', _stay_at(point), True, stroke_id))
        t += dur + touch
    return segments, t


def _slide_with_lifts(track: _StrokeTrack, episodes: list[_LiftEpisode], active: float, t0: float,
                      limit: float, stroke_id: int, low: float) -> list[_Segment]:
    """A stroke's segments from ``t0``: slides of ``active`` s in all, interrupted by the lift
    episodes, cut at ``limit``; empty segments dropped."""
    segments = []
    t, tau_prev = t0, 0.0
    for episode in [*episodes, _LiftEpisode(active, None, [])]:
        tb = t + (episode.tau - tau_prev)
        segments.append(_Segment(t, min(tb, limit), 'stroke', track.sliding_from(t, tau_prev), True,
                                 stroke_id))
        if tb >= limit:
            break
        t, tau_prev = tb, episode.tau
        if episode.lifts:
            lifts, t = _lifts_in_place(track, episode, t, limit, stroke_id, low)
            segments.extend(lifts)
    return [seg for seg in segments if seg.t1 > seg.t0]


def _stroke_segments(pool: _StrokePool, index: int, t0: float, duration: float, speed: float,
                     settings: ExplorationSettings, rng, stroke_id: int,
                     limit: float) -> tuple[list, float, np.ndarray, np.ndarray, np.ndarray]:
    """Segments of one stroke (with its involuntary lifts) starting at ``t0``, ending by
    ``limit``. Returns (segments, end time, last contact point, its normal, the stroke's
    direction there)."""
    track = _StrokeTrack(pool, index, speed, duration, settings, rng)
    active = track.sliding_time(duration)
    episodes = _draw_lift_episodes(active, settings, rng)
    low = 0.0 if settings.continuous_lifts else settings.clearance + 0.0005
    segments = _slide_with_lifts(track, episodes, active, t0, limit, stroke_id, low)
    if not segments:
        return [], t0, track.path[0], track.normals[0], _path_direction(track.path, 0)
    end_point = segments[-1].fn(np.array([segments[-1].t1]))[0]
    i_end = int(np.argmin(np.linalg.norm(track.path - end_point, axis=1)))
    return (segments, segments[-1].t1, end_point, track.normals[i_end],
            _path_direction(track.path, i_end))


def _path_direction(path: np.ndarray, i: int) -> np.ndarray:
    """The unit direction of a polyline at its point ``i`` (zero for a single point)."""
    if len(path) < 2:
        return np.zeros(3)
    a, b = (i - 1, i) if i > 0 else (0, 1)
    step = path[b] - path[a]
    return step / max(float(np.linalg.norm(step)), 1e-12)


# --- planning the three fingers ----------------------------------------------------------

@dataclass
class _Finger:
    """One fingertip while its timeline is planned (object frame)."""
    name: str                   # its entry in FINGERS
    side: np.ndarray            # unit vector towards the side of the object it prefers
    t: float                    # time up to which its timeline is planned, s
    pos: np.ndarray             # where it is at ``t``, off the surface (after a stroke: where
                                # it lifts to if it does not slide on)
    normal: np.ndarray          # outward direction at ``pos`` (the surface normal below it)
    contact: np.ndarray | None = None   # the surface point where its last stroke ended, if it
                                        # is still there at ``t`` (it may slide on from there)
    lift: tuple = (None, 0.0)   # how it leaves ``contact`` for ``pos``: direction, distance
    pending: tuple[int, int] | None = None  # (grip, pool index) of the stroke an away phase
                                            # brought it to, to be done next
    strokes: int = 0            # strokes begun: the id of the next one
    segments: list = field(default_factory=list)  # its timeline so far (_Segment), in order


class _Explorer:
    """Plans the fingers' timelines move by move: re-grasps (away phases), slides and
    transits to the next stroke, dwells and strokes.

    Holds what the moves share: the object, settings, random stream, surroundings, the
    windows of the re-grasps, the stroke pool of each grip with how often its stroke starts
    have been explored, the fingers and the log of events."""

    def __init__(self, obj: SolidObject, duration: float, rng: np.random.Generator,
                 settings: ExplorationSettings, grips: list, windows: list, table: bool,
                 object_pose: Callable | None):
        self.obj = obj
        self.duration = duration
        self.rng = rng
        self.st = settings
        self.windows = windows
        self.table = table
        self.object_pose = object_pose
        self.surroundings = _Surroundings(obj, table)
        # how far off the surface a fingertip leaves it and comes back: just past `clearance`
        self.hover = settings.clearance + 0.0005
        # the grips in force in turn: the first until the first window, the next after it ...
        self.grip_of = [grips[i % len(grips)] for i in range(len(windows) + 1)]
        self.pools: dict[str, _StrokePool] = {}      # one pool per held region
        for grip in self.grip_of:
            if grip.name not in self.pools:
                self.pools[grip.name] = _build_pool(obj, grip, table, settings, rng)
        self.pool_list = [self.pools[grip.name] for grip in self.grip_of]
        # per pool: how many strokes so far passed near each stroke start
        self.explored = {key: np.zeros(len(pool.starts)) for key, pool in self.pools.items()}
        self.fingers = [self._arriving(name) for name in FINGERS]
        self.events: list = []                       # (finger, kind, t_start, t_end)
        self.started: set[str] = set()               # fingers that chose a stroke already
        self.guide = None if settings.explorer == 'random' else \
            StrokeGuide(settings.explorer, obj.table_z if table else None)

    def _arriving(self, name: str) -> _Finger:
        """A finger where the hand arrives from: on its side, a few cm from the object,
        hovering there until a random moment in the first 0.3 s."""
        side = _normalize(np.asarray(_FINGER_SIDES[name]))
        centre = self.obj.centre
        start = centre + side * (0.5 * np.linalg.norm(self.obj.size[:2]) + 0.05) + np.array([0, 0, 0.03])
        start = self.surroundings.push_out(start[None], self.st.clearance + 0.01)[0]
        finger = _Finger(name=name, side=side, t=float(self.rng.uniform(0.0, 0.3)), pos=start,
                         normal=_normalize(start - centre))
        finger.segments.append(_Segment(-1.0, finger.t, 'transit', _stay_at(start), False))
        return finger

    # --- shared look-ups ---

    def grip_index(self, t: float) -> int:
        """Index of the grip in force at ``t``: the number of re-grasps over by then."""
        return sum(1 for _, b in self.windows if t >= b)

    def grip_indices(self, times: np.ndarray) -> np.ndarray:
        """``grip_index`` at each of ``times``."""
        ends = np.array([b for _, b in self.windows], dtype=float)
        return np.sum(times[:, None] >= ends[None, :], axis=1).astype(int)

    def next_window(self, t: float) -> tuple[float, float] | None:
        """The first re-grasp window not over at ``t``, if any."""
        for a, b in self.windows:
            if b > t:
                return a, b
        return None

    def choose_stroke(self, finger: _Finger, t: float, here: np.ndarray,
                      length: float | None = None) -> tuple[int, int]:
        """Draw ``finger``'s next stroke from the pool of the grip in force at ``t``: near
        ``here``, on the finger's side, preferably not explored yet, and not used since the
        pool was last reset (when none is left). Returns (grip, pool index), marked used.
        ``length``: the most of its path the stroke can slide (a guided stroke is steered
        that far), if known."""
        st = self.st
        gi = self.grip_index(t)
        pool = self.pool_list[gi]
        if self.guide is not None:
            guided = self.guide.choose(pool.starts, ~pool.used)
            if guided is not None:
                pool.used[guided] = True
                steering = self.guide.steering()
                if steering is not None:
                    self._steer(gi, guided, steering, length)
                return gi, guided
        d = np.linalg.norm(pool.starts - here, axis=1)
        w = np.exp(-d / st.neighbourhood)
        w *= np.exp(st.side_preference * (pool.start_normals @ finger.side))
        w *= np.where(self.explored[self.grip_of[gi].name] > 0, st.explored_weight, 1.0)
        if st.focus_centre is not None:
            focus = np.linalg.norm(pool.starts - np.asarray(st.focus_centre), axis=1) <= st.focus_radius
            first = finger.name not in self.started and focus[~pool.used].any()
            w *= np.where(focus, st.focus_weight, 0.0 if first else 1.0)
            self.started.add(finger.name)
        w = np.where(pool.used, 0.0, w)
        if w.sum() <= 0:
            pool.used[:] = False
            w = np.exp(-d / st.neighbourhood)
        index = int(self.rng.choice(len(w), p=w / w.sum()))
        pool.used[index] = True
        return gi, index

    def _steer(self, gi: int, index: int, steering: Callable[[np.ndarray], np.ndarray],
               length: float | None) -> None:
        """Stroke ``index`` of grip ``gi``'s pool becomes one from the same start that goes
        where ``steering`` sends it (the guided explorer: guidance.py), setting off that way,
        integrated for ``length`` of path (None: the longest the settings plan)."""
        pool = self.pool_list[gi]
        start, normal = pool.starts[index:index + 1], pool.start_normals[index:index + 1]
        wanted = steering(start)
        heading = _tangential(wanted, normal)
        if np.linalg.norm(heading) < 1e-9:      # nowhere to go: any way
            heading = np.cross(normal, self.rng.normal(size=(1, 3)))
        path, normals, valid = _integrate_strokes(
            self.obj, self.surroundings, self.grip_of[gi], self.table, self.st, start, normal,
            _normalize(heading), np.array([_STEERED]), self.rng, steering, length)
        steps = path.shape[1]       # past them the path stays at its end
        pool.paths[index, :steps], pool.normals[index, :steps] = path[0], normals[0]
        pool.paths[index, steps:], pool.normals[index, steps:] = path[0, -1], normals[0, -1]
        pool.lengths[index] = valid[0]
        pool.arclen[index] = float(_arc_length(path[0]))

    def mark_explored(self, points: np.ndarray) -> None:
        """Count a stroke along ``points`` (subsampled to about 40) as exploring every
        pool's stroke starts within 12 mm of it."""
        sub = points[:: max(1, len(points) // 40)]
        for key, pool in self.pools.items():
            d2 = np.min(np.sum((pool.starts[:, None, :] - sub[None, :, :]) ** 2, axis=2), axis=1)
            self.explored[key] += d2 < 0.012 ** 2

    def lifted(self, normal: np.ndarray, towards: np.ndarray) -> tuple[np.ndarray, float]:
        """How a finger leaves the surface (or comes down onto it), as a unit direction and
        a distance: just past ``clearance`` along the ``normal``, or with the hand's
        ``liftoff_height_range`` and ``liftoff_angle_range``, tilted from the normal towards
        the tangent direction ``towards`` (random where it has none)."""
        st = self.st
        if st.liftoff_height_range is None and st.liftoff_angle_range == (0.0, 0.0):
            return normal, self.hover
        height = (self.hover if st.liftoff_height_range is None
                  else self.rng.uniform(*st.liftoff_height_range))
        direction = normal
        if st.liftoff_angle_range != (0.0, 0.0):
            angle = math.radians(self.rng.uniform(*st.liftoff_angle_range))
            tangent = towards - np.dot(towards, normal) * normal
            if np.linalg.norm(tangent) < 1e-6:
                tangent = np.cross(normal, self.rng.normal(size=3))
            direction = math.cos(angle) * normal + math.sin(angle) * _normalize(tangent)
        return direction, height

    def _rise_time(self, distance: float) -> float:
        """How long a lift-off or touch-down over ``distance`` takes."""
        if self.st.liftoff_speed_range is None:
            return float(self.rng.uniform(*self.st.liftoff_duration_range))
        return distance / float(self.rng.uniform(*self.st.liftoff_speed_range))

    # --- the moves ---

    def plan(self) -> None:
        """Plan moves for the finger furthest behind until every finger reaches the end."""
        while True:
            behind = [finger for finger in self.fingers if finger.t < self.duration]
            if not behind:
                return
            self._next_move(min(behind, key=lambda finger: finger.t))

    def _next_move(self, finger: _Finger) -> None:
        """The finger's next move: an away phase when a re-grasp is due, otherwise to a
        stroke (by sliding or through the air, unless an away phase brought it there), a
        dwell now and then, and the stroke, all ending by ``limit`` (the re-grasp)."""
        t = finger.t
        window = self.next_window(t)
        limit = self.duration + 1.0
        if window is not None:
            limit = min(limit, window[0] - self.rng.uniform(0.0, 0.3))
            if t >= limit - 0.4:
                self._away(finger, window)
                return
        # A planned duration, or a planned length to slide at the stroke's speed.
        by_length = self.st.stroke_length_range is not None
        planned = self.rng.uniform(*(self.st.stroke_length_range if by_length
                                     else self.st.stroke_duration_range))
        speed = self.rng.uniform(*self.st.speed_range)
        if by_length:
            planned /= speed
        if finger.pending is not None:
            (gi, index), finger.pending = finger.pending, None
        else:
            here = finger.contact if finger.contact is not None else finger.pos
            # at most: the wave of its speed (_StrokeTrack) gains up to 4/pi s x variation
            reach = speed * (planned + 2.0 * self.st.speed_variation) * (1.0 + self.st.speed_variation)
            gi, index = self.choose_stroke(finger, t, here, reach)
            arrival = self._to_stroke(finger, t, gi, index, speed, limit, window)
            if arrival is None:     # waiting for the re-grasp instead
                return
            t = arrival
        t = self._dwell(finger, t, self.pool_list[gi].starts[index], limit)
        self._stroke(finger, t, gi, index, planned, speed, limit)

    def _away(self, finger: _Finger, window: tuple[float, float]) -> None:
        """Re-grasp: withdraw, wait while the object turns, come back to (lifted above, or
        with continuous lifts down onto) a stroke chosen from the next grip's pool, done
        next."""
        t = self._lift_off(finger, finger.t, 'away')
        t_back = max(window[1] + self.rng.uniform(0.0, 0.4), t + 0.1)
        gi, index = self.choose_stroke(finger, t_back, finger.pos)
        pool = self.pool_list[gi]
        down, height = self.lifted(pool.start_normals[index], -self._heading(pool, index))
        b = pool.starts[index] + down * height
        finger.segments.append(_away_segment(self.obj, self.surroundings, finger.pos, finger.normal, t, b,
                                             pool.start_normals[index], t_back, self.st, self.rng,
                                             self.object_pose))
        self.events.append((finger.name, 'away', t, t_back))
        finger.t, finger.pos, finger.normal = t_back, b, pool.start_normals[index]
        finger.contact = None
        finger.t = self._touch_down(finger, t_back, pool.starts[index], down, height, 'away')
        finger.pending = (gi, index)

    def _lift_off(self, finger: _Finger, t: float, kind: str, latest: float = math.inf) -> float:
        """With continuous lifts, a finger on the surface (``finger.contact``) rises from it
        to ``finger.pos`` (hover height, along ``finger.normal``) before it moves (``kind``),
        by ``latest`` at the latest. Returns the time it is up there."""
        if not self.st.continuous_lifts or finger.contact is None:
            return t
        direction, height = finger.lift
        rise = min(self._rise_time(height), latest - t)
        finger.segments.append(_Segment(t, t + rise, kind,
                                        _rise(finger.contact, direction, t, rise, height), False,
                                        near=True))
        finger.contact = None
        return t + rise

    def _touch_down(self, finger: _Finger, t: float, start: np.ndarray, direction: np.ndarray,
                    height: float, kind: str) -> float:
        """With continuous lifts, a finger ``height`` off the surface along ``direction``
        from ``start`` comes down onto it (the end of ``kind``). Returns the time it is on
        the surface."""
        if not self.st.continuous_lifts:
            return t
        fall = self._rise_time(height)
        finger.segments.append(_Segment(t, t + fall, kind,
                                        _rise(start, direction, t, fall, height, down=True), False,
                                        near=True))
        return t + fall

    @staticmethod
    def _heading(pool: _StrokePool, index: int) -> np.ndarray:
        """The direction stroke ``index`` of ``pool`` sets off in."""
        return _path_direction(pool.paths[index], 0)

    def _to_stroke(self, finger: _Finger, t: float, gi: int, index: int, speed: float, limit: float,
                   window: tuple[float, float] | None) -> float | None:
        """Move from ``t`` to the start of stroke ``index``: slide there over the surface if
        the finger is on it close by and the way is clear, else through the air. Returns the
        arrival time, or None when the finger waits for the re-grasp instead."""
        pool = self.pool_list[gi]
        path = None
        near = finger.contact is not None and (
            np.linalg.norm(pool.starts[index] - finger.contact) < self.st.slide_reach)
        if near:
            path = _slide_path(self.obj, self.surroundings, self.grip_of[gi], self.table, self.st,
                               finger.contact, pool.starts[index])
        if path is not None:
            return self._slide(finger, t, path, speed, limit)
        return self._transit(finger, t, gi, index, limit, window)

    def _slide(self, finger: _Finger, t: float, path: np.ndarray, speed: float, limit: float) -> float:
        """Contour following goes on over the surface along ``path`` at the stroke's speed
        (a contact like the stroke before, under its id), cut at ``limit``. Returns the
        arrival time."""
        length = float(_arc_length(path))
        dt = length / speed
        if t + dt >= limit:
            dt = max(limit - t, 0.0)
        finger.segments.append(_Segment(t, t + dt, 'stroke', _slide_along(path, t, t + length / speed),
                                        True, finger.strokes))
        self.events.append((finger.name, 'slide', t, t + dt))
        if self.guide is not None:
            self.guide.touched(path, stroke=False)
        return t + dt

    def _transit(self, finger: _Finger, t: float, gi: int, index: int, limit: float,
                 window: tuple[float, float] | None) -> float | None:
        """Lift off and move through the air to the lifted start of stroke ``index``. If it
        would not be there well before a re-grasp, the finger waits for the re-grasp where it
        is instead and the stroke goes back to the pool. Returns the arrival time, or None
        when waiting."""
        pool = self.pool_list[gi]
        down, height = self.lifted(pool.start_normals[index], -self._heading(pool, index))
        b = pool.starts[index] + down * height
        waypoints = _air_waypoints(self.obj, self.surroundings, finger.pos, finger.normal, b,
                                   pool.start_normals[index], self.st, self.rng)
        length = np.sum(np.linalg.norm(np.diff(waypoints, axis=0), axis=1))
        dt = float(np.clip(length / self.st.transit_speed, *self.st.transit_duration_range))
        # with continuous lifts the lift-off and touch-down take their time too
        landing = 2.0 * self.st.liftoff_duration_range[1] if self.st.continuous_lifts else 0.0
        if t + dt + landing > limit - 0.2 and window is not None:
            self._hover(finger, t, limit, finger.pos, finger.normal)
            pool.used[index] = False
            return None
        end_speed = self.st.transit_end_speed
        t0 = self._lift_off(finger, t, 'transit')
        finger.segments.append(_Segment(
            t0, t0 + dt, 'transit',
            lambda times: _timed_polyline(waypoints, times, t0, t0 + dt, end_speed), False))
        self.events.append((finger.name, 'transit', t, t0 + dt))
        return self._touch_down(finger, t0 + dt, pool.starts[index], down, height, 'transit')

    def _dwell(self, finger: _Finger, t: float, start: np.ndarray, limit: float) -> float:
        """Now and then the fingertip rests on the stroke's ``start`` for a moment (if that
        ends before ``limit``). Returns the time the stroke starts."""
        if self.rng.random() < self.st.dwell_probability:
            dd = self.rng.uniform(*self.st.dwell_duration_range)
            if t + dd < limit:
                finger.segments.append(_Segment(t, t + dd, 'dwell', _stay_at(start), True))
                self.events.append((finger.name, 'dwell', t, t + dd))
                t += dd
        return t

    def _stroke(self, finger: _Finger, t: float, gi: int, index: int, planned: float, speed: float,
                limit: float) -> None:
        """Stroke ``index`` from ``t`` (planned to last ``planned`` s at ``speed``), ending by
        ``limit``; the finger is left at the stroke's end, still in contact. With no time
        left for it, the finger stays lifted above the stroke's start until ``limit``."""
        pool = self.pool_list[gi]
        stroke_id = finger.strokes
        finger.strokes += 1
        segments, t_end, end_point, end_normal, end_direction = _stroke_segments(
            pool, index, t, planned, speed, self.st, self.rng, stroke_id, limit)
        if not segments:
            up, height = self.lifted(pool.start_normals[index], self._heading(pool, index))
            lifted = pool.starts[index] + up * height
            if self.st.continuous_lifts:    # on the stroke's start: it lifts off from there
                finger.t, finger.pos, finger.normal = t, lifted, pool.start_normals[index]
                finger.contact, finger.lift = pool.starts[index], (up, height)
            else:
                self._hover(finger, t, max(limit, t), lifted, pool.start_normals[index])
            return
        finger.segments.extend(segments)
        self.events.append((finger.name, 'stroke', t, t_end))
        path = pool.paths[index, :pool.lengths[index] + 1]
        self.mark_explored(path)
        if self.guide is not None:
            reached = int(np.argmin(np.linalg.norm(path - end_point, axis=1)))
            self.guide.touched(path[:reached + 1], stroke=True)
        up, height = self.lifted(end_normal, end_direction)
        finger.t, finger.pos, finger.normal = t_end, end_point + up * height, end_normal
        finger.contact, finger.lift = end_point, (up, height)
        if self.st.hover_probability > 0 and self.rng.random() < self.st.hover_probability:
            self._hover_back(finger, pool, index, end_point, speed, limit)

    def _hover_back(self, finger: _Finger, pool: _StrokePool, index: int, end_point: np.ndarray,
                    speed: float, limit: float) -> None:
        """After a stroke the finger rises a few millimetres and goes back over part of it
        at the stroke's speed without touching (``hover_height_range``), ending up there, off
        the surface."""
        path = pool.paths[index, :pool.lengths[index] + 1]
        normals = pool.normals[index, :pool.lengths[index] + 1]
        i_end = int(np.argmin(np.linalg.norm(path - end_point, axis=1)))
        if i_end < 2:
            return
        height = float(self.rng.uniform(*self.st.hover_height_range))
        back = max(2, int(round(i_end * self.rng.uniform(0.3, 1.0))))
        above = (path + normals * height)[i_end::-1][:back + 1]
        t = finger.t
        rise = min(height / 0.05, max(limit - t, 0.0))
        finger.segments.append(_Segment(t, t + rise, 'hover',
                                        _rise(end_point, normals[i_end], t, rise, height), False,
                                        near=True))
        t += rise
        length = float(np.sum(np.linalg.norm(np.diff(above, axis=0), axis=1)))
        t1 = min(t + length / speed, max(limit, t))
        glide = _slide_along(above, t, t + length / speed)
        if t1 > t:
            finger.segments.append(_Segment(t, t1, 'hover', glide, False, near=True))
        self.events.append((finger.name, 'hover', finger.t, t1))
        where = glide(np.array([t1]))[0]
        finger.t, finger.pos, finger.normal = t1, where, normals[i_end]
        finger.contact = None

    def _hover(self, finger: _Finger, t: float, until: float, point: np.ndarray,
               normal: np.ndarray) -> None:
        """The finger waits off the surface at ``point`` from ``t`` until ``until`` (a
        re-grasp), having lifted off to it first (continuous lifts, a finger on the surface)."""
        if until > t:
            t = self._lift_off(finger, t, 'transit', latest=until)
        finger.segments.append(_Segment(t, until, 'transit', _stay_at(point), False))
        finger.t, finger.pos, finger.normal = until, point, normal
        finger.contact = None


def _sample_timelines(fingers: list[_Finger], times: np.ndarray, rate: float, obj: SolidObject,
                      surroundings: _Surroundings, settings: ExplorationSettings,
                      tremor: np.ndarray | None = None):
    """Every finger's segments evaluated at the tracker frames ``times`` (= k / ``rate``),
    each segment at the frames in [t0, t1). Contacts are put exactly on the surface; the
    samples of lifts, lift-offs and touch-downs at least ``min_height`` off it, at their
    height above the surface itself (:func:`_above_the_surface`), everything else at least
    ``clearance`` off it. ``tremor`` (3, T, 3), if given, is added before that: on the
    surface it moves the contact along it. Returns positions (3, T, 3), contact, stroke and
    kind (3, T)."""
    n_frames = len(times)
    positions = np.zeros((3, n_frames, 3))
    contact = np.zeros((3, n_frames), dtype=bool)
    near = np.zeros((3, n_frames), dtype=bool)
    stroke = np.full((3, n_frames), -1, dtype=int)
    kind = np.zeros((3, n_frames), dtype=np.int8)
    for f, finger in enumerate(fingers):
        for seg in finger.segments:
            k0 = max(0, math.ceil(seg.t0 * rate - 1e-9))
            k1 = min(n_frames, math.ceil(seg.t1 * rate - 1e-9))
            if k1 <= k0:
                continue
            positions[f, k0:k1] = seg.fn(times[k0:k1])
            contact[f, k0:k1] = seg.contact
            near[f, k0:k1] = seg.near
            stroke[f, k0:k1] = seg.stroke_id if seg.kind == 'stroke' else -1
            kind[f, k0:k1] = SAMPLE_KINDS.index(seg.kind)
    if tremor is not None:
        positions += tremor
    on = contact.reshape(-1)
    flat = positions.reshape(-1, 3)
    flat[on] = obj.project_to_surface(flat[on])
    off = ~on
    if settings.continuous_lifts:
        low = near.reshape(-1)[off]
        floor = np.where(low, settings.min_height, settings.clearance)
        flat[off] = surroundings.push_out(flat[off], floor)
        flat[off] = _above_the_surface(obj, flat[off], floor)
    else:
        flat[off] = surroundings.push_out(flat[off], settings.clearance)
    return flat.reshape(3, n_frames, 3), contact, stroke, kind


def _above_the_surface(obj: SolidObject, points: np.ndarray, floor: np.ndarray,
                       zone: float = 0.002) -> np.ndarray:
    """Off-surface points within ``zone`` of the surface, placed at their height (the SDF,
    at least ``floor``) along the normal above their nearest point ON the surface: for a mesh
    the distance grid is a fraction of a millimetre off the triangles, so a sample planned
    0.1 mm up is put 0.1 mm above the triangles, not maybe under them."""
    points = points.copy()
    height = obj.sdf(points)
    close = np.flatnonzero(height < zone)
    if close.size:
        foot = obj.project_to_surface(points[close])
        up = np.maximum(height[close], floor[close])
        points[close] = foot + up[:, None] * obj.normals(foot)
    return points


def explore(obj: SolidObject, duration: float, rate: float, rng: np.random.Generator,
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
    grips = list(grips) if grips else [obj.static_grip]
    if settings.held_scale != 1.0:
        grips = [replace(grip, radii=tuple(r * settings.held_scale for r in grip.radii))
                 for grip in grips]
    windows = sorted((float(a), float(b)) for a, b in away_windows)
    if windows and object_pose is None:
        raise ValueError('away windows need object_pose')
    times = np.arange(round(duration * rate)) / rate
    explorer = _Explorer(obj, duration, rng, settings, grips, windows, table, object_pose)
    explorer.plan()
    positions, contact, stroke, kind = _sample_timelines(explorer.fingers, times, rate, obj,
                                                         explorer.surroundings, settings,
                                                         _tremor(settings, times, rng))
    return Exploration(times=times, positions=positions, contact=contact, stroke=stroke,
                       grip=explorer.grip_indices(times), held_regions=explorer.grip_of, kind=kind,
                       events=explorer.events)


def _tremor(settings: ExplorationSettings, times: np.ndarray, rng: np.random.Generator
            ) -> np.ndarray | None:
    """Each fingertip's tremor at ``times`` (3, T, 3): a sine of ``tremor_amplitude`` at
    ``tremor_frequency`` on each axis, phases drawn per finger and axis; None without one."""
    if settings.tremor_amplitude <= 0.0:
        return None
    phase = rng.uniform(0.0, 2.0 * math.pi, size=(3, 1, 3))
    return settings.tremor_amplitude * np.sin(
        2.0 * math.pi * settings.tremor_frequency * times[None, :, None] + phase)


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

    def brisk(u):
        """Progress along a brisk leg: minimum jerk blended with constant speed (the finger
        leaves and reaches the surface already moving)."""
        return end_speed * u + (1 - end_speed) * _min_jerk(u)

    def fn(times):
        t = np.asarray(times, dtype=float)
        u_out = np.clip((t - ta) / leg, 0.0, 1.0)
        u_mid = np.clip((t - ta - leg) / max(total - 2 * leg, 1e-9), 0.0, 1.0)
        u_back = np.clip((t - (tb - leg)) / leg, 0.0, 1.0)
        p_trk = np.where((t < ta + leg)[:, None],
                         a_trk + brisk(u_out)[:, None] * (ra - a_trk),
                         np.where((t < tb - leg)[:, None],
                                  ra + _min_jerk(u_mid)[:, None] * (rb - ra),
                                  rb + brisk(u_back)[:, None] * (b_trk - rb)))
        pos, quat = object_pose(t)
        p_obj = rotate_vectors(quaternion_conjugate(quat), p_trk - pos)
        return surroundings.push_out(p_obj, clearance)
    return _Segment(ta, tb, 'away', fn, False)
