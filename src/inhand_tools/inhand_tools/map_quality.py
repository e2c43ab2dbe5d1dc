"""How good a map is against the true surface (numpy and scipy's KD-tree only; no ROS).

:func:`map_metrics` scores the cells above a threshold, :func:`point_metrics` the
registered raw points and :func:`colour_metrics` the colours the stereo camera gave the
cells; :func:`evaluate` does them for the cells of a map
(:class:`~inhand_tools.map_cells.MapCells`) at several thresholds, :func:`frame_check` warns
when the map and the truth seem to be in different frames, :func:`find_truth` finds the
truth file of a session and :func:`metrics_table` lays the results out for people.

Inputs: cell centres of a map with their occupancy probabilities, the map's lattice (cell
edge ``h`` and the corner of any cell), and the ground truth: surface samples (uniform by
area), true contact points and true stray fingertip positions, all in the map's frame.

Definitions (metres inside, millimetres in the reported ``*_mm`` values)
-------------------------------------------------------------------------
* **Occupied cells** ``A``: cells with probability ``> threshold`` (default 0.8).
* **Explored surface** ``S_e``: the surface samples within ``explored_radius`` of a true
  contact. Default 5 mm (one cell of the default grid): with the one-cell tolerance below,
  a map that occupies exactly the cells of the true contacts recalls every explored cell
  (two points at most ``h`` apart lie in cells at most one index apart on every axis), so
  a perfect map of what was touched scores recall 1, and surface nobody came near is not
  held against the map.
* **Cells of a point set**: ``floor((p - origin) / h)`` per axis
  (:func:`~inhand_tools.map_cells.cell_indices`). ``G_e`` = cells holding at
  least one explored sample, ``G`` = cells holding any surface sample.
* **Voxel IoU** = ``|A & G_e| / |A | G_e|`` (exact cell sets; no tolerance).
* **Cell precision** = fraction of ``A`` within ``tolerance_cells`` (default 1: the cell itself
  or one of its 26 neighbours, Chebyshev distance in cell indices) of a cell of ``G``: the
  whole true surface, since an occupied cell on surface that was not explored is still
  right. **Cell recall** = fraction of ``G_e`` within ``tolerance_cells`` of a cell of ``A``.
* **Chamfer distance** = ``(mean_{a in A} d(a, S) + mean_{s in S_e} d(s, A)) / 2``: the mean of
  the two directed nearest-neighbour distances, occupied cell centres to the surface
  samples and explored samples to the occupied cell centres.
* **F-score at 5 mm** (``fscore_distance``) = ``2 P R / (P + R)`` with ``P`` = fraction of
  occupied centres within 5 mm of a surface sample and ``R`` = fraction of explored samples
  within 5 mm of an occupied centre (0 when both are 0).
* **Centre-of-mass error** = ``|sum p_a a / sum p_a - mean(S_e)|``: the map's centre of mass
  (occupied cells weighted by probability, as the object-centric frame) against the
  area-weighted centroid of the explored surface (the plain mean, since samples are
  uniform by area).
* **Normal offset** = mean over ``A`` of ``(a - s) . n_s``, ``s`` the nearest sample: > 0 when
  the map sits outside the surface (a fingertip sensor above the contact would do that).
* **Stray cells** = occupied cells that hold (the same cell, no tolerance) a true stray
  point farther than ``stray_surface_distance`` (5 mm) from the surface and that the
  surface does not reach: no surface sample in the cell grown by ``surface_margin`` (1 mm,
  the tracker's noise) on every side. A cell the surface passes through, or grazes within
  the noise of the contacts, is right to be occupied whatever else passed through it (a
  cell whose corner the surface misses by 0.2 mm fills with noisy contacts like its
  neighbours). The simulator's off-surface samples start 6 mm from the surface, so a
  stray's neighbouring cell is often a surface cell. An occupied cell merely next to a
  stray's cell is not a stray cell (the off-surface cells count it if it is more than a
  cell off).
  **Off-surface cells** = occupied cells not within tolerance of ``G`` (``|A|`` minus the
  correct ones), whatever put them there.
* **Recall lost** (:func:`recall_losses`, a touch map saved with its evidence): the explored
  samples farther than 5 mm from every occupied centre, each by the best cell holding a
  true contact within 5 mm of it (the one-touch oracle's cells): none; under one touch
  before the surface layer's rules; under the touches that reach the threshold alone; or
  as many, and the rules took it. It says whether a session touched too little, too fast
  or too thinly, or whether the rules cut what it touched.
* Registered raw points (:func:`point_metrics`): the same distances with the points in place
  of cell centres: precision, recall and F-score at 5 mm, Chamfer, and the median and 95th
  percentile of point-to-surface distances.

Distances to the surface are distances to the nearest sample: they overestimate the true
distance by at most about half the sample spacing (``sample_spacing_mm`` in the results;
about 0.3 mm for 100,000 samples on a 4 cm sphere).

The map's colours (:func:`colour_metrics`)
------------------------------------------
For a map with colours (``MapCells.colours``, ``textured``: what the stereo node's
``occupancy/textured`` gave the occupied cells) and a truth with ``surface_colours`` (the
true colour of each surface sample: the *albedo*, unshaded; the camera sees albedo times
the renderer's shading, ambient 0.35 plus Lambert and highlights, so even a right colour
differs from the truth, mostly darker).

* **Textured fraction** = textured cells / occupied cells ``A``.
* **Seen cells** (needs ``visible``, the surface samples the left camera saw:
  :func:`inhand_tools.stereo_quality.visible_samples`): an occupied cell holding surface
  samples is seen when one of them is visible; a cell holding none (off the surface) when
  its nearest sample is. **Coverage of the seen cells** = textured seen cells / seen cells;
  **textured unseen cells** = textured cells the camera did not see (paint on hidden
  surface: should be about 0). Judging a cell by its nearest sample alone miscounts the
  cells on the edge of the visible surface: their centre's nearest sample may be hidden
  while the cell holds visible surface (13 to 20 "unseen" textured cells on the bundled
  sessions, against 2 or 3 this way).
* **Colour error** of a textured cell = the Euclidean distance in RGB (0-441) between the
  cell's colour and its true colour: the per-channel median of the true colours of the
  surface samples inside the cell, or the nearest sample's colour for a cell holding none
  (:func:`true_cell_colours`). Reported as the median and the 95th percentile over the
  textured cells, and as a reference the median with the same colours shuffled among the
  textured cells (a fixed seed): what a colour that belongs to another cell scores.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from inhand_common.ground_truth import GroundTruth, truth_path
from inhand_tools.map_cells import Lattice, MapCells, cell_indices, is_bag

__all__ = ['COLOUR_SCORE_KEYS', 'MAP_SCORE_KEYS', 'METRIC_LABELS', 'SurfaceTruth',
           'colour_metrics', 'colour_problem', 'evaluate', 'explored_mask', 'find_truth',
           'format_metric', 'frame_check', 'label_width', 'map_metrics', 'metrics_table',
           'one_touch_oracle', 'point_metrics', 'recall_losses', 'seen_cells', 'surface_truth',
           'touch_coverage', 'touch_recall_losses', 'true_cell_colours']

# Cell indices are packed into one int64 per cell: 20 bits per axis, offset to be positive.
_BITS = 20
_OFFSET = 1 << (_BITS - 1)
_NEIGHBOURS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)],
                       dtype=np.int64)
_MM = 1000.0

# The scores of :func:`map_metrics`, in the order of its result (and of the JSON files).
MAP_SCORE_KEYS = (
    'threshold', 'resolution_mm', 'occupied_cells', 'explored_cells', 'surface_cells', 'iou',
    'cell_precision', 'cell_recall', 'cell_fscore', 'chamfer_mm', 'map_to_surface_mm',
    'surface_to_map_mm', 'precision_at_5mm', 'recall_at_5mm', 'fscore_at_5mm',
    'normal_offset_mm', 'com_error_mm', 'com_map', 'com_truth', 'stray_cells',
    'off_surface_cells', 'strays_far_from_surface', 'strays', 'fscore_distance_mm',
    'surface_margin_mm', 'tolerance_cells', 'explored_radius_mm', 'explored_samples',
    'surface_samples', 'contacts', 'sample_spacing_mm')

# The scores of :func:`colour_metrics`, in the order of its result.
COLOUR_SCORE_KEYS = (
    'threshold', 'occupied_cells', 'textured_cells', 'textured_fraction', 'seen_cells',
    'seen_textured_fraction', 'unseen_textured_cells', 'colour_cells',
    'colour_cells_nearest_sample', 'colour_error_median', 'colour_error_p95',
    'colour_error_shuffled_median')


def _keys(indices: np.ndarray) -> np.ndarray:
    shifted = np.clip(indices + _OFFSET, 0, (1 << _BITS) - 1)
    return (shifted[:, 0] << (2 * _BITS)) | (shifted[:, 1] << _BITS) | shifted[:, 2]


def _dilated_keys(indices: np.ndarray, cells: int) -> np.ndarray:
    """Keys of every cell within Chebyshev distance ``cells`` of one of ``indices``."""
    if cells <= 0 or len(indices) == 0:
        return np.unique(_keys(indices))
    offsets = _NEIGHBOURS if cells == 1 else np.array(
        np.meshgrid(*[np.arange(-cells, cells + 1)] * 3, indexing='ij')).reshape(3, -1).T
    unique = np.unique(indices, axis=0)
    return np.unique(_keys((unique[:, None, :] + offsets[None, :, :]).reshape(-1, 3)))


def explored_mask(surface_points, contacts, radius: float) -> np.ndarray:
    """Which surface samples lie within ``radius`` of a contact (all False if none)."""
    surface_points = np.asarray(surface_points, dtype=float).reshape(-1, 3)
    contacts = np.asarray(contacts, dtype=float).reshape(-1, 3)
    if len(contacts) == 0:
        return np.zeros(len(surface_points), dtype=bool)
    distance, _ = cKDTree(contacts).query(surface_points, k=1, distance_upper_bound=radius,
                                          workers=-1)
    return distance <= radius


class SurfaceTruth:
    """Surface samples (and normals), the explored part, and a KD-tree over the samples;
    built once and shared by the map and the point metrics."""

    def __init__(self, surface_points, contacts, surface_normals=None, stray_points=None,
                 explored_radius: float = 0.005):
        self.points = np.ascontiguousarray(surface_points, dtype=float).reshape(-1, 3)
        if len(self.points) == 0:
            raise ValueError('the truth has no surface samples')
        self.normals = (None if surface_normals is None
                        else np.asarray(surface_normals, dtype=float).reshape(-1, 3))
        self.contacts = np.asarray(contacts, dtype=float).reshape(-1, 3)
        self.strays = (np.empty((0, 3)) if stray_points is None
                       else np.asarray(stray_points, dtype=float).reshape(-1, 3))
        self.explored_radius = float(explored_radius)
        self.tree = cKDTree(self.points)
        self.explored = explored_mask(self.points, self.contacts, explored_radius)
        self.explored_points = self.points[self.explored]
        # Typical spacing: nearest-neighbour distance among a subset of the samples.
        subset = self.points[:: max(1, len(self.points) // 2000)]
        gaps, _ = self.tree.query(subset, k=2, workers=-1)
        self.sample_spacing = float(np.median(gaps[:, 1])) if len(self.points) > 1 else 0.0

    def distance(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Distance of each point to the nearest surface sample, and that sample's index."""
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        if len(points) == 0:
            return np.empty(0), np.empty(0, dtype=np.int64)
        return self.tree.query(points, k=1, workers=-1)


