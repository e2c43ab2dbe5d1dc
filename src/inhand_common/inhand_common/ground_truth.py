"""Ground truth of a simulated session: the ``<bag folder>.truth.npz`` sidecar.

This module owns the format: its keys, where the file sits, the writer and the validating
reader. The simulator (``inhand_sim``) writes it; the metrics and pictures (``inhand_tools``)
and the launch scripts read it.

Beside each bag folder ``BAG`` (e.g. ``bags/cat_static/``) sits ``BAG.truth.npz`` (e.g.
``bags/cat_static.truth.npz``), an NPZ archive written with fixed zip timestamps (the same
arrays give the same bytes), holding exactly these arrays. Positions in metres, times in
seconds since the Unix epoch (the bag's stamps, ``stamp_ns / 1e9``), quaternions x, y, z, w;
OBJECT frame = the object's own frame:

=====================  ==========  ============================================================
key                    shape       content
=====================  ==========  ============================================================
object_name            () str      which object was explored: a built-in one (``cat``,
                                   ``bottle``, ``mug``), a shipped mesh (``cup``, ``animal``,
                                   ``duck``) or a mesh file's path as given
static                 () bool     static session (no object sensor in the bag)
rate                   () float    tracker frame rate, Hz
seed                   () int      the simulation seed
settings_json          (B,) uint8  UTF-8 JSON of every simulation setting
surface_points         (N, 3)      dense surface samples, OBJECT frame, uniform by area,
                                   N >= 100,000; float32 (about 20 nm at these sizes)
surface_normals        (N, 3)      their outward unit normals; float32
contacts               (M, 3)      noise-free contact points of every on-surface fingertip
                                   sample, OBJECT frame, in time order; each on the surface
contact_times          (M,)        their stamps
stray_points           (K, 3)      noise-free fingertip positions off the surface (transits,
                                   involuntary lifts, re-grasps, lift-offs, touch-downs),
                                   OBJECT frame, at any height: lifts rise continuously from
                                   the surface, so some are a fraction of a millimetre off it
                                   (at least 0.05 mm; sessions simulated with ``--lifts
                                   between-frames``, and all before it, keep each at least 6 mm
                                   off). Select the far ones by their distance to the surface
                                   (the map metrics count strays > 5 mm off); same order
stray_times            (K,)        their stamps
object_times           (T,)        the stamp of every tracker frame
object_positions       (T, 3)      true position of the OBJECT frame in the tracker frame
object_quaternions     (T, 4)      its true orientation: ``p_tracker = R p_object + position``;
                                   constant in static sessions
=====================  ==========  ============================================================

Sessions with a stereo shot add these (:data:`STEREO_KEYS`; all or none):

=====================  ==========  ============================================================
surface_colours        (N, 3)      uint8 RGB: the true (unshaded) colour of each surface sample
camera_pose            (7,)        the left camera (``stereo_left_optical``) in the tracker
                                   frame: x, y, z, qx, qy, qz, qw (``p_tracker = R p_cam + t``)
stereo_time            () float    the stamp of the image pair (s)
stereo_depth           (H, W)      float32: true depth (z, m) of every pixel of the rectified
                                   left image; inf where the ray meets nothing
stereo_object_mask     (H, W)      bool: the pixel sees the object (not backdrop or table)
stereo_focal           () float    focal length of the rectified pair (px)
stereo_baseline        () float    baseline (m): true disparity = focal * baseline / depth
=====================  ==========  ============================================================

**The plainer format of other session generators** (``<name>_truth.npz`` beside the bag
``<name>``, as ``../shared/data/validation_sessions`` holds) is read too: ``surface`` (N, 3)
samples of the true surface, ``contacts`` (M, 3) the true contact points, ``contact_t`` (M,)
their times, ``mode`` ('static' or 'tracked'), and optionally ``rate``, ``seconds``,
``speed_cms``; everything already in the map's frame (tracked: the object sensor's; static:
the tracker's). :func:`load_truth` turns it into a :class:`GroundTruth` with one identity
object pose (so the map's default frame needs no move), no stray points (the format has
none), normals estimated from the samples (:func:`estimated_normals`, turned towards the
free space around the object: only the pictures' shading and the mean offset along the
normal use them) and ``settings`` saying so, with that format's own explored surface
(within :data:`CONTACT_TRUTH_EXPLORED` of a contact). :func:`truth_path` finds either
sidecar, the simulator's first.

Which frame a map is in: a tracked map (``config/mapping.yaml``, registration ``tracked``)
is in the ``object`` frame, which is the object sensor's frame; the truth puts the object
frame on the object sensor (so the two frames are one). A static map
(``config/mapping_static.yaml``, no object sensor) is in the tracker frame
``polhemus_source``: :func:`in_frame` then moves the truth by the object's pose. Surface
samples go by the first pose (constant in a static session); contacts and strays go by the
pose at their own time (interpolated: linear position, slerp orientation), which is where
the fingertip really was in the tracker frame.
"""

