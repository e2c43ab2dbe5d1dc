"""The local maps (touch, vision) and the global map fused from them, side by side.

For a map saved with fusion (its NPZ keeps ``local_touch`` and ``local_vision``), each of
the three maps is scored on its cells above the threshold:

* precision: occupied cell centres within 5 mm of the true surface;
* recall against the whole true surface (every surface sample within 5 mm of an occupied
  centre), and against the surface either sensor observed: the touched part (samples within
  the explored radius of a true contact) and the part the camera saw (``visible``: samples
  the truth's depth image shows), and the F-scores of both;
* the entropy of the map (binary entropy summed over the cells, bits: eq. 10's uncertainty);
* the occupied cells only this sensor contributed to (the other map never updated them).

Vectorised over the grid; the nearest-neighbour queries are scipy's KD-trees.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from inhand_common.log_odds import probability as probability_of
from inhand_mapping.entropy import map_entropy
from inhand_tools.map_cells import load_fused_maps
from inhand_tools.map_quality import SurfaceTruth

__all__ = ['FUSION_SCORE_KEYS', 'fusion_scores', 'fusion_table', 'map_scores']

FUSION_SCORE_KEYS = ('occupied_cells', 'precision_at_5mm', 'recall_whole_at_5mm',
                     'fscore_whole_at_5mm', 'recall_observed_at_5mm', 'fscore_observed_at_5mm',
                     'entropy_bits', 'only_this_sensor')
MAPS = ('touch', 'vision', 'global')


def _fscore(precision: float, recall: float) -> float:
    return 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0


def _within(targets: np.ndarray, queries: np.ndarray, distance: float) -> np.ndarray:
    """Which ``queries`` have a target within ``distance`` (all False without targets)."""
    if len(targets) == 0:
        return np.zeros(len(queries), dtype=bool)
    found, _ = cKDTree(targets).query(queries, k=1, distance_upper_bound=distance, workers=-1)
    return np.isfinite(found)


def map_scores(occupied: np.ndarray, surface: SurfaceTruth, observed: np.ndarray,
               distance: float = 0.005) -> dict:
    """Precision and both recalls of occupied cell centres (M, 3) against the surface;
    ``observed`` (N,) marks the surface samples either sensor observed."""
    near, _ = surface.tree.query(occupied, k=1, distance_upper_bound=distance, workers=-1) \
        if len(occupied) else (np.empty(0), None)
    precision = float(np.mean(np.isfinite(near))) if len(occupied) else math.nan
    covered = _within(occupied, surface.points, distance)
    whole = float(np.mean(covered))
    seen = float(np.mean(covered[observed])) if observed.any() else math.nan
    return {'occupied_cells': int(len(occupied)), 'precision_at_5mm': precision,
            'recall_whole_at_5mm': whole, 'fscore_whole_at_5mm': _fscore(precision, whole),
            'recall_observed_at_5mm': seen,
            'fscore_observed_at_5mm': _fscore(precision, seen) if not math.isnan(seen)
            else math.nan}


def fusion_scores(npz: Path, surface: SurfaceTruth, visible: np.ndarray | None,
                  threshold: float = 0.8) -> dict | None:
    """{'touch' | 'vision' | 'global': scores} of a map saved with fusion, None for a map
    without local maps. ``visible``: the surface samples the camera saw (None: only the
    touched surface counts as observed)."""
    fused = load_fused_maps(npz)
    if fused is None:
        return None
    observed = surface.explored | (visible if visible is not None else False)
    # a local map's occupied cells the other map never updated; the global map's, those
    # exactly one of them updated
    by_one_sensor = {'touch': ~fused.vision_observed, 'vision': ~fused.touch_observed,
                     'global': fused.touch_observed ^ fused.vision_observed}
    results = {}
    for name, log_odds in (('touch', fused.touch), ('vision', fused.vision),
                           ('global', fused.global_)):
        probability = probability_of(log_odds)
        occupied = probability > threshold
        scores = map_scores(fused.spec.cell_centres(np.argwhere(occupied)), surface, observed)
        scores['entropy_bits'] = map_entropy(probability)
        scores['only_this_sensor'] = int(np.count_nonzero(occupied & by_one_sensor[name]))
        results[name] = {key: scores[key] for key in FUSION_SCORE_KEYS}
    return results


_LABELS = {
    'occupied_cells': 'occupied cells',
    'precision_at_5mm': 'precision @ 5 mm',
    'recall_whole_at_5mm': 'recall @ 5 mm, whole true surface',
    'fscore_whole_at_5mm': 'F-score @ 5 mm, whole surface',
    'recall_observed_at_5mm': 'recall @ 5 mm, surface either sensor observed',
    'fscore_observed_at_5mm': 'F-score @ 5 mm, observed surface',
    'entropy_bits': 'entropy (bits, eq. 10 binary)',
    'only_this_sensor': 'occupied cells only this sensor updated',
}


def fusion_table(results: dict) -> list[str]:
    """The three maps side by side (lines of text)."""
    lines = [f'{"local and global maps":<48}{"touch":>10}{"vision":>10}{"global":>10}',
             '-' * 78]
    for key in FUSION_SCORE_KEYS:
        values = []
        for name in MAPS:
            value = results[name][key]
            values.append(f'{value:>10d}' if isinstance(value, int) else
                          f'{value:>10.0f}' if key == 'entropy_bits' else f'{value:>10.3f}')
        lines.append(f'{_LABELS[key]:<48}' + ''.join(values))
    lines.append('(global: "only one sensor" counts its occupied cells one sensor alone '
                 'updated)')
    return lines