def touch_coverage(surface: SurfaceTruth, contact_times, lattice: Lattice,
                   gap: float = 3.0) -> dict:
    """How much of the explored surface the session touched once and twice: what any map
    could know, whatever its model. A cell of ``lattice`` holding true contacts is touched
    once per episode (contacts in it more than ``gap`` seconds apart are two touches: the
    occupancy model's ``visit_gap``); the shares are of the explored surface samples whose
    cell was touched at least once / at least twice. Contacts are the tracker's samples, so
    at a low rate a fast stroke's path between two samples counts nowhere."""
    explored = surface.explored_points
    if len(explored) == 0 or len(surface.contacts) == 0:
        return {'once': 0.0, 'twice': 0.0, 'gap_s': gap}
    keys = _keys(cell_indices(surface.contacts, lattice))
    times = np.asarray(contact_times, dtype=float).reshape(-1)
    order = np.lexsort((times, keys))
    keys, times = keys[order], times[order]
    new_touch = np.ones(len(keys), dtype=bool)
    new_touch[1:] = (keys[1:] != keys[:-1]) | (np.diff(times) > gap)
    touched, touches = np.unique(keys[new_touch], return_counts=True)
    sample_keys = _keys(cell_indices(explored, lattice))
    where = np.minimum(np.searchsorted(touched, sample_keys), len(touched) - 1)
    count = np.where(touched[where] == sample_keys, touches[where], 0)
    return {'once': float(np.mean(count >= 1)), 'twice': float(np.mean(count >= 2)),
            'gap_s': gap}


