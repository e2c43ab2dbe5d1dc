"""How good a session's stereo shot is against the simulator's truth (numpy and the map
metrics' KD-tree; no ROS).

The truth file of a session with a stereo pair (``inhand_common.ground_truth``, the stereo
keys) holds the true depth of every pixel of the rectified left image, which pixels see the
object, the focal length and baseline, and the left (rectified) camera's pose in the
tracker frame. It does not hold the principal point: that is in the bag's left
``camera_info`` (its ``P``: the rectified camera the true depth is given in), so
:func:`visible_samples` takes it and :func:`shot_scores` reads it from the shot.

Definitions
-----------
* **Disparity density and bad-2** (:func:`disparity_scores`): on the object's pixels
  (``object_mask``), density = fraction with a disparity (``valid``: at or above the
  matcher's ``min_disparity``), bad-2 = fraction of those with ``|d - d_true| > 2`` px,
  ``d_true = focal * baseline / depth`` (``StereoTruth.disparity``); the same over the
  whole image beside it. ``test/benchmarks/bench_stereo_bags.py`` prints these for the
  disparity settings config/stereo.yaml was chosen among.
* **Stereo points to the surface** (:func:`stereo_point_scores`): each point's distance to
  the nearest true surface sample (an overestimate by at most about half the sample
  spacing, ``sample_spacing_mm``), as median and 95th percentile in mm, and the fraction
  within 5 mm. :func:`shot_scores` scores the points ``stereo/points`` carries (every
  matched pixel, one in ``point_step``: object, table and backdrop, so their fraction
  within 5 mm is about the object's share of them) and the points of the pixels the truth
  marks as object (:func:`object_pixel_points`: every such pixel with a depth). Beyond
  2 cm the distance is to every 16th sample (:func:`surface_distances`): exact
  nearest-sample distances of the backdrop's points took 3 s of KD-tree search, this way
  0.2 s, at most 0.5 mm more on the bundled bags' points (3.3 mm at worst: the
  subsample's covering radius on the cat).
* **Visible surface samples** (:func:`visible_samples`): a true surface sample is seen by
  the left camera when it is in front of it, projects inside the image (ROS's pixel
  convention: integers at pixel centres; the nearest pixel) and the true depth there is
  within ``tolerance`` (one map cell) of the sample's own depth. A sample on the far side
  or behind another part lies a whole thickness behind the depth its pixel sees. On the
  rim, seen edge-on, a sample whose nearest pixel centre just misses the object sees the
  backdrop or the table there and counts as not seen (about 4 % of the cat's samples, all
  one pixel off the object mask); the map's seen cells
  (:func:`inhand_tools.map_quality.seen_cells`: any visible sample in the cell) barely
  depend on it: counting those samples as seen adds 9 and 10 to the 376 and 383 seen
  cells of the bundled cats (coverage 0.646 and 0.614 become 0.631 and 0.598).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from inhand_common.ground_truth import GroundTruth, StereoTruth, pose_at
from inhand_common.rotations import quaternion_to_matrix
from inhand_tools.bag_stereo_shot import BagShot
from inhand_tools.map_quality import SurfaceTruth

__all__ = ['DISPARITY_SCORE_KEYS', 'STEREO_LABELS', 'STEREO_POINT_KEYS', 'disparity_scores',
           'object_pixel_points', 'principal_point', 'samples_in_camera', 'shot_problem',
           'shot_scores', 'stereo_point_scores', 'stereo_table', 'stereo_truth_problem',
           'surface_distances', 'visible_samples']

_MM = 1000.0

DISPARITY_SCORE_KEYS = ('object_pixels', 'object_density', 'object_bad2', 'image_density',
                        'image_bad2', 'bad_disparity_px')
STEREO_POINT_KEYS = ('points', 'median_mm', 'p95_mm', 'within_5mm')
EXACT_WITHIN = 0.02     # m: nearest-sample distances exact up to this
FAR_STEP = 16           # beyond it, to every FAR_STEP-th sample


# ------------------------------------------------------------------ the definitions

def _mean(mask: np.ndarray) -> float:
    return float(np.mean(mask)) if mask.size else math.nan


def disparity_scores(disparity, valid, truth_disparity, object_mask,
                     bad_disparity: float = 2.0) -> dict:
    """Density and bad-``bad_disparity`` of a disparity image against the true one, on the
    object's pixels and on the whole image (module doc). All arrays (H, W); NaN where a
    fraction has nothing to count."""
    disparity = np.asarray(disparity, dtype=np.float32)
    valid = np.asarray(valid, dtype=bool)
    truth_disparity = np.asarray(truth_disparity, dtype=np.float32)
    on = np.asarray(object_mask, dtype=bool)
    if not disparity.shape == valid.shape == truth_disparity.shape == on.shape:
        raise ValueError(f'disparity {disparity.shape}, valid {valid.shape}, true disparity '
                         f'{truth_disparity.shape} and object mask {on.shape} must be the '
                         'same image size')
    with np.errstate(invalid='ignore'):
        bad = np.abs(disparity - truth_disparity) > bad_disparity
    return {
        'object_pixels': int(np.count_nonzero(on)),
        'object_density': _mean(valid[on]),
        'object_bad2': _mean(bad[on & valid]),
        'image_density': _mean(valid),
        'image_bad2': _mean(bad[valid]),
        'bad_disparity_px': float(bad_disparity),
    }


def stereo_point_scores(distances, within: float = 0.005) -> dict:
    """Median and 95th percentile (mm) of points' distances (m) to the true surface, and the
    fraction within ``within`` (m)."""
    distances = np.asarray(distances, dtype=float).reshape(-1)
    count = len(distances)
    return {
        'points': int(count),
        'median_mm': float(np.median(distances)) * _MM if count else math.nan,
        'p95_mm': float(np.percentile(distances, 95)) * _MM if count else math.nan,
        'within_5mm': float(np.mean(distances <= within)) if count else math.nan,
    }


def surface_distances(surface: SurfaceTruth, points) -> np.ndarray:
    """Distance (m) of each point to the nearest true surface sample: exact within
    :data:`EXACT_WITHIN`, beyond it to the nearest of every :data:`FAR_STEP`-th sample
    (module doc)."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(points) == 0:
        return np.empty(0)
    distances: np.ndarray = surface.tree.query(points, k=1, distance_upper_bound=EXACT_WITHIN,
                                               workers=-1)[0]
    far = ~np.isfinite(distances)
    if far.any():
        coarse = cKDTree(surface.points[::FAR_STEP])
        distances[far] = np.maximum(coarse.query(points[far], k=1, workers=-1)[0],
                                    EXACT_WITHIN)
    return distances