from __future__ import annotations

import io
import json
import math
import re
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from inhand_common.rotations import quaternion_normalize, rotate_vectors, slerp

__all__ = ['CONTACT_TRUTH_EXPLORED', 'CONTACT_TRUTH_KEYS', 'FRAMES', 'STEREO_KEYS', 'TRUTH_KEYS',
           'GroundTruth', 'StereoTruth', 'default_frame', 'estimated_normals', 'in_frame',
           'load_truth', 'pose_at', 'truth_path', 'write_truth']

TRUTH_KEYS = ('object_name', 'static', 'rate', 'seed', 'settings_json', 'surface_points',
              'surface_normals', 'contacts', 'contact_times', 'stray_points', 'stray_times',
              'object_times', 'object_positions', 'object_quaternions')

STEREO_KEYS = ('surface_colours', 'camera_pose', 'stereo_time', 'stereo_depth',
               'stereo_object_mask', 'stereo_focal', 'stereo_baseline')

CONTACT_TRUTH_KEYS = ('surface', 'contacts', 'contact_t', 'mode')   # the plainer format
CONTACT_TRUTH_EXPLORED = 0.01   # m: that format's explored surface (its README's definition)

FRAMES = ('object', 'tracker')

# What numpy raises for a file that is not an NPZ archive of plain arrays, or is damaged.
_UNREADABLE = (OSError, ValueError, EOFError, zipfile.BadZipFile)

_SHAPES = {  # key: (number of dimensions, trailing size or None)
    'surface_points': (2, 3), 'surface_normals': (2, 3), 'contacts': (2, 3),
    'contact_times': (1, None), 'stray_points': (2, 3), 'stray_times': (1, None),
    'object_times': (1, None), 'object_positions': (2, 3), 'object_quaternions': (2, 4),
}


@dataclass(frozen=True, eq=False)
class StereoTruth:
    """What the stereo camera really saw: true depth of the rectified left image."""

    camera_pose: np.ndarray     # (7,) x y z qx qy qz qw: stereo_left_optical in the tracker
    time: float                 # the image pair's stamp (s)
    depth: np.ndarray           # (H, W) float32 z (m); inf: nothing hit
    object_mask: np.ndarray     # (H, W) bool: pixel on the object
    focal: float                # px
    baseline: float             # m

    @property
    def disparity(self) -> np.ndarray:
        """True disparity (px) of every pixel of the left image; 0 where nothing was hit."""
        with np.errstate(divide='ignore'):
            return (self.focal * self.baseline / self.depth).astype(np.float32)


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
    surface_colours: np.ndarray | None = field(default=None, compare=False)  # (N, 3) uint8
    stereo: StereoTruth | None = field(default=None, compare=False)

    @property
    def object_motion(self) -> float:
        """Largest distance (m) of the object origin from its first position."""
        if len(self.object_positions) == 0:
            return 0.0
        return float(np.linalg.norm(self.object_positions - self.object_positions[0],
                                    axis=1).max())


def truth_path(bag) -> Path:
    """The ground-truth sidecar of a bag: ``<bag folder>.truth.npz`` beside the bag folder
    (given the folder, or the .mcap/.db3 file inside it); the plainer format's
    ``<bag folder>_truth.npz`` when only that one is there."""
    bag = Path(bag)
    if bag.suffix in ('.mcap', '.db3') and not bag.is_dir():
        bag = bag.parent
    ours = bag.with_name(bag.name + '.truth.npz')
    theirs = bag.with_name(bag.name + '_truth.npz')
    return theirs if theirs.exists() and not ours.exists() else ours


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
    except _UNREADABLE as error:
        raise ValueError(f'{path}: not a truth file (cannot read it as NPZ: '
                         f'{type(error).__name__}: {error})') from None
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise ValueError(f'{path}: not a truth file (a single array, not an NPZ archive)')
    with data:
        missing = [key for key in TRUTH_KEYS if key not in data.files]
        if missing and all(key in data.files for key in CONTACT_TRUTH_KEYS):
            return _contact_truth(data, path)
        if missing:
            raise ValueError(f'{path}: not a simulator truth file: missing key(s) '
                             f'{", ".join(missing)} (it has {", ".join(sorted(data.files))})')
        try:
            arrays = {key: np.asarray(data[key], dtype=np.float64) for key in _SHAPES}
            settings_bytes = bytes(np.asarray(data['settings_json'], dtype=np.uint8))
            colours, stereo = _stereo_truth(data, path)
        except _UNREADABLE as error:
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
    if colours is not None and len(colours) != len(arrays['surface_points']):
        raise ValueError(f'{path}: surface_colours has {len(colours)} rows but surface_points '
                         f'has {len(arrays["surface_points"])}')
    return GroundTruth(settings=settings, path=path, frame='object', surface_colours=colours,
                       stereo=stereo, **scalars, **arrays)