def _ratio(numerator, denominator) -> float:
    return float(numerator) / float(denominator) if denominator else math.nan


def _fscore(precision: float, recall: float) -> float:
    if math.isnan(precision) or math.isnan(recall):
        return math.nan
    return 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)


def _nearest_distances(targets: np.ndarray, queries: np.ndarray) -> np.ndarray:
    if len(queries) == 0:
        return np.empty(0)
    if len(targets) == 0:
        return np.full(len(queries), math.inf)
    return cKDTree(targets).query(queries, k=1, workers=-1)[0]



@dataclass(frozen=True)
class _Occupied:
    """The occupied cells of a map: centres and probabilities above the threshold, and
    their distinct cell indices with the packed keys of those."""

    centres: np.ndarray
    weights: np.ndarray
    cells: np.ndarray
    keys: np.ndarray


def _occupied(centres, probabilities, lattice: Lattice, threshold: float) -> _Occupied:
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    probabilities = np.asarray(probabilities, dtype=float).reshape(-1)
    if len(centres) != len(probabilities):
        raise ValueError(f'{len(centres)} centres but {len(probabilities)} probabilities')
    keep = probabilities > threshold
    cells = np.unique(cell_indices(centres[keep], lattice), axis=0)
    return _Occupied(centres[keep], probabilities[keep], cells, _keys(cells))


def _cell_scores(occupied: _Occupied, truth: SurfaceTruth, lattice: Lattice,
                 tolerance_cells: int) -> dict:
    """Voxel sets: IoU against the explored cells, cell precision against the whole
    surface and cell recall of the explored cells, within ``tolerance_cells``."""
    explored_cells = np.unique(cell_indices(truth.explored_points, lattice), axis=0)
    explored_keys = _keys(explored_cells)
    surface_cells = cell_indices(truth.points, lattice)
    surface_keys = np.unique(_keys(surface_cells))
    intersection = np.intersect1d(occupied.keys, explored_keys).size
    union = occupied.keys.size + explored_keys.size - intersection
    correct = np.isin(occupied.keys, _dilated_keys(np.unique(surface_cells, axis=0),
                                                   tolerance_cells))
    recalled = np.isin(explored_keys, _dilated_keys(occupied.cells, tolerance_cells))
    precision = _ratio(np.count_nonzero(correct), correct.size)
    recall = _ratio(np.count_nonzero(recalled), recalled.size)
    return {
        'occupied_cells': int(len(occupied.cells)),
        'explored_cells': int(len(explored_cells)),
        'surface_cells': int(surface_keys.size),
        'iou': _ratio(intersection, union),
        'cell_precision': precision,
        'cell_recall': recall,
        'cell_fscore': _fscore(precision, recall),
        'off_surface_cells': int(correct.size - np.count_nonzero(correct)),
    }