def object_pixel_points(pixel_points, object_mask) -> np.ndarray:
    """The measured points (M, 3) of the pixels the truth marks as object that have a depth:
    ``pixel_points`` (H * W, 3) row-major, NaN where there is none (what
    ``PlacedShot.pixel_points_in_map`` gives)."""
    pixel_points = np.asarray(pixel_points, dtype=float).reshape(-1, 3)
    mask = np.asarray(object_mask, dtype=bool).reshape(-1)
    if len(mask) != len(pixel_points):
        raise ValueError(f'{len(pixel_points)} pixel points but an object mask of '
                         f'{len(mask)} pixels')
    chosen = pixel_points[mask]
    return chosen[np.all(np.isfinite(chosen), axis=1)]


def samples_in_camera(truth: GroundTruth) -> np.ndarray:
    """The truth's surface samples (N, 3) in the left (rectified) camera frame at the stereo
    pair's stamp: z along the optical axis, x right, y down.

    The samples are in ``truth.frame``: from the object frame they go to the tracker frame
    by the object's true pose at the pair's stamp; samples in the tracker frame (moved by
    the first pose, :func:`~inhand_common.ground_truth.in_frame`) are first brought back to
    the object frame."""
    stereo = _stereo(truth)
    points = np.asarray(truth.surface_points, dtype=float)
    if truth.frame == 'tracker':
        first_p, first_q = pose_at(truth, truth.object_times[:1])
        points = (points - first_p[0]) @ quaternion_to_matrix(first_q[0])
    elif truth.frame != 'object':
        raise ValueError(f'truth in an unknown frame {truth.frame!r}')
    shot_p, shot_q = pose_at(truth, [stereo.time])
    tracker = points @ quaternion_to_matrix(shot_q[0]).T + shot_p[0]
    pose = np.asarray(stereo.camera_pose, dtype=float)
    return (tracker - pose[:3]) @ quaternion_to_matrix(pose[3:])


def visible_samples(truth: GroundTruth, principal_point, tolerance: float) -> np.ndarray:
    """(N,) bool: the true surface samples the left camera saw (module doc), in the order of
    ``truth.surface_points``. ``principal_point`` (cx, cy) px of the rectified left image
    (the bag's left camera_info ``P``); ``tolerance`` (m): about one map cell."""
    stereo = _stereo(truth)
    cx, cy = (float(v) for v in principal_point)
    camera = samples_in_camera(truth)
    height, width = stereo.depth.shape
    z = camera[:, 2]
    in_front = z > 1e-3
    safe = np.where(in_front, z, 1.0)
    column = np.floor(stereo.focal * camera[:, 0] / safe + cx + 0.5)
    row = np.floor(stereo.focal * camera[:, 1] / safe + cy + 0.5)
    inside = in_front & (column >= 0) & (column < width) & (row >= 0) & (row < height)
    flat = (np.clip(row, 0, height - 1) * width + np.clip(column, 0, width - 1)).astype(np.intp)
    seen_depth = stereo.depth.reshape(-1)[flat].astype(float)    # inf: nothing hit
    with np.errstate(invalid='ignore'):
        visible: np.ndarray = inside & (np.abs(seen_depth - z) <= tolerance)
    return visible


# ------------------------------------------------------------------ a bag's shot

def stereo_truth_problem(truth: GroundTruth) -> str | None:
    """Why ``truth`` cannot judge a stereo shot or the map's colours, or None."""
    if truth.stereo is None or truth.surface_colours is None:
        where = f'{truth.path} has' if truth.path else 'the truth has'
        return f'{where} no stereo keys (a session simulated without a stereo pair)'
    return None


