"""Simulated pivot sessions: each finger in turn pivots about its pad resting in a dimple.

What a researcher does on the bench before a session (docs/mapping.md, "Real fingers"), with a
known tip offset, so pivot calibration (inhand_mapping/pivot_calibration.py) can be
checked against the truth. Per finger, in ``FINGERS`` order:

* ``approach`` s: the pad comes down 3 cm onto the dimple (not a pivot: calibration must
  leave these poses out);
* ``seconds`` s of pivoting: the finger, nail up, sweeps a cone about the pad centre, its
  tilt varying between 60% and 100% of ``tilt_deg / 2`` while the tilt's direction turns
  round once every ``CONE_PERIOD`` s, with a twist of up to ``twist_deg`` about its own
  axis: the largest angle between two poses is about ``tilt_deg`` (or twice the twist);
* ``approach`` s: it lifts off again.

The other fingers rest meanwhile, 4, 8 and 12 cm beside the dimple. Sensor positions carry tracker
noise (``noise_mm`` per axis) and orientations ``noise_deg`` per Euler angle (the Liberty's
static accuracy is 0.76 mm and 0.15 degrees RMS). Stations and stamps are those of a
session bag (static mode: no object sensor), so the same bag tools read it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from inhand_common.rotations import (
    euler_zyx_to_quaternion,
    quaternion_multiply,
    quaternion_normalize,
    rotate_vectors,
)
from inhand_sim.exploration import FINGERS

__all__ = ['PivotSession', 'PivotSettings', 'simulate_pivot']

CONE_PERIOD = 3.0      # s: the tilt's direction goes round once
REST_SPACING = 0.04    # m: resting fingers stand this far beside the dimple
APPROACH_HEIGHT = 0.03  # m: the pad comes down from this high


@dataclass(frozen=True)
class PivotSettings:
    tip_offsets: tuple = ((0.0, 0.0, -0.01),) * len(FINGERS)   # m, sensor frame, per finger
    tilt_deg: float = 45.0
    twist_deg: float = 10.0     # amplitude of the turn about the finger's own axis
    seconds: float = 10.0       # s of pivoting per finger
    approach: float = 1.0       # s coming down onto the dimple, and again lifting off
    rate: float = 30.0
    noise_mm: float = 1.0
    noise_deg: float = 0.15
    dimple: tuple = (0.25, 0.0, 0.1)   # m, tracker frame (z down: on a table below the source)
    seed: int = 0
    epoch: float = 1_700_000_000.0

    def __post_init__(self):
        offsets = np.asarray(self.tip_offsets, dtype=float)
        if offsets.shape != (len(FINGERS), 3) or not np.isfinite(offsets).all():
            raise ValueError(f'tip_offsets: one x, y, z per finger ({len(FINGERS)}) in metres')
        if not (0.0 <= self.tilt_deg <= 120.0 and 0.0 <= self.twist_deg <= 90.0):
            raise ValueError(f'tilt_deg {self.tilt_deg} must be in [0, 120] and twist_deg '
                             f'{self.twist_deg} in [0, 90]')
        if not (self.seconds > 0 and self.approach >= 0 and self.rate > 0):
            raise ValueError('seconds and rate must be positive, approach >= 0')


@dataclass
class PivotSession:
    """A pivot session in memory: what goes into the bag (the fields write_bag reads) and the
    truth (each finger's offset and pad centre, tracker frame)."""
    settings: PivotSettings
    stations: tuple
    stamps_ns: np.ndarray     # (T,)
    poses: np.ndarray         # (S, T, 7) x, y, z, qx, qy, qz, qw
    offsets: np.ndarray       # (F, 3) m, sensor frame
    pivots: np.ndarray        # (F, 3) m, tracker frame
    stereo_shots: list = field(default_factory=list)


def _nail_up() -> np.ndarray:
    """The finger at rest: the sensor's z axis up (the tracker's -z), its x forward."""
    return euler_zyx_to_quaternion(0.0, 0.0, math.pi)


def simulate_pivot(settings: PivotSettings) -> PivotSession:
    """The session of :class:`PivotSettings` (deterministic in ``seed``)."""
    rng = np.random.default_rng(settings.seed)
    fingers = len(FINGERS)
    per_finger = 2 * settings.approach + settings.seconds
    n = int(round(per_finger * fingers * settings.rate))
    t = np.arange(n) / settings.rate
    offsets = np.asarray(settings.tip_offsets, dtype=float)
    dimple = np.asarray(settings.dimple, dtype=float)
    rest = np.array([dimple + [0.0, REST_SPACING * (f + 1), 0.0] for f in range(fingers)])
    base = _nail_up()
    pads = np.broadcast_to(rest[:, None, :], (fingers, n, 3)).copy()
    quats = np.broadcast_to(base, (fingers, n, 4)).copy()
    pivots = np.empty((fingers, 3))
    for f in range(fingers):
        local = t - f * per_finger
        mine = (local >= 0) & (local < per_finger)
        pivots[f] = dimple
        s = local[mine]
        # Height above the dimple: down during the approach, 0 while pivoting, up after it.
        down = np.clip(1.0 - s / max(settings.approach, 1e-9), 0.0, 1.0)
        up = np.clip((s - settings.approach - settings.seconds) / max(settings.approach, 1e-9),
                     0.0, 1.0)
        height = APPROACH_HEIGHT * np.maximum(down, up)
        pivoting = (s >= settings.approach) & (s < settings.approach + settings.seconds)
        phase = (s - settings.approach) * 2.0 * math.pi / CONE_PERIOD
        half = math.radians(settings.tilt_deg) / 2.0
        tilt = np.where(pivoting, half * (0.8 + 0.2 * np.sin(0.37 * phase + f)), 0.0)
        twist = np.where(pivoting, math.radians(settings.twist_deg) * np.sin(0.53 * phase), 0.0)
        # tilt about a horizontal axis turning with phase, then twist about the finger's axis
        axis = np.stack([np.cos(phase), np.sin(phase), np.zeros_like(phase)], axis=1)
        q_tilt = np.concatenate([axis * np.sin(tilt / 2)[:, None], np.cos(tilt / 2)[:, None]], axis=1)
        q_twist = euler_zyx_to_quaternion(twist, 0.0, 0.0)
        quats[f, mine] = quaternion_normalize(quaternion_multiply(q_tilt, quaternion_multiply(
            np.broadcast_to(base, (len(s), 4)), q_twist)))
        pads[f, mine] = dimple - [0.0, 0.0, 1.0] * height[:, None]
    # The sensor sits where the pad centre minus the rotated offset puts it.
    sensors = pads - rotate_vectors(quats, offsets[:, None, :])
    sensors += rng.normal(0.0, settings.noise_mm / 1000.0, sensors.shape)
    sigma = math.radians(settings.noise_deg)
    wobble = euler_zyx_to_quaternion(*rng.normal(0.0, sigma, (3, fingers, n)))
    quats = quaternion_normalize(quaternion_multiply(quats, wobble))
    stamps = int(round(settings.epoch * 1e9)) + np.round(t * 1e9).astype(np.int64)
    poses = np.concatenate([sensors, quats], axis=2)
    return PivotSession(settings=settings, stations=tuple(FINGERS), stamps_ns=stamps,
                        poses=poses, offsets=offsets, pivots=pivots)