def _distance_scores(occupied: np.ndarray, truth: SurfaceTruth,
                     fscore_distance: float) -> dict:
    """Chamfer, the directed mean distances, the F-score at ``fscore_distance`` and the
    mean offset along the surface normal of the occupied centres."""
    explored = truth.explored_points
    to_surface, nearest = truth.distance(occupied)
    to_map = _nearest_distances(occupied, explored)
    precision = _ratio(np.count_nonzero(to_surface <= fscore_distance), len(occupied))
    recall = _ratio(np.count_nonzero(to_map <= fscore_distance), len(explored))
    chamfer = (float(np.mean(to_surface)) + float(np.mean(to_map))) / 2.0 \
        if len(occupied) and len(explored) else math.nan
    offset = math.nan
    if truth.normals is not None and len(occupied):
        offset = float(np.mean(np.einsum('ij,ij->i', occupied - truth.points[nearest],
                                         truth.normals[nearest])))
    return {
        'chamfer_mm': chamfer * _MM,
        'map_to_surface_mm': float(np.mean(to_surface)) * _MM if len(occupied) else math.nan,
        'surface_to_map_mm': float(np.mean(to_map)) * _MM if len(explored) and len(occupied)
        else math.nan,
        'precision_at_5mm': precision,
        'recall_at_5mm': recall,
        'fscore_at_5mm': _fscore(precision, recall),
        'normal_offset_mm': offset * _MM,
    }


def _centre_of_mass_scores(occupied: _Occupied, explored: np.ndarray) -> dict:
    """The map's centre of mass (weighted by probability) against the explored surface's
    centroid."""
    com_error, com_map, com_truth = math.nan, None, None
    if len(explored):
        com_truth = explored.mean(axis=0)
    if len(occupied.centres):
        com_map = occupied.weights @ occupied.centres / occupied.weights.sum()
    if com_map is not None and com_truth is not None:
        com_error = float(np.linalg.norm(com_map - com_truth))
    return {
        'com_error_mm': com_error * _MM,
        'com_map': None if com_map is None else [float(v) for v in com_map],
        'com_truth': None if com_truth is None else [float(v) for v in com_truth],
    }


def _stray_scores(occupied: _Occupied, truth: SurfaceTruth, lattice: Lattice,
                  stray_surface_distance: float, surface_margin: float) -> dict:
    """True off-surface fingertip positions, and the occupied cells that hold one but that
    the surface does not reach (a cell holding surface is right to be occupied)."""
    far_strays = np.empty((0, 3))
    if len(truth.strays):
        far_strays = truth.strays[truth.distance(truth.strays)[0] > stray_surface_distance]
    stray_cells = 0
    if len(far_strays) and len(occupied.centres):
        holding = occupied.cells[np.isin(occupied.keys,
                                         _keys(cell_indices(far_strays, lattice)))]
        centres_holding = np.asarray(lattice.origin) + (holding + 0.5) * lattice.resolution
        # Chebyshev distance to the nearest surface sample: inside the grown cell or not.
        reach = truth.tree.query(centres_holding, k=1, p=np.inf)[0] if len(holding) \
            else np.empty(0)
        stray_cells = int(np.count_nonzero(reach > lattice.resolution / 2 + surface_margin))
    return {
        'stray_cells': stray_cells,
        'strays_far_from_surface': int(len(far_strays)),
        'strays': int(len(truth.strays)),
    }


def map_metrics(centres, probabilities, lattice: Lattice, truth: SurfaceTruth,
                threshold: float = 0.8, tolerance_cells: int = 1,
                fscore_distance: float = 0.005,
                stray_surface_distance: float = 0.005,
                surface_margin: float = 0.001) -> dict:
    """The metrics of the module docstring for the cells above ``threshold``.

    ``centres`` (n, 3) and ``probabilities`` (n,) may hold every touched cell; only those
    with probability > threshold count. Returns a flat dict (JSON-ready, NaN where a
    metric is undefined, e.g. precision of an empty map), keys in :data:`MAP_SCORE_KEYS`
    order.
    """
    occupied = _occupied(centres, probabilities, lattice, threshold)
    scores = {
        'threshold': float(threshold),
        'resolution_mm': lattice.resolution * _MM,
        **_cell_scores(occupied, truth, lattice, tolerance_cells),
        **_distance_scores(occupied.centres, truth, fscore_distance),
        **_centre_of_mass_scores(occupied, truth.explored_points),
        **_stray_scores(occupied, truth, lattice, stray_surface_distance, surface_margin),
        'fscore_distance_mm': fscore_distance * _MM,
        'surface_margin_mm': surface_margin * _MM,
        'tolerance_cells': int(tolerance_cells),
        'explored_radius_mm': truth.explored_radius * _MM,
        'explored_samples': int(len(truth.explored_points)),
        'surface_samples': int(len(truth.points)),
        'contacts': int(len(truth.contacts)),
        'sample_spacing_mm': truth.sample_spacing * _MM,
    }
    return {key: scores[key] for key in MAP_SCORE_KEYS}


def _contact_cells(truth: SurfaceTruth, lattice: Lattice) -> tuple[np.ndarray, np.ndarray]:
    """The distinct cells holding a true contact: their indices (K, 3) and centres (K, 3)."""
    cells = np.unique(cell_indices(truth.contacts, lattice), axis=0)
    return cells, np.asarray(lattice.origin) + (cells + 0.5) * lattice.resolution


