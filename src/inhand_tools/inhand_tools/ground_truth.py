"""Ground truth of a simulated session: the ``<bag folder>.truth.npz`` sidecar.

The simulator writes, beside each bag folder ``BAG``, a file ``BAG.truth.npz`` with exactly
these arrays (object frame = the object's own frame, metres, quaternions x, y, z, w):

============================  ==============================================================
``object_name``               0-d str: which object was explored
``static``                    0-d bool: object fixed on the table (static-mode session)
``rate``                      0-d float: tracker frame rate (Hz)
``seed``                      0-d int: the simulation's random seed
``settings_json``             uint8: the simulation settings as JSON text
``surface_points``            (N, 3) surface samples, uniform by area (N >= 100,000)
``surface_normals``           (N, 3) outward unit normals at those samples
``contacts``                  (M, 3) true (noise-free) fingertip contact points
``contact_times``             (M,) their times (s)
``stray_points``              (K, 3) true fingertip positions off the surface
``stray_times``               (K,) their times (s)
``object_times``              (T,) times of the object poses (s)
``object_positions``          (T, 3) true pose of the object frame in the tracker frame
``object_quaternions``        (T, 4)
============================  ==============================================================

Which frame a map is in: a tracked map (``config/mapping.yaml``, registration ``tracked``)
is in the ``object`` frame, which is the object sensor's frame; the truth is assumed to put
the object frame on the object sensor (so the two frames are one). A static map
(``config/mapping_static.yaml``, no object sensor) is in the tracker frame
``polhemus_source``: :func:`in_frame` then moves the truth by the object's pose. Surface
samples go by the first pose (constant in a static session); contacts and strays go by the
pose at their own time (interpolated: linear position, slerp orientation), which is where
the fingertip really was in the tracker frame.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from inhand_common.rotations import quaternion_normalize, rotate_vectors, slerp
from inhand_sim.session import TRUTH_KEYS, truth_path  # the format's one definition

__all__ = ['GroundTruth', 'TRUTH_KEYS', 'FRAMES', 'load_truth', 'truth_path_for_bag',
           'in_frame', 'default_frame', 'pose_at', 'save_truth']

FRAMES = ('object', 'tracker')

_SHAPES = {  # key: (number of dimensions, trailing size or None)
    'surface_points': (2, 3), 'surface_normals': (2, 3), 'contacts': (2, 3),
    'contact_times': (1, None), 'stray_points': (2, 3), 'stray_times': (1, None),
    'object_times': (1, None), 'object_positions': (2, 3), 'object_quaternions': (2, 4),
}


@dataclass(frozen=True)
class GroundTruth:
    """What really happened in a simulated session, in one frame (``frame``)."""

    object_name: str
    static: bool
    rate: float
    seed: int
    settings: dict
    surface_points: np.ndarray
    surface_normals: np.ndarray
    contacts: np.ndarray
    contact_times: np.ndarray
    stray_points: np.ndarray
    stray_times: np.ndarray
    object_times: np.ndarray
    object_positions: np.ndarray
    object_quaternions: np.ndarray
    frame: str = 'object'
    path: Path | None = field(default=None, compare=False)

    @property
    def object_motion(self) -> float:
        """Largest distance (m) of the object origin from its first position."""
        if len(self.object_positions) == 0:
            return 0.0
        return float(np.linalg.norm(self.object_positions - self.object_positions[0],
                                    axis=1).max())


def truth_path_for_bag(bag) -> Path:
    """``BAG.truth.npz`` beside the bag folder (or beside the .mcap/.db3 file's folder)."""
    bag = Path(bag)
    if bag.is_file() and bag.suffix in ('.mcap', '.db3'):
        bag = bag.parent
    return truth_path(bag)


def _scalar(data, key, kind, path):
    value = data[key]
    if value.shape != ():
        raise ValueError(f'{path}: truth key {key!r} must be a scalar (0-d), has shape '
                         f'{value.shape}')
    try:
        return kind(value.item())
    except (TypeError, ValueError) as error:
        raise ValueError(f'{path}: truth key {key!r}: {error}') from None


def load_truth(path) -> GroundTruth:
    """The truth file at ``path`` (object frame). ValueError naming the problem if it is
    missing, not an NPZ archive, lacks keys or has arrays of the wrong shape."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f'{path}: no such truth file (the simulator writes '
                         '<bag folder>.truth.npz beside each bag)')
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as error:  # numpy raises many kinds for a foreign file
        raise ValueError(f'{path}: not a truth file (cannot read it as NPZ: '
                         f'{type(error).__name__}: {error})') from None
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise ValueError(f'{path}: not a truth file (a single array, not an NPZ archive)')
    with data:
        missing = [key for key in TRUTH_KEYS if key not in data.files]
        if missing:
            raise ValueError(f'{path}: not a simulator truth file: missing key(s) '
                             f'{", ".join(missing)} (it has {", ".join(sorted(data.files))})')
        try:
            arrays = {key: np.asarray(data[key], dtype=np.float64) for key in _SHAPES}
            settings_bytes = bytes(np.asarray(data['settings_json'], dtype=np.uint8))
        except Exception as error:
            raise ValueError(f'{path}: unreadable truth arrays ({type(error).__name__}: '
                             f'{error})') from None
        scalars = dict(object_name=_scalar(data, 'object_name', str, path),
                       static=_scalar(data, 'static', bool, path),
                       rate=_scalar(data, 'rate', float, path),
                       seed=_scalar(data, 'seed', int, path))
    for key, (ndim, size) in _SHAPES.items():
        array = arrays[key]
        if array.ndim != ndim or (size is not None and array.shape[-1] != size):
            want = f'(n, {size})' if size else '(n,)'
            raise ValueError(f'{path}: truth key {key!r} has shape {array.shape}, expected {want}')
    for points, times in (('surface_points', 'surface_normals'), ('contacts', 'contact_times'),
                          ('stray_points', 'stray_times'), ('object_positions', 'object_times'),
                          ('object_quaternions', 'object_times')):
        if len(arrays[points]) != len(arrays[times]):
            raise ValueError(f'{path}: {points} has {len(arrays[points])} rows but {times} '
                             f'has {len(arrays[times])}')
    if len(arrays['surface_points']) == 0:
        raise ValueError(f'{path}: truth file has no surface_points')
    try:
        settings = json.loads(settings_bytes.decode('utf-8')) if settings_bytes else {}
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f'{path}: settings_json is not JSON text ({error})') from None
    return GroundTruth(settings=settings, path=path, frame='object', **scalars, **arrays)


def default_frame(truth: GroundTruth) -> str:
    """The frame a map of this session is in by default: ``tracker`` for a static session
    (mapped with config/mapping_static.yaml), ``object`` otherwise."""
    return 'tracker' if truth.static else 'object'


def pose_at(truth: GroundTruth, times) -> tuple[np.ndarray, np.ndarray]:
    """Object pose in the tracker frame at ``times`` (positions (n, 3), quaternions (n, 4)):
    linear position and slerp between the two poses around each time, held constant
    before the first and after the last pose."""
    times = np.asarray(times, dtype=float).reshape(-1)
    pose_t, positions = truth.object_times, truth.object_positions
    quaternions = quaternion_normalize(truth.object_quaternions) if len(pose_t) else None
    if len(pose_t) == 0:
        raise ValueError('the truth file has no object poses; cannot express it in the '
                         'tracker frame')
    if len(pose_t) == 1 or len(times) == 0:
        return (np.repeat(positions[:1], len(times), axis=0),
                np.repeat(quaternions[:1], len(times), axis=0))
    order = np.argsort(pose_t, kind='stable')
    pose_t, positions, quaternions = pose_t[order], positions[order], quaternions[order]
    clipped = np.clip(times, pose_t[0], pose_t[-1])
    upper = np.clip(np.searchsorted(pose_t, clipped, side='right'), 1, len(pose_t) - 1)
    lower = upper - 1
    span = pose_t[upper] - pose_t[lower]
    fraction = np.where(span > 0, (clipped - pose_t[lower]) / np.where(span > 0, span, 1.0), 0.0)
    position = positions[lower] + fraction[:, None] * (positions[upper] - positions[lower])
    return position, slerp(quaternions[lower], quaternions[upper], fraction)


def in_frame(truth: GroundTruth, frame: str) -> GroundTruth:
    """The truth expressed in ``frame``: ``object`` (as stored) or ``tracker``.

    Tracker frame: surface samples and normals move by the object's first pose (its only
    pose in a static session); contacts and strays by the pose at their own times.
    """
    if frame not in FRAMES:
        raise ValueError(f'frame must be one of {", ".join(FRAMES)}, not {frame!r}')
    if frame == truth.frame:
        return truth
    if truth.frame != 'object':
        raise ValueError(f'cannot move truth from {truth.frame} to {frame}')
    first_p, first_q = pose_at(truth, truth.object_times[:1] if len(truth.object_times)
                               else np.zeros(1))
    surface = rotate_vectors(first_q[0], truth.surface_points) + first_p[0]
    normals = rotate_vectors(first_q[0], truth.surface_normals)

    def moved(points, times):
        if len(points) == 0:
            return points.copy()
        p, q = pose_at(truth, times)
        return rotate_vectors(q, points) + p

    return replace(truth, surface_points=surface, surface_normals=normals,
                   contacts=moved(truth.contacts, truth.contact_times),
                   stray_points=moved(truth.stray_points, truth.stray_times), frame=frame)


def save_truth(path, **arrays) -> Path:
    """Write a truth file with the keys of :data:`TRUTH_KEYS` (for tests and tools that make
    synthetic truth); ``settings`` (a dict) may be given instead of ``settings_json``."""
    if 'settings' in arrays:
        arrays['settings_json'] = np.frombuffer(json.dumps(arrays.pop('settings')).encode(),
                                                dtype=np.uint8)
    missing = [key for key in TRUTH_KEYS if key not in arrays]
    if missing:
        raise ValueError(f'save_truth: missing {", ".join(missing)}')
    arrays['object_name'] = np.array(str(arrays['object_name']))
    arrays['static'] = np.array(bool(arrays['static']))
    arrays['rate'] = np.array(float(arrays['rate']))
    arrays['seed'] = np.array(int(arrays['seed']))
    path = Path(path)
    with open(path, 'wb') as stream:
        np.savez_compressed(stream, **{key: arrays[key] for key in TRUTH_KEYS})
    return path
