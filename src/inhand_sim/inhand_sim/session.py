"""Simulated exploration sessions: the driver's bag plus exact ground truth beside it.

A session is

* **static**: the object stands on the table in front of the transmitter, its centre at
  ``static_centre`` (default [0.25, 0.0, 0.05] m, the centre of config/mapping_static.yaml's
  workspace) in the tracker frame ``polhemus_source`` (x forward, y right, z down: the
  object's up is the tracker's -z). The other hand holds it still at its top
  (``SolidObject.static_grip``); no object sensor is published. Stations: thumb, index,
  middle.
* **moving** (non-static): the other hand holds the object in the air around
  ``moving_centre``; it drifts (a few cm) and sways (about 10 degrees) all the time, and at
  each **re-grasp** (about every ``regrasp_interval`` s; at least one when the session is
  long enough) the exploring fingers all leave the object, the other hand turns it by
  60-120 degrees and takes it at another place (the next of ``SolidObject.moving_grips``),
  and the exploration resumes. The object sensor (station ``object``) is the OBJECT frame;
  optionally a second one (``object2``) is rigidly attached at
  ``SolidObject.second_sensor``. Stations: thumb, index, middle, object (, object2).

Fingertip positions in the tracker frame are the object pose applied to the object-frame
fingertip positions of :mod:`inhand_sim.exploration`, plus tracker noise (Gaussian per axis,
``noise_mm``, and rare outliers of 1-2 cm). Object sensors get their own small noise
(``object_noise_mm`` per axis, ``object_noise_deg`` per Euler angle). Fingertip
orientations: the sensor's z axis along the outward surface normal (nail away from the
surface).

Files (:func:`write_session`)
-----------------------------
``<output>/``: a rosbag2 bag (MCAP, rosbags writer) holding exactly the driver's topics:
``/polhemus/<name>/pose`` of type ``geometry_msgs/msg/PoseStamped``, ``frame_id``
``polhemus_source``, metres, quaternion x, y, z, w. All stations of one tracker frame carry
the same ``header.stamp``, which is also the message's log time; frames are
``1 / rate`` apart from ``epoch`` (1_700_000_000.0 s), so the bag is reproducible: the same
settings give a bit-for-bit identical bag (MCAP file and metadata.yaml; rosbags writes no
wall-clock time).

``<output>.truth.npz`` beside the bag folder: the ground truth, in the format that
:mod:`inhand_common.ground_truth` defines (contacts, strays and surface samples in the
OBJECT frame, which is the object sensor's frame; the object's true pose in the tracker
frame). Every fingertip sample is a contact or a stray: M + K = 3 T.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from inhand_common.ground_truth import truth_path, write_truth
from inhand_common.mcap_integrity import stamp_bag_crcs
from inhand_common.ros_names import STEREO_FRAME, TRACKER_FRAME, station_pose_topic
from inhand_common.rotations import (
    euler_zyx_to_quaternion,
    matrix_to_quaternion,
    quaternion_multiply,
    quaternion_normalize,
    rotate_vectors,
    slerp,
)
from inhand_mapping.pose_cdr import encode_pose_stamped
from inhand_sim.catalogue import load_object
from inhand_sim.exploration import (
    FINGERS,
    HAND_DEFAULTS,
    Exploration,
    ExplorationSettings,
    TrackerNoise,
    explore,
)
from inhand_sim.objects import SolidObject
from inhand_sim.stereo_rig import DEFAULT_VIEW_DIRECTION, RenderedPair, StereoRig, render_pair
from inhand_sim.textures import surface_colour

__all__ = [
    'EPOCH',
    'SessionSettings',
    'SimulatedSession',
    'StereoConnections',
    'simulate',
    'write_bag',
    'write_session',
]

EPOCH = 1_700_000_000.0
FRAME_ID = TRACKER_FRAME
MSGTYPE = 'geometry_msgs/msg/PoseStamped'

@dataclass(frozen=True)
class SessionSettings:
    """Everything that decides a session (all of it goes into ``settings_json``)."""
    object_name: str = 'cat'             # a built-in object, a shipped mesh or a mesh file
                                          # (inhand_sim.catalogue)
    mesh_scale: float = 1.0               # meshes: metres per unit of the file
    mesh_up: str = 'z'                    # meshes: the file's axis that points up
    static: bool = True
    regrasp: bool = True                  # moving sessions: re-grasps by the other hand
    second_object_sensor: bool = False    # moving sessions: also publish 'object2'
    rate: float = 15.0                    # Hz: 15 (the paper), 30, 120 or 240 (the device's two)
    duration: float = 60.0                # s
    seed: int = 0
    noise_mm: float = 1.0                 # fingertip tracker noise, per axis
    outlier_fraction: float = 0.002
    outlier_range_mm: tuple = (10.0, 20.0)
    object_noise_mm: float = 0.5          # object sensor position noise, per axis
    object_noise_deg: float = 0.1         # object sensor orientation noise, per Euler angle
    epoch: float = EPOCH                  # stamp of the first frame, s
    surface_samples: int = 120_000        # ground-truth surface samples in the sidecar
    static_centre: tuple = (0.25, 0.0, 0.05)   # tracker frame, where the object's centre stands
    static_yaw_deg: float = 0.0           # turn of the static object about the vertical
    moving_centre: tuple = (0.25, 0.0, 0.0)    # tracker frame, around which it is held
    drift_mm: float = 20.0                # moving: amplitude of the hand's drift
    sway_deg: float = 10.0                # moving: amplitude of the hand's sway
    regrasp_interval: float = 40.0        # s between re-grasps
    regrasp_window: float = 3.0           # s the fingers are off the object per re-grasp
    regrasp_angle_range_deg: tuple = (60.0, 120.0)
    exploration: ExplorationSettings = field(default_factory=ExplorationSettings)
    # One stereo pair of the object, taken at the first tracker frame (before the exploration;
    # in tracked mode the object sensor is already streaming), by the default virtual rig
    # (inhand_sim.stereo_rig) looking at the object from camera_distance.
    stereo: bool = False
    # Pairs in all: the first before the exploration, the others at evenly spaced frames
    # during it (a held object shows the fixed rig another side each time).
    stereo_shots: int = 1
    camera_distance: float = 0.42         # m
    # Where the rig stands around the object (tracker frame, z down): azimuth about the
    # vertical from the tracker's +x, elevation above the horizontal. None: the default rig's
    # view (from the tracker's -y side, 34 degrees up).
    camera_azimuth_deg: float | None = None
    camera_elevation_deg: float | None = None
    # Real fingers (docs/mapping.md, "Real fingers"): the sensor on the nail, the pad a ball touching
    # the surface. tip_offset_mm: the pad centre in the sensor's frame, one x, y, z for
    # every finger or one per finger (None: the sensor is the contact point, as in the
    # bundled bags); pad_radius_mm: the pad ball's radius; finger_roll_deg: how far the
    # finger rolls about its own axis during a stroke (amplitude).
    tip_offset_mm: tuple | None = None
    pad_radius_mm: float = 0.0
    finger_roll_deg: float = 0.0

    def __post_init__(self):
        problems = []
        if self.tip_offset_mm is not None and np.shape(self.tip_offset_mm) not in (
                (3,), (len(FINGERS), 3)):
            problems.append(f'tip_offset_mm {self.tip_offset_mm}: one x, y, z, or one per '
                            f'finger ({len(FINGERS)})')
        if not 0.0 <= self.pad_radius_mm <= 15.0:
            problems.append(f'pad_radius_mm {self.pad_radius_mm} must be in [0, 15]')
        if not 0.0 <= self.finger_roll_deg <= 60.0:
            problems.append(f'finger_roll_deg {self.finger_roll_deg} must be in [0, 60]')
        if self.rate <= 0 or not math.isfinite(self.rate):
            problems.append(f'rate {self.rate} must be a positive number of Hz')
        if not (0 < self.duration <= 24 * 3600):
            problems.append(f'duration {self.duration} must be in (0, 86400] s')
        if self.noise_mm < 0 or self.object_noise_mm < 0 or self.object_noise_deg < 0:
            problems.append('noise levels must be >= 0')
        if not 0 <= self.outlier_fraction <= 1:
            problems.append(f'outlier_fraction {self.outlier_fraction} must be in [0, 1]')
        if self.surface_samples < 1:
            problems.append('surface_samples must be >= 1')
        if self.seed < 0:
            problems.append(f'seed {self.seed} must be >= 0')
        if not 1 <= self.stereo_shots <= 100:
            problems.append(f'stereo_shots {self.stereo_shots} must be in [1, 100]')
        if not 0.15 <= self.camera_distance <= 2.0:
            problems.append(f'camera_distance {self.camera_distance} must be in [0.15, 2] m')
        if self.camera_elevation_deg is not None and not -80 <= self.camera_elevation_deg <= 89:
            problems.append(f'camera_elevation_deg {self.camera_elevation_deg} must be in '
                            '[-80, 89] degrees')
        if not (self.mesh_scale > 0 and math.isfinite(self.mesh_scale)):
            problems.append(f'mesh_scale {self.mesh_scale} must be a positive number')
        if self.static and self.second_object_sensor:
            problems.append('a static session has no object sensor, so no second one either')
        if problems:
            raise ValueError('; '.join(problems))

    def to_json(self) -> str:
        # The viewpoint keys only when set, so sessions made before they existed (the
        # bundled bags) are written byte for byte as they were.
        # So is the number of pairs when it is the one pair they had, and the mesh's scale
        # and up axis when they are the file's own.
        unset = {'camera_azimuth_deg': None, 'camera_elevation_deg': None, 'stereo_shots': 1,
                 'mesh_scale': 1.0, 'mesh_up': 'z', 'tip_offset_mm': None, 'pad_radius_mm': 0.0,
                 'finger_roll_deg': 0.0}
        values = {key: value for key, value in asdict(self).items()
                  if not (key in unset and value == unset[key])}
        # The hand's properties likewise when they are the default hand's.
        values['exploration'] = {key: value for key, value in values['exploration'].items()
                                 if not (key in HAND_DEFAULTS and value == HAND_DEFAULTS[key])}
        return json.dumps(values, sort_keys=True, separators=(',', ':'))

    @property
    def real_fingers(self) -> bool:
        """Whether the sensors sit off the contact point (the pad's centre, a nail)."""
        return self.tip_offset_mm is not None or self.pad_radius_mm > 0 \
            or self.finger_roll_deg > 0

    def tip_offsets(self) -> np.ndarray:
        """(fingers, 3) m: each finger's pad centre in its sensor's frame."""
        offsets = np.zeros(3) if self.tip_offset_mm is None else \
            np.asarray(self.tip_offset_mm, dtype=float) / 1000.0
        return np.broadcast_to(offsets, (len(FINGERS), 3)).copy()

    @property
    def camera_direction(self) -> tuple[float, float, float]:
        """Object -> camera, tracker frame: from the azimuth and elevation, or the default
        rig's direction."""
        if self.camera_azimuth_deg is None and self.camera_elevation_deg is None:
            return DEFAULT_VIEW_DIRECTION
        default_x, default_y, default_z = DEFAULT_VIEW_DIRECTION
        azimuth = math.radians(self.camera_azimuth_deg) if self.camera_azimuth_deg is not None \
            else math.atan2(default_y, default_x)
        elevation = math.radians(self.camera_elevation_deg) \
            if self.camera_elevation_deg is not None \
            else math.asin(-default_z / math.dist((0, 0, 0), DEFAULT_VIEW_DIRECTION))
        return (math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                -math.sin(elevation))


@dataclass
class SimulatedSession:
    """A simulated session in memory: what goes into the bag, and the ground truth."""
    settings: SessionSettings
    object: SolidObject
    stations: tuple                # station names in publishing order
    stamps_ns: np.ndarray          # (T,) int64
    poses: np.ndarray              # (S, T, 7): x, y, z, qx, qy, qz, qw in the tracker frame
    exploration: Exploration
    truth: dict                    # the sidecar's arrays (inhand_common.ground_truth)
    regrasp_windows: list          # (start, end) s relative to the first frame
    # (frame index, image pair) of every pair, when settings.stereo; the first at frame 0
    stereo_shots: list[tuple[int, RenderedPair]] = field(default_factory=list)

    @property
    def stereo_shot(self) -> RenderedPair | None:
        """The pair before the exploration (the one the truth describes)."""
        return self.stereo_shots[0][1] if self.stereo_shots else None

    @property
    def message_count(self) -> int:
        """Messages in the bag: every station's pose per frame, and four per stereo pair."""
        return self.poses.shape[0] * self.poses.shape[1] + 4 * len(self.stereo_shots)

    @property
    def duration(self) -> float:
        return (self.stamps_ns[-1] - self.stamps_ns[0]) / 1e9 if len(self.stamps_ns) else 0.0


# --- object motion -----------------------------------------------------------------------

def _static_pose(settings: SessionSettings, obj: SolidObject):
    """Constant pose: the object upright (object +z = tracker -z), its centre at
    ``static_centre``."""
    q = quaternion_multiply(euler_zyx_to_quaternion(math.radians(settings.static_yaw_deg), 0.0, 0.0),
                            euler_zyx_to_quaternion(0.0, 0.0, math.pi))
    q = quaternion_normalize(q)
    position = np.asarray(settings.static_centre, dtype=float) - rotate_vectors(q, obj.centre)

    def pose(times):
        n = len(np.atleast_1d(times))
        return np.repeat(position[None], n, axis=0), np.repeat(q[None], n, axis=0)
    return pose


def _regrasp_times(settings: SessionSettings, rng: np.random.Generator) -> list:
    if settings.static or not settings.regrasp:
        return []
    w = settings.regrasp_window
    times = []
    k = 1
    while settings.regrasp_interval * k + w + 4.0 < settings.duration:
        times.append(settings.regrasp_interval * k + rng.uniform(-3.0, 3.0))
        k += 1
    if not times and settings.duration >= w + 8.0:
        times.append(0.45 * settings.duration)
    return [(t, t + w) for t in times]


def _moving_pose(settings: SessionSettings, obj: SolidObject, windows: list,
                 rng: np.random.Generator) -> Callable:
    """The hand-held object's pose as a function of time (s from the first frame):
    drifting and swaying all the time, turned substantially at each re-grasp, about its
    centre."""
    centre0 = np.asarray(settings.moving_centre, dtype=float)
    drift_amp = settings.drift_mm / 1000.0
    # three sinusoids per axis with periods of 6-25 s
    drift = [(rng.uniform(0.3, 0.6, 3) * drift_amp, 2 * math.pi / rng.uniform(6.0, 25.0, 3),
              rng.uniform(0, 2 * math.pi, 3)) for _ in range(3)]
    sway_amp = math.radians(settings.sway_deg)
    sway = [(rng.uniform(0.35, 0.65, 2) * sway_amp, 2 * math.pi / rng.uniform(4.0, 15.0, 2),
             rng.uniform(0, 2 * math.pi, 2)) for _ in range(3)]
    yaw0 = rng.uniform(-0.5, 0.5)
    base = [quaternion_normalize(quaternion_multiply(euler_zyx_to_quaternion(yaw0, 0.0, 0.0),
                                                     euler_zyx_to_quaternion(0.0, 0.0, math.pi)))]
    turns = []
    for _ in windows:
        angle = math.radians(rng.uniform(*settings.regrasp_angle_range_deg)) * rng.choice([-1.0, 1.0])
        small = rng.normal(0.0, math.radians(8.0), 3)
        kind = int(rng.integers(3))   # about the vertical, about forward, about sideways
        small[kind] = angle
        dq = euler_zyx_to_quaternion(*small)
        base.append(quaternion_normalize(quaternion_multiply(dq, base[-1])))
        turns.append(angle)
    base = np.array(base)
    centre_obj = obj.centre

    def sums(params, t):
        out = np.zeros((len(t), len(params)))
        for axis, (amp, omega, phase) in enumerate(params):
            out[:, axis] = np.sum(amp[None] * np.sin(omega[None] * t[:, None] + phase[None]), axis=1)
        return out

    def pose(times):
        t = np.atleast_1d(np.asarray(times, dtype=float))
        q_base = np.repeat(base[:1], len(t), axis=0)
        for k, (wa, wb) in enumerate(windows):
            # the turn itself, in the middle of the window (fingers away), smoothly
            ra, rb = wa + 0.2 * (wb - wa), wb - 0.2 * (wb - wa)
            u = np.clip((t - ra) / (rb - ra), 0.0, 1.0)
            u = u ** 3 * (10 - 15 * u + 6 * u ** 2)
            inside = t >= ra
            if inside.any():
                q_base[inside] = slerp(base[k], base[k + 1], u[inside])
        angles = sums(sway, t)
        q_sway = euler_zyx_to_quaternion(angles[:, 0], angles[:, 1], angles[:, 2])
        q = quaternion_normalize(quaternion_multiply(q_sway, q_base))
        centre = centre0 + sums(drift, t)
        position = centre - rotate_vectors(q, centre_obj)
        return position, q
    pose.turn_angles = turns
    return pose


# --- the simulation ----------------------------------------------------------------------

def _tangent_reference(n: np.ndarray) -> np.ndarray:
    """A unit tangent per outward normal (N, 3): the object's x (its y where the normal is
    near x) projected into the tangent plane."""
    ref = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    x = ref - np.sum(ref * n, axis=1, keepdims=True) * n
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _fingertip_orientations(obj: SolidObject, p_obj: np.ndarray, q_obj: np.ndarray) -> np.ndarray:
    """Fingertip sensor orientations in the tracker frame: z along the outward normal
    there (object frame), x along the object's x as far as it goes, composed with the object's."""
    n = obj.normals(p_obj)
    x = _tangent_reference(n)
    y = np.cross(n, x)
    q_local = matrix_to_quaternion(np.stack([x, y, n], axis=2))
    return quaternion_normalize(quaternion_multiply(q_obj, q_local))


MOTION_SMOOTHING = 0.3    # s: the finger's axis follows the motion averaged over this long
ROLL_PERIOD = 5.0         # s: one roll of the finger to each side and back
PITCH_SHARE = 0.3         # the finger's pitch varies by this share of the roll's amplitude


def _real_finger(obj: SolidObject, p_obj: np.ndarray, times: np.ndarray, finger: int,
                 settings: SessionSettings, q_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A real finger at the fingertip path ``p_obj`` (object frame; on the surface at a
    contact): the sensor's position (object frame) and orientation (tracker frame).

    The pad is a ball of ``pad_radius_mm`` touching the surface, so its centre is one radius
    out along the outward normal. The finger's axis (sensor x) follows the motion along the
    surface (averaged over ``MOTION_SMOOTHING``), the nail (sensor z) faces away from the
    surface; the finger rolls about its axis by up to ``finger_roll_deg`` and pitches by
    ``PITCH_SHARE`` of that. The sensor is where the pad centre minus the offset, turned by
    the sensor's orientation, puts it (tip_offsets.py's relation, inverted)."""
    n = obj.normals(p_obj)
    pad = p_obj + settings.pad_radius_mm / 1000.0 * n
    velocity = np.gradient(p_obj, times, axis=0) if len(times) > 1 else np.zeros_like(p_obj)
    width = max(1, int(round(MOTION_SMOOTHING / max(float(np.median(np.diff(times))), 1e-6))))
    kernel = np.ones(width) / width
    smooth = np.stack([np.convolve(velocity[:, k], kernel, mode='same') for k in range(3)], axis=1)
    along = smooth - np.sum(smooth * n, axis=1, keepdims=True) * n
    moving = np.linalg.norm(along, axis=1) > 1e-3
    x = np.where(moving[:, None], along, _tangent_reference(n))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(n, x)
    q_local = matrix_to_quaternion(np.stack([x, y, n], axis=2))
    amplitude = math.radians(settings.finger_roll_deg)
    roll = amplitude * np.sin(2.0 * math.pi * times / ROLL_PERIOD + finger)
    pitch = PITCH_SHARE * amplitude * np.sin(2.0 * math.pi * times / (1.4 * ROLL_PERIOD) + 2 * finger)
    q_local = quaternion_normalize(quaternion_multiply(
        q_local, euler_zyx_to_quaternion(np.zeros_like(roll), pitch, roll)))
    sensor = pad - rotate_vectors(q_local, settings.tip_offsets()[finger])
    return sensor, quaternion_normalize(quaternion_multiply(q_obj, q_local))


def simulate(settings: SessionSettings, progress: Callable[[str], None] | None = None
             ) -> SimulatedSession:
    """Simulate a session: deterministic in ``settings`` (seeded numpy Generators)."""
    say = progress or (lambda message: None)
    obj = load_object(settings.object_name, settings.mesh_scale, settings.mesh_up)
    seeds = np.random.SeedSequence(settings.seed).spawn(5)
    rng_surface, rng_motion, rng_explore, rng_noise, rng_object_noise = (
        np.random.default_rng(s) for s in seeds)
    n_frames = int(round(settings.duration * settings.rate))
    if n_frames < 2:
        raise ValueError(f'{settings.duration} s at {settings.rate} Hz is fewer than 2 frames')
    stamps_ns = (int(round(settings.epoch * 1e9))
                 + np.round(np.arange(n_frames) * (1e9 / settings.rate)).astype(np.int64))
    rel = (stamps_ns - stamps_ns[0]) / 1e9

    windows = _regrasp_times(settings, rng_motion)
    if settings.static:
        pose_fn = _static_pose(settings, obj)
        grips = [obj.static_grip]
    else:
        pose_fn = _moving_pose(settings, obj, windows, rng_motion)
        grips = list(obj.moving_grips)
    say('exploring')
    exploration = explore(obj, settings.duration, settings.rate, rng_explore,
                          settings.exploration, grips=grips, away_windows=windows,
                          table=settings.static, object_pose=pose_fn)
    # explore's sample times are k / rate: the same frames as the stamps
    obj_pos, obj_q = pose_fn(rel)

    say('sensors')
    noise = TrackerNoise(settings.noise_mm / 1000.0, settings.outlier_fraction,
                         tuple(v / 1000.0 for v in settings.outlier_range_mm))
    stations = list(FINGERS)
    poses = []
    for f in range(len(FINGERS)):
        p_obj = exploration.positions[f]
        if settings.real_fingers:
            p_obj, q_tip = _real_finger(obj, p_obj, rel, f, settings, obj_q)
        else:
            q_tip = _fingertip_orientations(obj, p_obj, obj_q)
        p_trk = obj_pos + rotate_vectors(obj_q, p_obj)
        p_meas = p_trk + noise.sample((n_frames,), rng_noise)
        poses.append(np.concatenate([p_meas, q_tip], axis=1))
    if not settings.static:
        sensors = [('object', np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))]
        if settings.second_object_sensor:
            mount_p, mount_q = obj.second_sensor
            sensors.append(('object2', np.asarray(mount_p, float), np.asarray(mount_q, float)))
        sigma_p = settings.object_noise_mm / 1000.0
        sigma_a = math.radians(settings.object_noise_deg)
        for name, mount_p, mount_q in sensors:
            p = obj_pos + rotate_vectors(obj_q, np.broadcast_to(mount_p, (n_frames, 3)))
            q = quaternion_multiply(obj_q, np.broadcast_to(mount_q, (n_frames, 4)))
            p = p + rng_object_noise.normal(0.0, sigma_p, (n_frames, 3))
            dq = euler_zyx_to_quaternion(*rng_object_noise.normal(0.0, sigma_a, (3, n_frames)))
            q = quaternion_normalize(quaternion_multiply(q, dq))
            stations.append(name)
            poses.append(np.concatenate([p, q], axis=1))
    poses = np.stack(poses)

    say('ground truth')
    surface, normals = obj.sample_surface(settings.surface_samples, rng_surface)
    times_s = stamps_ns / 1e9
    order_pos = exploration.positions.transpose(1, 0, 2)   # (T, fingers, 3): time order
    order_contact = exploration.contact.T
    frame_times = np.repeat(times_s[:, None], len(FINGERS), axis=1)
    truth = {
        'object_name': np.array(settings.object_name),
        'static': np.array(bool(settings.static)),
        'rate': np.array(float(settings.rate)),
        'seed': np.array(int(settings.seed), dtype=np.int64),
        'settings_json': np.frombuffer(settings.to_json().encode('utf-8'), dtype=np.uint8).copy(),
        # float32 (about 20 nm at these sizes) halves the bundled truth files.
        'surface_points': surface.astype(np.float32),
        'surface_normals': normals.astype(np.float32),
        'contacts': order_pos[order_contact],
        'contact_times': frame_times[order_contact],
        'stray_points': order_pos[~order_contact],
        'stray_times': frame_times[~order_contact],
        'object_times': times_s,
        'object_positions': obj_pos,
        'object_quaternions': obj_q,
    }
    shots = []
    if settings.stereo:
        say('stereo pair' if settings.stereo_shots == 1 else
            f'{settings.stereo_shots} stereo pairs')
        frames = [int(k) for k in np.round(np.arange(settings.stereo_shots) * n_frames
                                           / settings.stereo_shots)]
        shots = [(k, _stereo_shot(settings, obj, obj_pos[k], obj_q[k], number))
                 for number, k in enumerate(frames)]
        truth.update(_stereo_truth(obj, shots[0][1], surface, times_s[0]))
    return SimulatedSession(settings=settings, object=obj, stations=tuple(stations),
                            stamps_ns=stamps_ns, poses=poses, exploration=exploration,
                            truth=truth, regrasp_windows=windows, stereo_shots=shots)


def _stereo_shot(settings: SessionSettings, obj: SolidObject, position: np.ndarray,
                 quaternion: np.ndarray, number: int = 0) -> RenderedPair:
    """The ``number``-th pair the rig takes of the object, at the pose given: static objects
    on their table, held objects in the air (the backdrop behind them either way). The rig
    stands where a bench rig would: fixed, aimed at the table's object position whether or
    not the object is held (so one camera_pose calibration serves every session)."""
    rig = StereoRig.looking_at(target=settings.static_centre,
                               direction=settings.camera_direction,
                               distance=settings.camera_distance)
    # Its own stream of the seed: the poses above stay what they were without a camera.
    # Later pairs: streams of their own after it.
    rng = np.random.default_rng(np.random.SeedSequence(settings.seed).spawn(6 + number)[5 + number])
    return render_pair(rig, obj, (position, quaternion), rng, table=settings.static)


def _stereo_truth(obj: SolidObject, shot: RenderedPair, surface: np.ndarray,
                  stamp: float) -> dict:
    """The truth file's stereo keys (inhand_common.ground_truth.STEREO_KEYS)."""
    return {
        'surface_colours': surface_colour(obj.texture, surface),
        'camera_pose': np.asarray(shot.camera_pose, dtype=np.float64),
        'stereo_time': np.array(float(stamp)),
        'stereo_depth': shot.depth.astype(np.float32),
        'stereo_object_mask': shot.mask.astype(bool),
        'stereo_focal': np.array(float(shot.focal)),
        'stereo_baseline': np.array(float(shot.baseline)),
    }


# --- files -------------------------------------------------------------------------------

class PoseRecording(Protocol):
    """What :func:`write_bag` writes: a session's poses (and its stereo pairs, if any)."""
    stations: tuple
    stamps_ns: np.ndarray            # (T,) int64
    poses: np.ndarray                # (S, T, 7)
    stereo_shots: list


def write_bag(session: PoseRecording, path, progress: Callable[[float], None] | None = None
              ) -> Path:
    """Write the session's poses as a rosbag2 MCAP bag at ``path`` (must not exist);
    ``session`` is a :class:`SimulatedSession` or a pivot session (pivot.py)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    path = Path(path)
    store = get_typestore(Stores.ROS2_JAZZY)
    n_stations, n_frames, _ = session.poses.shape
    stamps = session.stamps_ns
    secs = (stamps // 1_000_000_000).tolist()
    nsecs = (stamps % 1_000_000_000).tolist()
    poses = session.poses.tolist()
    stamp_list = stamps.tolist()
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        pairs = dict(session.stereo_shots)
        camera = StereoConnections(writer, store)
        if 0 in pairs:      # the pair before the exploration comes first
            camera.write(pairs.pop(0), stamp_list[0])
        connections = [writer.add_connection('/' + station_pose_topic(name), MSGTYPE,
                                             typestore=store)
                       for name in session.stations]
        step = max(1, n_frames // 50)
        for k in range(n_frames):
            sec, nsec, stamp = secs[k], nsecs[k], stamp_list[k]
            if k in pairs:
                camera.write(pairs[k], stamp)
            for s in range(n_stations):
                writer.write(connections[s], stamp,
                             encode_pose_stamped(sec, nsec, FRAME_ID, poses[s][k]))
            if progress is not None and (k % step == 0 or k == n_frames - 1):
                progress((k + 1) / n_frames)
    stamp_bag_crcs(path)        # rosbags writes no CRCs: damage would go unnoticed
    return path


STEREO_TOPICS = {  # side: (image topic, camera_info topic, frame)
    'left': ('/stereo/left/image_raw', '/stereo/left/camera_info', STEREO_FRAME),
    'right': ('/stereo/right/image_raw', '/stereo/right/camera_info', 'stereo_right_optical'),
}


class StereoConnections:
    """The four camera topics of a bag, each added once, and pairs written as a camera driver
    publishes them: rgb8 images and their camera_info, all four stamped with the exposure."""

    def __init__(self, writer, store):
        self.writer, self.store = writer, store
        self.connections: dict = {}

    def write(self, shot: RenderedPair, stamp_ns: int) -> None:
        store = self.store
        types = store.types
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        for side, image, camera in (('left', shot.left, shot.left_camera),
                                    ('right', shot.right, shot.right_camera)):
            image_topic, info_topic, frame = STEREO_TOPICS[side]
            header = types['std_msgs/msg/Header'](
                stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec),
                frame_id=frame)
            height, width = image.shape[:2]
            image_msg = types['sensor_msgs/msg/Image'](
                header=header, height=height, width=width, encoding='rgb8', is_bigendian=0,
                step=3 * width, data=np.ascontiguousarray(image, dtype=np.uint8).reshape(-1))
            roi = types['sensor_msgs/msg/RegionOfInterest'](x_offset=0, y_offset=0, height=0,
                                                           width=0, do_rectify=False)
            info_msg = types['sensor_msgs/msg/CameraInfo'](
                header=header, height=camera.height, width=camera.width,
                distortion_model=camera.distortion_model,
                d=np.asarray(camera.D, dtype=np.float64), k=camera.K.reshape(-1),
                r=camera.R.reshape(-1), p=camera.P.reshape(-1), binning_x=0, binning_y=0,
                roi=roi)
            for topic, msgtype, msg in ((info_topic, 'sensor_msgs/msg/CameraInfo', info_msg),
                                        (image_topic, 'sensor_msgs/msg/Image', image_msg)):
                # each connection added just before its first message (the records in
                # the order the bags have always had them)
                if topic not in self.connections:
                    self.connections[topic] = self.writer.add_connection(topic, msgtype,
                                                                         typestore=store)
                self.writer.write(self.connections[topic], stamp_ns,
                                  store.serialize_cdr(msg, msgtype))


def write_session(session: SimulatedSession, output, force: bool = False,
                  progress: Callable[[float], None] | None = None) -> tuple[Path, Path]:
    """Write ``output/`` (the bag) and ``output.truth.npz`` atomically (see
    :func:`write_recording`). Refuses to replace existing ones unless ``force``."""
    output = Path(output)
    return write_recording(session, output, truth_path(output),
                           lambda path: write_truth(path, session.truth), force, progress)


def write_recording(session: PoseRecording, output, sidecar: Path,
                    write_sidecar: Callable[[Path], Path], force: bool = False,
                    progress: Callable[[float], None] | None = None) -> tuple[Path, Path]:
    """Write the bag ``output/`` and its truth ``sidecar`` (``write_sidecar(path)`` writes it
    and returns the path) atomically: both are written in a temporary folder beside them
    and renamed into place (the sidecar first, then the bag), so an interrupted run leaves
    the old pair or the new one, never half of a bag. Refuses to replace existing ones
    unless ``force``."""
    import shutil
    import tempfile
    output = Path(output)
    existing = [p for p in (output, sidecar) if p.exists() or p.is_symlink()]
    if existing and not force:
        raise FileExistsError(f'{", ".join(map(str, existing))} exists already (use --force to replace)')
    output.parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=f'.{output.name}.', dir=output.parent))
    try:
        bag_tmp = write_bag(session, scratch / output.name, progress)
        truth_tmp = write_sidecar(scratch / sidecar.name)
        for target in existing:
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            else:
                target.unlink()
        truth_tmp.replace(sidecar)
        bag_tmp.replace(output)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return output, sidecar