def one_touch_oracle(truth: SurfaceTruth, lattice: Lattice, threshold: float = 0.8) -> dict:
    """The map that marks exactly the cells holding a true contact, scored by
    :func:`map_metrics` as a map is: what a session's contacts allow at best when one touch
    is enough (precision about 1, so its F is about 2r / (1 + r), r its recall). A session
    that touched too little of its surface is judged against it."""
    _, centres = _contact_cells(truth, lattice)
    return map_metrics(centres, np.ones(len(centres)), lattice, truth, threshold)


def recall_losses(centres, probabilities, lattice: Lattice, truth: SurfaceTruth,
                  touch_evidence: np.ndarray, touches_needed: float, threshold: float = 0.8,
                  fscore_distance: float = 0.005) -> dict:
    """Where the explored surface a touch map misses was lost: shares of the explored
    samples (``explored_samples`` of them). ``missed``: farther than ``fscore_distance``
    from every cell above ``threshold`` (what recall counts). Each missed sample by the best
    of the cells holding a true contact within that distance of it (the cells the one-touch
    oracle marks), by its touches before the surface layer's rules (``touch_evidence``, the
    path model's (n, n, n) evidence on ``lattice``'s cells, as saved in the NPZ):
    ``untouched``, no such cell (the oracle misses it too); ``under_one_touch``, less than
    one pass at stroke speed (a fast stretch, a corner clipped); ``unconfirmed``, at least
    one but under ``touches_needed`` (what reaches ``threshold`` on its own; the rules'
    sheet gain did not make it up); ``taken_by_rules``, as many or more, and the rules took
    the cell under ``threshold`` (the layer above a surface, a thin wall's other side, a
    cell alone)."""
    evidence = np.asarray(touch_evidence, dtype=float)
    if evidence.ndim != 3:
        raise ValueError(f'touch_evidence must be a 3-D grid, not {evidence.shape}')
    explored = truth.explored_points
    occupied = _occupied(centres, probabilities, lattice, threshold)
    missed = explored[_nearest_distances(occupied.centres, explored) > fscore_distance]
    keys, contact_cells = _contact_cells(truth, lattice)
    inside = np.all((keys >= 0) & (keys < np.array(evidence.shape)), axis=1)
    touches = np.zeros(len(keys))
    touches[inside] = evidence[tuple(keys[inside].T)]
    best = np.full(len(missed), -math.inf)
    if len(keys) and len(missed):
        # the cell centres within the distance of a point lie in a ball one cell wider
        k = min(len(keys), math.ceil(4 / 3 * math.pi
                                     * (fscore_distance / lattice.resolution + 1) ** 3))
        _, index = cKDTree(contact_cells).query(missed, k=k,
                                                distance_upper_bound=fscore_distance)
        best = np.append(touches, -math.inf)[np.asarray(index).reshape(len(missed), k)].max(axis=1)
    total = max(len(explored), 1)
    touched = np.isfinite(best)
    return {'explored_samples': len(explored), 'missed': len(missed) / total,
            'untouched': int(np.count_nonzero(~touched)) / total,
            'under_one_touch': int(np.count_nonzero(touched & (best < 1.0))) / total,
            'unconfirmed': int(np.count_nonzero((best >= 1.0) & (best < touches_needed))) / total,
            'taken_by_rules': int(np.count_nonzero(best >= touches_needed)) / total}


def touch_recall_losses(path, cells: MapCells, surface: SurfaceTruth,
                        threshold: float = 0.8) -> dict | None:
    """:func:`recall_losses` of the touch map saved at ``path`` (an NPZ, its ``cells`` as
    :func:`~inhand_tools.map_cells.load_map` read them), with the touches that reach
    ``threshold`` on their own from the map's model (its ``p_z_given_not_occupied`` and
    prior), and those two numbers; None for a map without the path model's evidence or a
    truth without contacts."""
    if cells.kind != 'npz' or len(surface.contacts) == 0:
        return None
    with np.load(path, allow_pickle=False) as data:
        if 'touch_evidence' not in data.files:
            return None
        evidence = data['touch_evidence']
    # imported here, as map_cells imports the map reader: only when a map needs it
    from inhand_mapping.occupancy import logit
    c = float(cells.metadata['p_z_given_not_occupied'])
    needed = float(logit(threshold) - logit(float(cells.metadata['prior']))) / -math.log(c)
    losses = recall_losses(cells.centres, cells.probabilities, cells.lattice, surface,
                           evidence, needed, threshold)
    return {**losses, 'threshold': threshold, 'touches_needed': needed}