def _stereo(truth: GroundTruth) -> StereoTruth:
    problem = stereo_truth_problem(truth)
    if problem or truth.stereo is None:
        raise ValueError(problem)
    return truth.stereo


def principal_point(shot: BagShot) -> tuple[float, float]:
    """(cx, cy) px of the shot's rectified left image (its camera_info ``P``)."""
    P = shot.placed.shot.left_camera.P
    return float(P[0, 2]), float(P[1, 2])


def shot_problem(shot: BagShot, truth: GroundTruth) -> str | None:
    """Why the bag's shot cannot be compared with this truth, or None: no stereo truth, or
    a shot that is not the truth's (another stamp, image size or focal length)."""
    problem = stereo_truth_problem(truth)
    if problem or truth.stereo is None:
        return problem
    stereo = truth.stereo
    image = shot.placed.shot.depth.shape
    P = shot.placed.shot.left_camera.P
    if image != stereo.depth.shape:
        return (f"the bag's stereo image is {image[1]}x{image[0]}, the truth's "
                f'{stereo.depth.shape[1]}x{stereo.depth.shape[0]}')
    if abs(shot.stamp - stereo.time) > 1e-3:
        return (f"the bag's first usable stereo pair (at {shot.stamp:.3f} s) is not the "
                f"truth's (at {stereo.time:.3f} s)")
    if not math.isclose(float(P[0, 0]), stereo.focal, rel_tol=1e-6) or \
            not math.isclose(float(P[1, 1]), stereo.focal, rel_tol=1e-6):
        return (f"the bag's rectified focal length ({P[0, 0]:g}, {P[1, 1]:g} px) is not the "
                f"truth's ({stereo.focal:g} px)")
    return None


def shot_scores(shot: BagShot, truth: GroundTruth, surface: SurfaceTruth,
                within: float = 0.005) -> dict:
    """The bag's shot against ``truth`` (in the map's frame; ``surface`` built from it):
    ``{'disparity': disparity_scores, 'points': stereo_point_scores of stereo/points,
    'object_points': those of the object's pixels, 'principal_point': [cx, cy]}``.
    ValueError with :func:`shot_problem`'s reason when they cannot be compared."""
    problem = shot_problem(shot, truth)
    if problem or truth.stereo is None:
        raise ValueError(problem)
    stereo = truth.stereo
    result = shot.placed.shot.disparity
    points, _ = shot.points()
    on_object = object_pixel_points(shot.placed.pixel_points_in_map(shot.config.camera_pose),
                                    stereo.object_mask)
    return {
        'disparity': disparity_scores(result.disparity, result.valid, stereo.disparity,
                                      stereo.object_mask),
        'points': stereo_point_scores(surface_distances(surface, points), within),
        'object_points': stereo_point_scores(surface_distances(surface, on_object), within),
        'principal_point': list(principal_point(shot)),
    }


# ------------------------------------------------------------------ for people

# (section, key) -> label and format of the rows of :func:`stereo_table`.
STEREO_LABELS = {
    ('disparity', 'object_pixels'): ('object pixels (truth mask)', '{:d}'),
    ('disparity', 'object_density'): ('disparity density on the object', '{:.3f}'),
    ('disparity', 'object_bad2'): ('  bad-2 (|d - d_true| > 2 px) on the object', '{:.4f}'),
    ('disparity', 'image_density'): ('disparity density, whole image', '{:.3f}'),
    ('disparity', 'image_bad2'): ('  bad-2, whole image', '{:.4f}'),
    ('object_points', 'points'): ('points of the object pixels', '{:d}'),
    ('object_points', 'median_mm'): ('  -> surface, median (mm)', '{:.2f}'),
    ('object_points', 'p95_mm'): ('  -> surface, 95th percentile (mm)', '{:.2f}'),
    ('object_points', 'within_5mm'): ('  within 5 mm of the surface', '{:.3f}'),
    ('points', 'points'): ('stereo/points (object, table, backdrop)', '{:d}'),
    ('points', 'median_mm'): ('  -> surface, median (mm)', '{:.1f}'),
    ('points', 'p95_mm'): ('  -> surface, 95th percentile (mm)', '{:.1f}'),
    ('points', 'within_5mm'): ('  within 5 mm of the surface', '{:.3f}'),
}


def _format(value, label_format: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return 'n/a'
    return label_format.format(int(value) if label_format.endswith('d}') else value)


def stereo_table(scores: dict | None, note: str | None, width: int) -> list[str]:
    """The lines of the stereo section of the metrics table: :func:`shot_scores`' results,
    or one line saying why there are none (``note``; no lines if there is no note
    either). ``width``: the label column's width."""
    if scores is None:
        return [f'stereo shot: n/a ({note})'] if note else []
    lines = [f'{"stereo shot (first usable pair)":<{width}}{"shot":>12}', '-' * (width + 12)]
    for (section, key), (label, label_format) in STEREO_LABELS.items():
        lines.append(f'{label:<{width}}{_format(scores[section][key], label_format):>12}')
    return lines