def _contact_truth(data: Any, path: Path) -> GroundTruth:
    """A truth file of the plainer format (module doc) as a :class:`GroundTruth`."""
    try:
        surface = np.asarray(data['surface'], dtype=np.float64)
        contacts = np.asarray(data['contacts'], dtype=np.float64).reshape(-1, 3)
        times = np.asarray(data['contact_t'], dtype=np.float64).reshape(-1)
        mode = str(data['mode'])
        extra = {key: float(data[key]) for key in ('rate', 'seconds', 'speed_cms')
                 if key in data.files}
    except _UNREADABLE as error:
        raise ValueError(f'{path}: unreadable truth arrays ({type(error).__name__}: '
                         f'{error})') from None
    if mode not in ('static', 'tracked'):
        raise ValueError(f"{path}: truth key 'mode' is {mode!r}, expected 'static' or 'tracked'")
    if surface.ndim != 2 or surface.shape[1] != 3 or len(surface) == 0:
        raise ValueError(f"{path}: truth key 'surface' has shape {surface.shape}, expected (n, 3)")
    if len(contacts) != len(times):
        raise ValueError(f'{path}: contacts has {len(contacts)} rows but contact_t has '
                         f'{len(times)}')
    # the names say <object>_<st|tr>_..._s<seed>
    name = re.match(r'(?P<object>.+?)_(st|tr)_.*?(_s(?P<seed>\d+))?_truth\.npz$', path.name)
    settings = {'format': 'contacts (surface, contacts, contact_t, mode)',
                'explored_radius': CONTACT_TRUTH_EXPLORED, 'normals': 'estimated', **extra}
    return GroundTruth(
        object_name=name['object'] if name else path.name.removesuffix('_truth.npz'),
        static=mode == 'static', rate=extra.get('rate', math.nan),
        seed=int(name['seed']) if name and name['seed'] else 0, settings=settings,
        surface_points=surface, surface_normals=estimated_normals(surface), contacts=contacts,
        contact_times=times, stray_points=np.zeros((0, 3)), stray_times=np.zeros(0),
        object_times=np.zeros(1), object_positions=np.zeros((1, 3)),
        object_quaternions=np.array([[0.0, 0.0, 0.0, 1.0]]), frame='object', path=path)


def estimated_normals(points: np.ndarray, near: int = 12, spacing: float = 0.002) -> np.ndarray:
    """Unit normals (N, 3) of dense samples (N, 3) of a closed surface (a scanned object:
    solid inside, open cavities such as a cup's): the direction of least spread of each
    sample's ``near`` nearest, turned towards the *outside*, the free space connected to
    the border of a grid of ``spacing`` around the samples (the samples' cells, grown by one,
    are the wall). A sample whose two sides are both outside or both not (a part thinner
    than the grown wall, a closed hollow) is turned away from the centroid of all."""
    from scipy import ndimage  # type: ignore[import-untyped]
    from scipy.spatial import cKDTree  # type: ignore[import-untyped]
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) < 3:
        return np.tile([0.0, 0.0, 1.0], (len(points), 1))
    _, nearest = cKDTree(points).query(points, min(near, len(points)))
    local = points[nearest] - points[nearest].mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum('nki,nkj->nij', local, local))
    normals = vectors[:, :, 0]
    # the outside: free cells reached from the grid's border
    low = points.min(axis=0) - 4 * spacing
    index = np.floor((points - low) / spacing).astype(np.int64)
    shape = tuple(index.max(axis=0) + 5)
    wall = np.zeros(shape, dtype=bool)
    wall[tuple(index.T)] = True
    wall = ndimage.binary_dilation(wall, iterations=1)
    labels, _ = ndimage.label(~wall)
    outside = np.zeros(labels.max() + 1, dtype=bool)
    outside[np.unique(np.concatenate([labels[0].ravel(), labels[-1].ravel(), labels[:, 0].ravel(),
                                      labels[:, -1].ravel(), labels[:, :, 0].ravel(),
                                      labels[:, :, -1].ravel()]))] = True
    outside[0] = False          # label 0: the wall itself

    def is_outside(probe: np.ndarray) -> np.ndarray:
        cell = np.clip(np.floor((probe - low) / spacing).astype(np.int64), 0, np.array(shape) - 1)
        return np.asarray(outside[labels[tuple(cell.T)]])

    ahead, behind = is_outside(points + 2.5 * spacing * normals), is_outside(points - 2.5 * spacing * normals)
    fallback = np.einsum('ij,ij->i', normals, points - points.mean(axis=0)) >= 0
    keep = np.where(ahead != behind, ahead, fallback)
    return np.asarray(np.where(keep[:, None], normals, -normals))