def point_metrics(points, truth: SurfaceTruth, fscore_distance: float = 0.005) -> dict:
    """Registered raw points against the surface: the distance metrics of the module doc."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    points = points[np.all(np.isfinite(points), axis=1)]
    explored = truth.explored_points
    to_surface, _ = truth.distance(points)
    to_points = _nearest_distances(points, explored)
    precision = _ratio(np.count_nonzero(to_surface <= fscore_distance), len(points))
    recall = _ratio(np.count_nonzero(to_points <= fscore_distance), len(explored))
    mm = 1000.0
    has_both = len(points) and len(explored)
    return {
        'points': int(len(points)),
        'precision_at_5mm': precision,
        'recall_at_5mm': recall,
        'fscore_at_5mm': _fscore(precision, recall),
        'chamfer_mm': (float(np.mean(to_surface)) + float(np.mean(to_points))) / 2 * mm
        if has_both else math.nan,
        'points_to_surface_mm': float(np.mean(to_surface)) * mm if len(points) else math.nan,
        'median_to_surface_mm': float(np.median(to_surface)) * mm if len(points) else math.nan,
        'p95_to_surface_mm': float(np.percentile(to_surface, 95)) * mm if len(points)
        else math.nan,
        'surface_to_points_mm': float(np.mean(to_points)) * mm if has_both else math.nan,
    }



# ------------------------------------------------------------------ the map's colours

def true_cell_colours(centres, lattice: Lattice, truth: SurfaceTruth, surface_colours
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The true colour of each cell (n, 3) float: the per-channel median of the true colours
    of the surface samples inside the cell (the mean of the two middle values for an even
    count), or the nearest sample's colour for a cell holding none; and which cells held
    samples (n,) bool."""
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    surface_colours = np.asarray(surface_colours).reshape(-1, 3)
    if len(surface_colours) != len(truth.points):
        raise ValueError(f'{len(surface_colours)} surface colours for {len(truth.points)} '
                         'surface samples')
    cell_keys = _keys(cell_indices(centres, lattice))
    sample_keys = _keys(cell_indices(truth.points, lattice))
    inside = np.isin(sample_keys, cell_keys)
    keys, values = sample_keys[inside], surface_colours[inside].astype(float)
    result = np.empty((len(centres), 3))
    held = np.zeros(len(centres), dtype=bool)
    if len(keys):
        groups, starts, counts = np.unique(np.sort(keys), return_index=True,
                                           return_counts=True)
        low, high = starts + (counts - 1) // 2, starts + counts // 2
        medians = np.empty((len(groups), 3))
        for channel in range(3):    # sorted by cell, then by this channel's value
            ranked = values[np.lexsort((values[:, channel], keys)), channel]
            medians[:, channel] = (ranked[low] + ranked[high]) / 2.0
        where = np.minimum(np.searchsorted(groups, cell_keys), len(groups) - 1)
        held = groups[where] == cell_keys
        result[held] = medians[where[held]]
    if not held.all():
        _, nearest = truth.distance(centres[~held])
        result[~held] = surface_colours[nearest]
    return result, held


def seen_cells(centres, lattice: Lattice, truth: SurfaceTruth, visible) -> np.ndarray:
    """(n,) bool: the cells the camera saw, by the truth: a cell holding surface samples when
    one of them is visible, any other cell when its nearest sample is (``visible``: (N,)
    bool per surface sample, :func:`inhand_tools.stereo_quality.visible_samples`)."""
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    visible = np.asarray(visible, dtype=bool).reshape(-1)
    if len(visible) != len(truth.points):
        raise ValueError(f'{len(visible)} visibility flags for {len(truth.points)} surface '
                         'samples')
    if len(centres) == 0:
        return np.zeros(0, dtype=bool)
    cell_keys = _keys(cell_indices(centres, lattice))
    sample_keys = _keys(cell_indices(truth.points, lattice))
    holding = np.isin(cell_keys, sample_keys)
    seen = np.isin(cell_keys, sample_keys[visible])
    if not holding.all():
        seen[~holding] = visible[truth.distance(centres[~holding])[1]]
    return seen


def colour_metrics(centres, probabilities, lattice: Lattice, colours, textured,
                   truth: SurfaceTruth, surface_colours, visible=None,
                   threshold: float = 0.8, shuffle_seed: int = 0) -> dict:
    """The colours of the occupied cells against the truth (module doc, "The map's
    colours"). ``colours`` (n, 3) and ``textured`` (n,) per map cell, as
    :class:`~inhand_tools.map_cells.MapCells` holds them; ``surface_colours`` (N, 3) the
    truth's colour per surface sample; ``visible`` (N,) bool the samples the camera saw, or
    None (the scores of the seen cells are then None and NaN)."""
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    keep = np.asarray(probabilities, dtype=float).reshape(-1) > threshold
    colours = np.asarray(colours).reshape(-1, 3)
    textured = np.asarray(textured, dtype=bool).reshape(-1)
    if not len(centres) == len(keep) == len(colours) == len(textured):
        raise ValueError(f'{len(centres)} centres, {len(keep)} probabilities, '
                         f'{len(colours)} colours and {len(textured)} textured flags')
    occupied, painted = centres[keep], textured[keep]
    scores: dict = {'threshold': float(threshold), 'occupied_cells': int(len(occupied)),
                    'textured_cells': int(np.count_nonzero(painted)),
                    'textured_fraction': _ratio(np.count_nonzero(painted), len(occupied)),
                    'seen_cells': None, 'seen_textured_fraction': math.nan,
                    'unseen_textured_cells': None}
    if visible is not None:
        seen = seen_cells(occupied, lattice, truth, visible)
        scores.update(seen_cells=int(np.count_nonzero(seen)),
                      seen_textured_fraction=_ratio(np.count_nonzero(seen & painted),
                                                    np.count_nonzero(seen)),
                      unseen_textured_cells=int(np.count_nonzero(painted & ~seen)))
    mapped = colours[keep][painted].astype(float)
    true, held = true_cell_colours(occupied[painted], lattice, truth, surface_colours)
    error = np.linalg.norm(mapped - true, axis=1)
    shuffled = mapped[np.random.default_rng(shuffle_seed).permutation(len(mapped))]
    shuffled_error = np.linalg.norm(shuffled - true, axis=1)
    count = len(error)
    scores.update(
        colour_cells=int(count),
        colour_cells_nearest_sample=int(np.count_nonzero(~held)),
        colour_error_median=float(np.median(error)) if count else math.nan,
        colour_error_p95=float(np.percentile(error, 95)) if count else math.nan,
        colour_error_shuffled_median=float(np.median(shuffled_error)) if count else math.nan)
    return {key: scores[key] for key in COLOUR_SCORE_KEYS}


# Row labels of the printed table: key -> (label, format).
METRIC_LABELS = {
    'occupied_cells': ('occupied cells (> threshold)', '{:d}'),
    'explored_cells': ('explored surface cells (truth)', '{:d}'),
    'iou': ('voxel IoU (occupied vs explored cells)', '{:.3f}'),
    'cell_precision': ('cell precision (within 1 cell of surface)', '{:.3f}'),
    'cell_recall': ('cell recall (explored cells within 1 cell)', '{:.3f}'),
    'cell_fscore': ('cell F-score', '{:.3f}'),
    'precision_at_5mm': ('precision @ 5 mm', '{:.3f}'),
    'recall_at_5mm': ('recall @ 5 mm', '{:.3f}'),
    'fscore_at_5mm': ('F-score @ 5 mm', '{:.3f}'),
    'chamfer_mm': ('Chamfer distance (mm)', '{:.2f}'),
    'map_to_surface_mm': ('  map -> surface, mean (mm)', '{:.2f}'),
    'surface_to_map_mm': ('  explored surface -> map, mean (mm)', '{:.2f}'),
    'normal_offset_mm': ('mean offset along the normal (mm, + outside)', '{:+.2f}'),
    'com_error_mm': ('centre-of-mass error (mm)', '{:.2f}'),
    'stray_cells': ('occupied cells holding true strays (> 5 mm off), not surface', '{:d}'),
    'off_surface_cells': ('occupied cells off the surface (> 1 cell)', '{:d}'),
    'strays_far_from_surface': ('true stray points > 5 mm off the surface', '{:d}'),
    'points': ('registered points', '{:d}'),
    'points_to_surface_mm': ('  points -> surface, mean (mm)', '{:.2f}'),
    'median_to_surface_mm': ('  points -> surface, median (mm)', '{:.2f}'),
    'p95_to_surface_mm': ('  points -> surface, 95th percentile (mm)', '{:.2f}'),
    'surface_to_points_mm': ('  explored surface -> points, mean (mm)', '{:.2f}'),
    'textured_cells': ('textured cells (coloured from the camera)', '{:d}'),
    'textured_fraction': ('  fraction of the occupied cells', '{:.3f}'),
    'seen_cells': ('occupied cells the camera saw (truth)', '{:d}'),
    'seen_textured_fraction': ('  fraction of them textured', '{:.3f}'),
    'unseen_textured_cells': ('textured cells the camera did not see', '{:d}'),
    'colour_error_median': ('colour error, median (RGB distance 0-441)', '{:.1f}'),
    'colour_error_p95': ('  95th percentile', '{:.1f}'),
    'colour_error_shuffled_median': ('  median, colours shuffled among the cells', '{:.1f}'),
}


# ------------------------------------------------------------------ a map against its truth

def find_truth(truth: str | None, bag: Path | None, map_path: Path) -> Path:
    """The truth file of a session: ``truth`` if given, else the ``BAG.truth.npz`` sidecar
    of ``bag`` or of the map (when the map is a bag). ValueError if there is none."""
    if truth:
        return Path(truth)
    for candidate in ([bag] if bag else []) + ([map_path] if is_bag(map_path) else []):
        sidecar = truth_path(candidate)
        if sidecar.exists():
            return sidecar
    raise ValueError('no ground truth: give --truth TRUTH.npz (or --bag BAG with its '
                     'BAG.truth.npz beside it)')


def surface_truth(truth: GroundTruth, explored_radius: float = 0.005) -> SurfaceTruth:
    """The :class:`SurfaceTruth` of a truth file (in the frame it is in)."""
    return SurfaceTruth(truth.surface_points, truth.contacts, truth.surface_normals,
                        truth.stray_points, explored_radius)


def colour_problem(cells: MapCells, truth: GroundTruth) -> str | None:
    """Why the map's colours cannot be judged against ``truth``, or None."""
    if not cells.has_colours:
        return (f'the {cells.kind} map carries no colours; build_map colours the map of a '
                'bag with a stereo pair when given --config config/stereo.yaml')
    if truth.surface_colours is None:
        where = f'{truth.path} has' if truth.path else 'the truth has'
        return f'{where} no surface colours (a session simulated without a stereo pair)'
    return None