def _stereo_truth(data: Any, path: Path) -> tuple[np.ndarray | None, StereoTruth | None]:
    """The optional stereo keys: all or none."""
    present = [key for key in STEREO_KEYS if key in data.files]
    if not present:
        return None, None
    missing = [key for key in STEREO_KEYS if key not in data.files]
    if missing:
        raise ValueError(f'{path}: stereo truth incomplete: has {", ".join(present)} but not '
                         f'{", ".join(missing)}')
    colours = np.asarray(data['surface_colours'])
    depth = np.asarray(data['stereo_depth'], dtype=np.float32)
    mask = np.asarray(data['stereo_object_mask'], dtype=bool)
    pose = np.asarray(data['camera_pose'], dtype=np.float64)
    if colours.ndim != 2 or colours.shape[1] != 3 or colours.dtype != np.uint8:
        raise ValueError(f'{path}: surface_colours must be (n, 3) uint8, is {colours.shape} '
                         f'{colours.dtype}')
    if depth.ndim != 2 or mask.shape != depth.shape or pose.shape != (7,):
        raise ValueError(f'{path}: stereo_depth {depth.shape}, stereo_object_mask '
                         f'{mask.shape} and camera_pose {pose.shape} do not fit together')
    stereo = StereoTruth(camera_pose=pose, time=_scalar(data, 'stereo_time', float, path),
                         depth=depth, object_mask=mask,
                         focal=_scalar(data, 'stereo_focal', float, path),
                         baseline=_scalar(data, 'stereo_baseline', float, path))
    return colours, stereo


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


def write_truth(path, arrays: Mapping[str, Any]) -> Path:
    """Write a truth file holding :data:`TRUTH_KEYS` (and :data:`STEREO_KEYS`, if given)
    from ``arrays``.

    ``settings`` (a dict) may stand instead of ``settings_json``; the four scalars may be
    plain Python values. The archive is stored uncompressed with fixed zip timestamps, so the
    same arrays give the same bytes (the bundled bags are regenerated bit for bit).
    """
    arrays = dict(arrays)
    if 'settings' in arrays:
        arrays['settings_json'] = np.frombuffer(
            json.dumps(arrays.pop('settings')).encode('utf-8'), dtype=np.uint8)
    missing = [key for key in TRUTH_KEYS if key not in arrays]
    if missing:
        raise ValueError(f'write_truth: missing {", ".join(missing)}')
    stereo = [key for key in STEREO_KEYS if key in arrays]
    if stereo and len(stereo) != len(STEREO_KEYS):
        raise ValueError('write_truth: the stereo keys go together; missing '
                         f'{", ".join(k for k in STEREO_KEYS if k not in arrays)}')
    arrays['object_name'] = np.array(str(arrays['object_name']))
    arrays['static'] = np.array(bool(arrays['static']))
    arrays['rate'] = np.array(float(arrays['rate']))
    arrays['seed'] = np.array(int(arrays['seed']), dtype=np.int64)
    path = Path(path)
    with zipfile.ZipFile(path, 'w', compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
        for key in TRUTH_KEYS + tuple(stereo):
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.asanyarray(arrays[key]), allow_pickle=False)
            info = zipfile.ZipInfo(f'{key}.npy', date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            archive.writestr(info, buffer.getvalue())
    return path