def evaluate(cells: MapCells, truth: GroundTruth, thresholds, explored_radius: float = 0.005,
             points: np.ndarray | None = None, *, surface: SurfaceTruth | None = None,
             visible: np.ndarray | None = None, visible_note: str | None = None) -> dict:
    """Metrics of the map at each threshold (and of the points, if given) against
    ``truth``, which must already be in the map's frame: ``{'map': {'<threshold>':
    scores}, 'points': scores or None, 'colour': {'<threshold>': colour scores} or None,
    'colour_note': why there are none, 'seen_note': visible_note}``.

    ``surface``: :func:`surface_truth` of ``truth`` if already built. The colour scores
    need the map's colours and the truth's; ``visible`` (the surface samples the camera
    saw) adds the coverage of the seen cells, ``visible_note`` says why it is None."""
    if surface is None:
        surface = surface_truth(truth, explored_radius)
    results: dict = {'map': {}, 'points': None, 'colour': None,
                     'colour_note': colour_problem(cells, truth), 'seen_note': None}
    for threshold in thresholds:
        results['map'][f'{threshold:g}'] = map_metrics(
            cells.centres, cells.probabilities, cells.lattice, surface, threshold)
    if points is not None:
        results['points'] = point_metrics(points, surface)
    if results['colour_note'] is None:
        results['colour'] = {f'{threshold:g}': colour_metrics(
            cells.centres, cells.probabilities, cells.lattice, cells.colours, cells.textured,
            surface, truth.surface_colours, visible, threshold) for threshold in thresholds}
        results['seen_note'] = None if visible is not None else visible_note
    return results


def frame_check(cells: MapCells, truth: GroundTruth, threshold: float) -> str | None:
    """A warning when the map and the truth seem to be in different frames."""
    keep = cells.probabilities > threshold
    if not keep.any() or len(truth.contacts) == 0:
        return None
    offset = np.linalg.norm(cells.centres[keep].mean(axis=0) - truth.contacts.mean(axis=0))
    extent = np.linalg.norm(np.ptp(truth.surface_points, axis=0))
    if offset > max(0.5 * extent, 0.03):
        other = 'tracker' if truth.frame == 'object' else 'object'
        return (f'the occupied cells are {offset * 100:.1f} cm from the true contacts: are the '
                f'map and the truth in the same frame? (compared in the {truth.frame} frame; '
                f'try --frame {other})')
    return None


# Rows of the printed table: the map's (one column per threshold) and the points'.
MAP_TABLE_KEYS = ('occupied_cells', 'explored_cells', 'iou', 'cell_precision', 'cell_recall',
                  'cell_fscore', 'precision_at_5mm', 'recall_at_5mm', 'fscore_at_5mm',
                  'chamfer_mm', 'map_to_surface_mm', 'surface_to_map_mm', 'normal_offset_mm',
                  'com_error_mm', 'stray_cells', 'off_surface_cells')
POINT_TABLE_KEYS = ('points', 'precision_at_5mm', 'recall_at_5mm', 'fscore_at_5mm',
                    'chamfer_mm', 'points_to_surface_mm', 'median_to_surface_mm',
                    'p95_to_surface_mm', 'surface_to_points_mm')
COLOUR_TABLE_KEYS = ('textured_cells', 'textured_fraction', 'seen_cells',
                     'seen_textured_fraction', 'unseen_textured_cells', 'colour_error_median',
                     'colour_error_p95', 'colour_error_shuffled_median')


def label_width() -> int:
    """Width of the label column of :func:`metrics_table` (and of the sections that other
    modules append to it)."""
    return max(len(METRIC_LABELS[k][0]) for k in METRIC_LABELS) + 2


def format_metric(key: str, value) -> str:
    """A score as its table shows it (``n/a`` where undefined)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return 'n/a'
    label_format = METRIC_LABELS[key][1]
    return label_format.format(int(value) if label_format.endswith('d}') else value)


def metrics_table(results: dict, column_names: list[str]) -> list[str]:
    """The lines of the table of :func:`evaluate`'s results: a row per map score, a column
    per threshold (``column_names``), the map's colours (same columns) or one line saying
    why there are none, then the registered points' scores if any."""
    columns = list(results['map'].values())
    width = label_width()
    lines = [f'{"metric":<{width}}' + ''.join(f'{name:>12}' for name in column_names)]
    lines.append('-' * len(lines[0]))
    for key in MAP_TABLE_KEYS:
        lines.append(f'{METRIC_LABELS[key][0]:<{width}}'
                     + ''.join(f'{format_metric(key, column[key]):>12}' for column in columns))
    colour = results.get('colour')
    if colour is not None:
        lines.append('')
        lines.append(f'{"map colours (occupied cells)":<{width}}'
                     + ''.join(f'{name:>12}' for name in column_names))
        lines.append('-' * len(lines[0]))
        for key in COLOUR_TABLE_KEYS:
            lines.append(f'{METRIC_LABELS[key][0]:<{width}}' + ''.join(
                f'{format_metric(key, column[key]):>12}' for column in colour.values()))
        if results.get('seen_note'):
            lines.append(f'  (seen cells: n/a: {results["seen_note"]})')
    elif results.get('colour_note'):
        lines.append('')
        lines.append(f'map colours: n/a ({results["colour_note"]})')
    points = results.get('points')
    if points is not None:
        lines.append('')
        lines.append(f'{"registered raw points":<{width}}{"points":>12}')
        lines.append('-' * (width + 12))
        for key in POINT_TABLE_KEYS:
            lines.append(f'{METRIC_LABELS[key][0]:<{width}}{format_metric(key, points[key]):>12}')
    return lines
