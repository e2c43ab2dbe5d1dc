"""The occupancy mapping core: eq. 3-4 update (the samples model), object frame, entropy,
map files, clouds.

Expected values are worked out here by hand (math.exp / math.log on the paper's formulas)
or by a plain-Python per-point, per-neighbour loop, never by calling the code under test.

Model under test (occupancy.py, docs/mapping.md): l += w log(L / c) with L = exp(-d^2 / (2 sigma^2)),
d the distance to the cell (default; 0 inside it) or to its centre (the paper, PAPER
below), c = P(Z|not O) = 0.45, prior 0.5 (l = 0), clamp to [0.12, 0.97] after every update;
neighbourhood 1 (containing cell) or 27 (also the 26 neighbours). ``w`` is the sample's
dwell weight (dwell.py), and one finger's visit of a cell gives at most w = 1 in total.

"""

from __future__ import annotations

import json
import math
import os
import pickle
import subprocess
import sys
import types

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from plyfile import PlyData
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2, PointField

from inhand_common.packed_rgb import pack_rgb
from inhand_common.point_cloud import from_point_cloud2, to_point_cloud2
from inhand_mapping import map_io
from inhand_mapping.cloud_layouts import MAP_CELL_DTYPE, TEXTURED_CELL_DTYPE, textured_cells
from inhand_mapping.dwell import DwellWeights, WeightedSamples
from inhand_mapping.entropy import cell_entropy, entropy_weights, eq10_entropy, map_entropy
from inhand_mapping.map_products import MapProducts, save_map
from inhand_mapping.object_frame import object_frame
from inhand_mapping.occupancy import GridSpec, IntegrationCounts, logit, probability
from inhand_mapping.occupancy import OccupancyGrid as _OccupancyGrid
from inhand_mapping.occupancy import SensorModel as _SensorModel


def SensorModel(**parameters):
    """The samples model (this module's subject; the path model is test_touch_paths.py)."""
    return _SensorModel(**{'touch_model': 'samples', **parameters})


def OccupancyGrid(spec=None, model=None):
    """A grid of the samples model unless told otherwise."""
    return _OccupancyGrid(spec or GridSpec(), model if model is not None else SensorModel())


RES = 0.005      # default cell size (m)
SIGMA = 0.002    # default sensor sigma (m)
C = 0.45         # default P(Z | not O)
HALF = 0.175     # half of the default 0.35 m workspace, centred at the origin
P_MIN, P_MAX = 0.12, 0.97
# The paper read literally: eq. 3 at the cell centre, every sample a full measurement.
PAPER = SensorModel(distance_to='centre', evidence_rate=0.0, visit_gap=0.0)


# ============================================================================ hand helpers

def centre_of(i, j, k, res=RES, half=HALF):
    """Centre of cell (i, j, k) of a workspace [-half, half)^3 centred at the origin."""
    return np.array([-half + (i + 0.5) * res, -half + (j + 0.5) * res, -half + (k + 0.5) * res])


def log_ratio(d2, sigma=SIGMA, c=C):
    """log(L / c) of eq. 3 for a squared distance d2 (m^2)."""
    return math.log(math.exp(-d2 / (2.0 * sigma * sigma)) / c)


def prob(log_odds):
    return 1.0 / (1.0 + math.exp(-log_odds))


def hand_logit(p):
    return math.log(p / (1.0 - p))


def untouched_elsewhere(grid, keep):
    """Every cell not in ``keep`` still holds the prior, no hits and no first touch."""
    others = np.ones(grid.spec.shape, dtype=bool)
    for ijk in keep:
        others[ijk] = False
    return (np.all(grid.log_odds[others] == 0.0) and np.all(grid.hits[others] == 0)
            and np.all(np.isnan(grid.first_touch[others])))


# ============================================================================ hand-computed cases

def test_one_hit_at_a_cell_centre_gives_one_over_one_plus_c():
    grid = OccupancyGrid()
    grid.integrate(centre_of(10, 20, 30)[None])
    p = grid.probabilities()[10, 20, 30]
    # L = 1 at the centre; prior 0.5: p = L / (L + c) = 1 / 1.45
    assert p == pytest.approx(1.0 / (1.0 + 0.45), abs=1e-12)
    assert round(float(p), 4) == 0.6897
    assert p < 0.7  # one contact is not enough to call a cell occupied
    assert grid.log_odds[10, 20, 30] == pytest.approx(-math.log(0.45), abs=1e-12)
    assert grid.hits[10, 20, 30] == 1
    assert grid.touched_mask().sum() == 1
    assert untouched_elsewhere(grid, [(10, 20, 30)])


@pytest.mark.parametrize('sign', [+1.0, -1.0])
def test_one_hit_at_a_cell_corner_follows_eq4(sign):
    eps = 1e-9  # just inside the cell, so which cell holds it is not a rounding question
    offset = RES / 2 - eps
    grid = OccupancyGrid(model=PAPER)
    grid.integrate((centre_of(40, 5, 61) + sign * offset)[None])
    d2 = 3 * offset ** 2
    big_l = math.exp(-d2 / (2 * SIGMA ** 2))
    expected = big_l * 0.5 / (big_l * 0.5 + C * 0.5)  # eq. 4 with prior 0.5
    assert grid.probabilities()[40, 5, 61] == pytest.approx(expected, abs=1e-12)
    # the exact corner, d = sqrt(3) res / 2: L = exp(-2.34375) = 0.0960, p = 0.1758
    corner = math.exp(-(3 * RES * RES / 4) / (2 * SIGMA ** 2))
    assert grid.probabilities()[40, 5, 61] == pytest.approx(corner / (corner + C), abs=1e-6)
    assert grid.probabilities()[40, 5, 61] == pytest.approx(0.1758, abs=1e-4)
    assert grid.hits[40, 5, 61] == 1
    assert untouched_elsewhere(grid, [(40, 5, 61)])


@pytest.mark.parametrize('one_batch', [True, False])
def test_repeated_hits_at_the_centre_pass_the_thresholds(one_batch):
    grid = OccupancyGrid()
    point = centre_of(33, 34, 35)[None]
    expected = {1: 1 / (1 + C), 2: 1 / (1 + C ** 2), 3: 1 / (1 + C ** 3)}
    if one_batch:
        for n in (1, 2, 3):
            fresh = OccupancyGrid()
            fresh.integrate(np.repeat(point, n, axis=0))
            assert fresh.probabilities()[33, 34, 35] == pytest.approx(expected[n], abs=1e-12)
    else:
        for n in (1, 2, 3):
            grid.integrate(point)
            assert grid.probabilities()[33, 34, 35] == pytest.approx(expected[n], abs=1e-12)
            assert grid.hits[33, 34, 35] == n
    assert expected[1] < 0.7 < 0.8 < expected[2] < expected[3]
    assert round(expected[2], 4) == 0.8316 and round(expected[3], 4) == 0.9165


@pytest.mark.parametrize('distance_to', ['cell', 'centre'])
def test_a_single_stray_point_stays_below_0_7_wherever_it_falls_in_its_cell(distance_to):
    rng = np.random.default_rng(7)
    cells = rng.choice(70 ** 3, size=600, replace=False)
    ijk = np.stack(np.unravel_index(cells, (70, 70, 70)), axis=1)
    offsets = rng.uniform(-RES / 2 + 1e-9, RES / 2 - 1e-9, size=(600, 3))
    offsets[0] = 0.0                                   # exactly at the centre
    offsets[1] = RES / 2 - 1e-9                        # at a corner
    offsets[2] = [RES / 2 - 1e-9, 0.0, 0.0]            # at a face
    points = np.array([centre_of(*c) for c in ijk]) + offsets
    grid = OccupancyGrid(model=SensorModel(distance_to=distance_to))
    grid.integrate(points)
    p = grid.probabilities()[tuple(ijk.T)]
    assert p.max() < 0.7
    assert p[0] == pytest.approx(1 / 1.45, abs=1e-12)
    for k in range(600):
        # inside its own cell: distance 0 to the cell, |offset| to the centre
        d2 = float(offsets[k] @ offsets[k]) if distance_to == 'centre' else 0.0
        big_l = math.exp(-d2 / (2 * SIGMA ** 2))
        assert p[k] == pytest.approx(big_l / (big_l + C), abs=1e-12), k
    assert grid.touched_mask().sum() == 600


def test_clamped_at_0_97_after_many_hits():
    for batches in ([20], [1] * 20):
        grid = OccupancyGrid()
        for n in batches:
            grid.integrate(np.repeat(centre_of(1, 2, 3)[None], n, axis=0))
        assert grid.log_odds[1, 2, 3] == pytest.approx(math.log(0.97 / 0.03), abs=1e-12)
        assert grid.probabilities()[1, 2, 3] == pytest.approx(0.97, abs=1e-12)
        assert grid.hits[1, 2, 3] == 20


def test_clamped_at_0_12_after_many_far_from_centre_hits():
    corner = centre_of(68, 0, 9) + (RES / 2 - 1e-9)
    for batches in ([15], [1] * 15):
        grid = OccupancyGrid(model=PAPER)
        for n in batches:
            grid.integrate(np.repeat(corner[None], n, axis=0))
        assert grid.log_odds[68, 0, 9] == pytest.approx(math.log(0.12 / 0.88), abs=1e-12)
        assert grid.probabilities()[68, 0, 9] == pytest.approx(0.12, abs=1e-12)


def test_clamping_is_applied_after_every_update_whatever_the_batches():
    centre = centre_of(20, 20, 20)
    corner = centre + (RES / 2 - 1e-9)
    l_max = math.log(0.97 / 0.03)
    down = log_ratio(3 * (RES / 2 - 1e-9) ** 2)        # one hit at the corner (-1.545)
    # 10 centre hits clamp to l_max; then the corner lowers from there, in one batch or two
    for split in (True, False):
        grid = OccupancyGrid(model=PAPER)
        if split:
            grid.integrate(np.repeat(centre[None], 10, axis=0))
            grid.integrate(corner[None])
        else:
            grid.integrate(np.vstack([np.repeat(centre[None], 10, axis=0), corner[None]]))
        assert grid.log_odds[20, 20, 20] == pytest.approx(l_max + down, abs=1e-12)
        assert grid.probabilities()[20, 20, 20] == pytest.approx(prob(l_max + down), abs=1e-12)
    # the corner first: it cannot go below the lower clamp, then 10 hits climb back up
    grid = OccupancyGrid(model=PAPER)
    grid.integrate(np.vstack([np.repeat(corner[None], 3, axis=0),
                              np.repeat(centre[None], 2, axis=0)]))
    assert grid.log_odds[20, 20, 20] == pytest.approx(hand_logit(P_MIN) - 2 * math.log(C),
                                                      abs=1e-12)


def test_a_measurement_anywhere_in_its_cell_supports_it_fully_by_default():
    grid = OccupancyGrid()
    corner = centre_of(40, 5, 61) + (RES / 2 - 1e-9)
    grid.integrate(np.repeat(corner[None], 2, axis=0))
    assert grid.probabilities()[40, 5, 61] == pytest.approx(1 / (1 + C * C), abs=1e-12)


def test_neighbourhood_27_updates_each_neighbour_with_eq3_at_its_own_centre():
    grid = OccupancyGrid(model=SensorModel(neighbourhood=27, distance_to='centre'))
    offset = np.array([0.0023, 0.0022, -0.0024])
    point = centre_of(30, 40, 50) + offset
    grid.integrate(point[None], np.array([2.5]))
    grid.flush()
    touched = np.argwhere(grid.touched_mask())
    assert len(touched) == 27
    assert {tuple(t) for t in touched} == {(30 + a, 40 + b, 50 + c) for a in (-1, 0, 1)
                                           for b in (-1, 0, 1) for c in (-1, 0, 1)}
    # three of them by hand: the containing cell, a face neighbour, a corner neighbour
    d2_own = 0.0023 ** 2 + 0.0022 ** 2 + 0.0024 ** 2
    d2_face = (0.0023 - 0.005) ** 2 + 0.0022 ** 2 + 0.0024 ** 2            # (+1, 0, 0)
    d2_corner = (0.0023 - 0.005) ** 2 + (0.0022 - 0.005) ** 2 + (-0.0024 + 0.005) ** 2
    assert grid.log_odds[30, 40, 50] == pytest.approx(
        math.log(math.exp(-d2_own / 8e-6) / 0.45), abs=1e-12)             # -1.187
    assert grid.log_odds[31, 40, 50] == pytest.approx(
        math.log(math.exp(-d2_face / 8e-6) / 0.45), abs=1e-12)            # -1.438
    assert grid.log_odds[31, 41, 49] == pytest.approx(                    # (+1, +1, -1)
        math.log(math.exp(-d2_corner / 8e-6) / 0.45), abs=1e-12)          # -1.938
    # the opposite corner (-1, -1, +1) is 7.3 mm away: eq. 3 gives far below 0.12, clamped
    assert grid.log_odds[29, 39, 51] == pytest.approx(math.log(0.12 / 0.88), abs=1e-12)
    # and all 27 (clamped where eq. 3 pushes them below 0.12)
    for i, j, k in touched:
        d = point - centre_of(i, j, k)
        expected = min(max(log_ratio(float(d @ d)), hand_logit(P_MIN)), hand_logit(P_MAX))
        assert grid.log_odds[i, j, k] == pytest.approx(expected, abs=1e-12), (i, j, k)
    # the hit and its time belong to the containing cell only
    assert grid.hits[30, 40, 50] == 1 and grid.hits.sum() == 1
    assert grid.first_touch[30, 40, 50] == 2.5
    assert np.isnan(grid.first_touch).sum() == 70 ** 3 - 1
    assert untouched_elsewhere(grid, [tuple(t) for t in touched])


def test_neighbourhood_27_with_the_distance_to_each_cell():
    grid = OccupancyGrid(model=SensorModel(neighbourhood=27))
    offset = np.array([0.0023, -0.0012, 0.0])
    grid.integrate((centre_of(30, 40, 50) + offset)[None], np.array([1.0]))
    grid.flush()
    # own cell: inside, L = 1; (+1, 0, 0): 0.2 mm away; (-1, 0, 0): 4.8 mm; (+1, -1, 0):
    # 0.2 mm and 1.3 mm; (0, +1, 0): 3.7 mm (L < c: lowered)
    assert grid.log_odds[30, 40, 50] == pytest.approx(-math.log(C), abs=1e-12)
    assert grid.log_odds[31, 40, 50] == pytest.approx(log_ratio(0.0002 ** 2), abs=1e-12)
    assert grid.log_odds[29, 40, 50] == pytest.approx(
        max(log_ratio(0.0048 ** 2), hand_logit(P_MIN)), abs=1e-12)
    assert grid.log_odds[31, 39, 50] == pytest.approx(
        log_ratio(0.0002 ** 2 + 0.0013 ** 2), abs=1e-12)
    assert grid.log_odds[30, 41, 50] == pytest.approx(log_ratio(0.0037 ** 2), abs=1e-12)
    assert grid.log_odds[30, 41, 50] < 0 < grid.log_odds[31, 39, 50]


@pytest.mark.parametrize('cell, expected', [((0, 0, 0), 8), ((69, 69, 69), 8),
                                            ((0, 0, 33), 12), ((0, 33, 33), 18),
                                            ((69, 33, 69), 12), ((33, 69, 33), 18)])
def test_neighbourhood_27_at_the_workspace_border_updates_only_cells_inside(cell, expected):
    grid = OccupancyGrid(model=SensorModel(neighbourhood=27))
    grid.integrate((centre_of(*cell) + 0.0003)[None])
    assert grid.touched_mask().sum() == expected
    assert grid.counts == IntegrationCounts(integrated=1, outside=0, invalid=0)


def test_neighbourhood_1_touches_only_the_containing_cell():
    grid = OccupancyGrid(model=SensorModel(neighbourhood=1))
    grid.integrate((centre_of(30, 40, 50) + 0.0024)[None])
    assert grid.touched_mask().sum() == 1
    assert untouched_elsewhere(grid, [(30, 40, 50)])


# =========================================================================== brute-force reference

def reference_log_odds(spec: GridSpec, model: SensorModel, batches, times=None,
                       fingers=None, weights=None):
    """Eq. 3-4 the slow, obvious way: per point, per neighbour, clamped after each update;
    with ``times`` (one list per batch), one finger's visit of a cell gives at most 1 in
    total, each point adding ``weights`` (default 1) until then.

    Returns (log-odds as a flat list indexed like the grid, min and max value ever reached
    before clamping, counts as a dict)."""
    n = int(round(spec.size / spec.resolution))
    origin = [spec.centre[a] - spec.size / 2 for a in range(3)]
    prior = math.log(model.prior / (1 - model.prior))
    l_min = math.log(model.clamp_min / (1 - model.clamp_min))
    l_max = math.log(model.clamp_max / (1 - model.clamp_max))
    reach = 1 if model.neighbourhood == 27 else 0
    log_odds = [prior] * n ** 3
    lowest, highest = prior, prior
    counts = {'integrated': 0, 'outside': 0, 'invalid': 0}
    visits = {}   # (finger, cell) -> [last time, evidence given]
    for b, batch in enumerate(batches):
        for k, point in enumerate(batch):
            x, y, z = (float(v) for v in point)
            t = float(times[b][k]) if times is not None else 0.0
            if not all(math.isfinite(v) for v in (x, y, z, t)):
                counts['invalid'] += 1
                continue
            ijk = [math.floor((v - o) / spec.resolution) for v, o in zip((x, y, z), origin)]
            if any(i < 0 or i >= n for i in ijk):
                counts['outside'] += 1
                continue
            counts['integrated'] += 1
            w = float(weights[b][k]) if weights is not None else 1.0
            finger = int(fingers[b][k]) if fingers is not None else 0
            for dx in range(-reach, reach + 1):
                for dy in range(-reach, reach + 1):
                    for dz in range(-reach, reach + 1):
                        jx, jy, jz = ijk[0] + dx, ijk[1] + dy, ijk[2] + dz
                        if not (0 <= jx < n and 0 <= jy < n and 0 <= jz < n):
                            continue
                        d2 = 0.0
                        for v, jv, o in zip((x, y, z), (jx, jy, jz), origin):
                            low, high = o + jv * spec.resolution, o + (jv + 1) * spec.resolution
                            if model.distance_to == 'centre':
                                d2 += (v - (low + high) / 2) ** 2
                            else:
                                d2 += max(low - v, 0.0, v - high) ** 2
                        likelihood = math.exp(-d2 / (2 * model.sigma ** 2))
                        j = (jx * n + jy) * n + jz
                        dw = w
                        if times is not None:
                            last, given = visits.get((finger, j), (-math.inf, 0.0))
                            if abs(t - last) > model.visit_gap:
                                given = 0.0
                            dw = min(w, 1.0 - given)
                            visits[(finger, j)] = (t, given + max(dw, 0.0))
                            if dw <= 0:
                                continue
                        value = log_odds[j] + dw * math.log(
                            likelihood / model.p_z_given_not_occupied)
                        lowest, highest = min(lowest, value), max(highest, value)
                        log_odds[j] = min(max(value, l_min), l_max)
    return log_odds, lowest, highest, counts


def random_batches(seed, spec: GridSpec, count=400, n_batches=3):
    """Points over and a little beyond a small workspace (some land outside), half of them
    near a few cell centres so that cells get several good hits, with a few NaN/inf; split
    into batches."""
    rng = np.random.default_rng(seed)
    centre = np.asarray(spec.centre)
    spread = centre + rng.uniform(-0.6 * spec.size, 0.6 * spec.size, size=(count // 2, 3))
    n = spec.cells_per_axis
    hot = spec.cell_centres(rng.integers(0, n, size=(25, 3)))
    near = hot[rng.integers(0, 25, count // 3)] + \
        rng.normal(0.0, 0.2 * spec.resolution, size=(count // 3, 3))
    cold = spec.cell_centres(rng.integers(0, n, size=(8, 3))) + 0.45 * spec.resolution
    far = cold[rng.integers(0, 8, count - count // 2 - count // 3)]
    points = np.vstack([spread, near, far])
    points[rng.choice(count, 6, replace=False), rng.integers(0, 3, 6)] = [
        np.nan, np.inf, -np.inf, np.nan, np.inf, np.nan]
    rng.shuffle(points)
    return np.array_split(points, n_batches)


SMALL = GridSpec(size=0.05, resolution=0.005, centre=(0.01, -0.02, 0.03))
WIDE = dict(clamp_min=1e-300, clamp_max=1 - 2 ** -52)


@pytest.mark.parametrize('neighbourhood', [1, 27])
@pytest.mark.parametrize('clamps', ['wide', 'default'])
def test_grid_matches_the_brute_force_reference(neighbourhood, clamps):
    model = SensorModel(neighbourhood=neighbourhood, distance_to='centre',
                        **(WIDE if clamps == 'wide' else {}))
    batches = random_batches(11 + neighbourhood, SMALL)
    grid = OccupancyGrid(SMALL, model)
    for batch in batches:
        grid.integrate(batch)
    expected, lowest, highest, counts = reference_log_odds(SMALL, model, batches)
    expected = np.array(expected).reshape(SMALL.shape)
    assert np.max(np.abs(grid.log_odds - expected)) < 1e-12
    assert vars(grid.counts) == counts
    assert counts['outside'] > 50 and counts['invalid'] == 6 and counts['integrated'] > 200
    if clamps == 'wide':
        # the clamps were never reached, so they hid no difference
        assert hand_logit(WIDE['clamp_min']) < lowest and highest < hand_logit(WIDE['clamp_max'])
        # and the values spread beyond the default clamps (with 27 cells, the points in
        # the neighbours of a hot cell pull it down, so it peaks lower)
        assert lowest < hand_logit(P_MIN) and lowest < -10 * (neighbourhood == 27)
        assert highest > (hand_logit(P_MAX) if neighbourhood == 1 else 1.5)
    else:
        # clamping happened, on both sides
        assert np.any(expected == hand_logit(P_MIN))
        assert np.any(expected == hand_logit(P_MAX)) == (neighbourhood == 1)
        assert np.isclose(grid.log_odds, hand_logit(P_MIN), rtol=0, atol=1e-12).sum() == \
            np.isclose(expected, hand_logit(P_MIN), rtol=0, atol=1e-12).sum()


def test_brute_force_with_other_sigma_and_c_and_dense_cells():
    spec = GridSpec(size=0.03, resolution=0.003, centre=(0.0, 0.0, 0.0))
    model = SensorModel(sigma=0.0035, p_z_given_not_occupied=0.3, neighbourhood=27, **WIDE)
    rng = np.random.default_rng(5)
    points = rng.normal(0.0, 0.004, size=(600, 3))   # many points per cell
    grid = OccupancyGrid(spec, model)
    grid.integrate(points)
    expected, lowest, highest, _ = reference_log_odds(spec, model, [points])
    assert np.max(np.abs(grid.log_odds - np.array(expected).reshape(spec.shape))) < 1e-12
    assert grid.hits.max() > 10


@pytest.mark.parametrize('neighbourhood', [1, 27])
@pytest.mark.parametrize('distance_to', ['cell', 'centre'])
def test_visits_and_weights_match_the_brute_force_reference(neighbourhood, distance_to):
    """Three fingers wandering in a small workspace, coming back to cells within and after
    the visit gap, with times, finger ids and dwell weights given to the kernel."""
    model = SensorModel(neighbourhood=neighbourhood, distance_to=distance_to, visit_gap=0.5,
                        evidence_rate=15.0)
    spec = GridSpec(size=0.03, resolution=0.005, centre=(0.0, 0.0, 0.0))
    rng = np.random.default_rng(17 + neighbourhood)
    steps = 900
    times = np.repeat(np.arange(steps // 3) * 0.02, 3)
    fingers = np.tile([0, 1, 2], steps // 3)
    points = np.cumsum(rng.normal(0, 0.0012, (steps, 3)), axis=0) % 0.03 - 0.015
    batches = np.array_split(np.arange(steps), 4)
    dwell = DwellWeights(1.0 / model.evidence_rate, spec.resolution)
    weighed = [dwell.push(points[p], times[p], fingers[p]) for p in batches] + [dwell.flush()]
    grid = OccupancyGrid(spec, model)
    for part in batches:
        grid.integrate(points[part], times[part], fingers[part])
    grid.flush()
    expected, _, _, counts = reference_log_odds(
        spec, model, *zip(*weighed))
    assert np.max(np.abs(grid.log_odds - np.array(expected).reshape(spec.shape))) < 1e-12
    assert counts['integrated'] == steps and grid.counts.integrated == steps
    w = np.concatenate([part.weights for part in weighed])
    assert 0.05 < w.min() and w.max() <= 1.0 and (w < 1).mean() > 0.2   # weights in play


# ============================================================================ bookkeeping

def test_outside_and_invalid_points_are_counted_and_ignored():
    grid = OccupancyGrid()
    outside = np.array([[0.2, 0, 0], [-0.2, 0, 0], [0, 0.176, 0], [0, -0.1751, 0],
                        [0, 0, 0.5], [0, 0, -3.0]])
    invalid = np.array([[np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf]])
    inside = np.array([[0.01, 0.01, 0.01], [0.01, 0.01, 0.01]])
    batch = grid.integrate(np.vstack([outside, invalid, inside]))
    assert batch == IntegrationCounts(integrated=2, outside=6, invalid=3)
    assert grid.touched_mask().sum() == 1
    assert grid.hits.sum() == 2
    # NaN or infinite times reject otherwise good points
    times = np.array([1.0, np.nan, np.inf])
    batch = grid.integrate(np.array([[0.05, 0, 0]] * 3), times) + grid.flush()
    assert batch == IntegrationCounts(integrated=1, outside=0, invalid=2)
    assert grid.hits.sum() == 3
    # counts accumulate across calls
    grid.integrate(np.array([[1.0, 1.0, 1.0], [np.nan] * 3]))
    assert grid.counts == IntegrationCounts(integrated=3, outside=7, invalid=6)
    with pytest.raises(ValueError):
        grid.integrate(np.zeros((3, 3)), np.zeros(2))


def test_points_on_the_upper_faces_never_write_past_the_grid():
    grid = OccupancyGrid()
    on_faces = np.array([[0.175, 0.0, 0.0], [0.0, 0.175, 0.0], [0.0, 0.0, 0.175],
                         [0.175, 0.175, 0.175]])
    batch = grid.integrate(on_faces)
    assert batch.integrated + batch.outside == 4 and batch.invalid == 0
    assert grid.touched_mask().sum() == batch.integrated
    grid.integrate(np.array([[0.175 - 1e-12, 0.0, -0.175]]))
    assert grid.hits[69, 35, 0] == 1


def test_a_finite_point_far_away_is_outside_not_invalid():
    grid = OccupancyGrid()
    assert grid.integrate(np.array([[1e307, 0.0, 0.0]])) == \
        IntegrationCounts(integrated=0, outside=1, invalid=0)


def test_hits_per_cell():
    grid = OccupancyGrid()
    a, b = centre_of(5, 6, 7), centre_of(60, 61, 62)
    grid.integrate(np.array([a, a, b, a]))
    grid.integrate(np.array([b, a + 0.001]))
    assert grid.hits[5, 6, 7] == 4 and grid.hits[60, 61, 62] == 2 and grid.hits.sum() == 6
    assert grid.hits.dtype == np.uint32


@pytest.mark.parametrize('touch_model', ['samples', 'path'])
def test_each_cell_keeps_where_its_hits_were_and_their_mean_places_its_surface(touch_model):
    """The sum of the positions counted in each cell's hits (timed and untimed points,
    outside and invalid ones left out) is kept exactly; ``contact_centroids`` is their mean
    per listed cell, the centre of a cell occupied without a hit of its own. The shape node
    sums the registered points it receives with ``position_sums``: the same sums."""
    from inhand_common.cell_lattice import Lattice
    from inhand_common.contact_centroids import position_sums
    model = SensorModel(neighbourhood=27) if touch_model == 'samples' else _SensorModel()
    grid = OccupancyGrid(SMALL, model)
    points = []
    for k, batch in enumerate(random_batches(5, SMALL)):
        grid.integrate(batch, np.full(len(batch), float(k)), np.arange(len(batch)) % 3)
        points.append(batch)
    untimed = random_batches(6, SMALL, count=60, n_batches=1)[0]
    grid.integrate(untimed)
    grid.flush()
    points = np.concatenate(points + [untimed])
    inside = np.isfinite(points).all(axis=1) & SMALL.contains(np.nan_to_num(points, nan=1e9))
    keys = SMALL.cell_indices(points[inside])
    expected = np.zeros((*SMALL.shape, 3))
    np.add.at(expected, tuple(keys.T), points[inside])
    assert np.allclose(grid.contact_sum, expected, rtol=0, atol=1e-15)
    assert grid.hits.sum() == inside.sum()
    centres, _, hits, _ = grid.cells()
    means = grid.contact_centroids()
    counted = hits > 0
    assert counted.any() and (~counted).any()       # 27-neighbourhood / spread: both kinds
    ijk = SMALL.cell_indices(centres)
    assert np.allclose(means[counted], expected[tuple(ijk[counted].T)] / hits[counted, None])
    assert np.array_equal(means[~counted], centres[~counted])
    assert np.all(np.abs(means - centres) <= RES / 2 + 1e-12)    # inside their cells
    sums, counts = position_sums(points, centres, Lattice(RES, tuple(SMALL.origin)))
    assert np.array_equal(counts, hits) and np.allclose(sums, expected[tuple(ijk.T)], atol=1e-12)
    settled = grid.settled_copy()
    assert np.array_equal(settled.contact_sum, grid.contact_sum)
    grid.reset()
    assert not grid.contact_sum.any()


def test_the_shape_nodes_store_keeps_the_newest_positions_and_far_ones_fall_in_no_cell():
    from inhand_common.cell_lattice import Lattice
    from inhand_common.contact_centroids import RecentPositions, centroids, position_sums
    store = RecentPositions(8)
    for k in range(5):
        store.add(np.full((2, 3), float(k)))
    # over the capacity by a quarter at most before the oldest go: none dropped yet
    assert len(store) == 8 and store.dropped == 0
    assert np.array_equal(store.points()[:, 0], [1.0, 1.0, 2.0, 2.0, 3.0, 3.0, 4.0, 4.0])
    store.add(np.full((1, 3), 5.0))
    assert len(store) == 8 and store.dropped == 3
    assert np.array_equal(store.points()[:, 0], [1.0, 2.0, 2.0, 3.0, 3.0, 4.0, 4.0, 5.0])
    lattice = Lattice(0.01)
    centres = np.array([[0.005, 0.005, 0.005], [0.015, 0.005, 0.005]])
    far = np.array([[0.002, 0.004, 0.006], [1e12, 0.0, 0.0], [np.nan, 0.0, 0.0], [0.013, 0.001, 0.009]])
    sums, counts = position_sums(far, centres, lattice)
    assert counts.tolist() == [1, 1]
    assert np.allclose(centroids(centres, sums, counts), far[[0, 3]])
    assert np.array_equal(centroids(centres, sums, [0, 0]), centres)
    with pytest.raises(ValueError, match='2 cells, 2 sums and 1 counts'):
        centroids(centres, sums, [1])
    # at most each cell's newest as many as the map's hits there (older: before a reset)
    stream = np.array([[0.001, 0.001, 0.001], [0.012, 0.002, 0.002], [0.003, 0.003, 0.003],
                       [0.009, 0.009, 0.009], [0.014, 0.004, 0.004]])
    sums, counts = position_sums(stream, centres, lattice, newest=[2, 5])
    assert counts.tolist() == [2, 2]
    assert np.allclose(sums[0], stream[2] + stream[3]) and np.allclose(sums[1], stream[1] + stream[4])
    sums, counts = position_sums(stream, centres, lattice, newest=[1, 0])
    assert counts.tolist() == [1, 0] and np.allclose(sums[0], stream[3])


def test_first_touch_is_the_earliest_time_and_never_moves_later():
    grid = OccupancyGrid()
    a, b = centre_of(5, 6, 7), centre_of(8, 9, 10)
    grid.integrate(np.array([a, a, a, b]), np.array([3.0, 1.0, 2.0, 7.5]))
    grid.flush()
    assert grid.first_touch[5, 6, 7] == 1.0 and grid.first_touch[8, 9, 10] == 7.5
    grid.integrate(np.array([a, b]), np.array([5.0, 9.0]))        # later: no change
    grid.flush()
    assert grid.first_touch[5, 6, 7] == 1.0 and grid.first_touch[8, 9, 10] == 7.5
    grid.integrate(np.array([a]), np.array([0.25]))                # earlier: moves earlier
    grid.flush()
    assert grid.first_touch[5, 6, 7] == 0.25
    grid.integrate(np.array([b]))                                  # no times: no change
    assert grid.first_touch[8, 9, 10] == 7.5
    grid.integrate(np.array([b, a]), np.array([np.nan, -np.inf]))  # rejected: no change
    assert grid.first_touch[8, 9, 10] == 7.5 and grid.first_touch[5, 6, 7] == 0.25
    assert np.isnan(grid.first_touch).sum() == 70 ** 3 - 2
    fresh = OccupancyGrid()
    fresh.integrate(np.array([b]))
    assert np.all(np.isnan(fresh.first_touch))


def test_reset_clears_everything_and_the_grid_starts_afresh():
    model = SensorModel(neighbourhood=27)
    batches = random_batches(3, SMALL)
    grid = OccupancyGrid(SMALL, model)
    for k, batch in enumerate(batches):
        grid.integrate(batch, np.full(len(batch), float(k)))
    assert grid.touched_mask().any()
    grid.reset()
    assert np.all(grid.log_odds == 0.0) and np.all(grid.hits == 0)
    assert np.all(np.isnan(grid.first_touch))
    assert not grid.touched_mask().any()
    assert grid.counts == IntegrationCounts()
    fresh = OccupancyGrid(SMALL, model)
    for grid_ in (grid, fresh):
        grid_.integrate(batches[0], np.arange(len(batches[0]), dtype=float))
    assert np.array_equal(grid.log_odds, fresh.log_odds)
    assert np.array_equal(grid.hits, fresh.hits)
    assert np.array_equal(grid.first_touch, fresh.first_touch, equal_nan=True)


def test_cells_lists_touched_cells_and_thresholds():
    grid = OccupancyGrid()
    a, b = centre_of(1, 2, 3), centre_of(4, 5, 6)
    # two fingers at a (two visits), one at b
    grid.integrate(np.array([a, a, b]), np.array([0.5, 0.7, 0.9]), np.array([0, 1, 0]))
    grid.flush()
    centres, p, hits, first = grid.cells()
    order = np.argsort(hits)
    assert np.allclose(centres[order], [b, a], atol=1e-15)
    assert np.allclose(p[order], [1 / 1.45, 1 / (1 + C * C)], atol=1e-12)
    assert list(hits[order]) == [1, 2] and list(first[order]) == [0.9, 0.5]
    centres, p, hits, first = grid.cells(threshold=0.8)
    assert len(p) == 1 and np.allclose(centres[0], a, atol=1e-15)
    assert logit(0.5) == 0.0 and probability(0.0) == 0.5


# ============================================================================ streams

def fingertip_stream(seed, count=6000, rate=240.0):
    """Three fingertips per tracker frame (same stamp), monotone sensor time, a few bad
    points and NaN stamps, some points outside."""
    rng = np.random.default_rng(seed)
    frames = count // 3
    times = np.repeat(np.arange(frames) / rate + 12.3, 3)
    fingers = np.tile([0, 1, 2], frames)
    walk = np.cumsum(rng.normal(0, 0.0008, size=(frames * 3, 3)), axis=0) * 0.3
    points = np.tile(np.array([[0.02, 0.0, 0.0], [-0.02, 0.01, 0.0], [0.0, -0.02, 0.01]]),
                     (frames, 1)) + walk + rng.normal(0, 0.0015, size=(frames * 3, 3))
    chosen = rng.choice(len(points), 39, replace=False)
    points[chosen[:30]] += 0.3             # outside
    points[chosen[30:35], 1] = np.nan      # bad positions
    times[chosen[35:]] = np.nan            # bad stamps
    return points, times, fingers


def streamed_grid(points, times, fingers, cuts, model=None):
    grid = OccupancyGrid(GridSpec(0.1, 0.005), model or SensorModel())
    bounds = [0, *sorted(cuts), len(points)]
    for start, end in zip(bounds[:-1], bounds[1:]):
        grid.integrate(points[start:end], times[start:end], fingers[start:end])
    grid.flush()
    return grid


def same_grid(a, b, contact_sum=True):
    """``contact_sum=False``: a file of a writer before the contact sums (they load as 0)."""
    return (np.array_equal(a.log_odds, b.log_odds) and np.array_equal(a.hits, b.hits)
            and np.array_equal(a.first_touch, b.first_touch, equal_nan=True)
            and (not contact_sum or np.array_equal(a.contact_sum, b.contact_sum))
            and a.counts == b.counts)


@pytest.mark.parametrize('neighbourhood', [1, 27])
def test_the_map_does_not_depend_on_message_batching(neighbourhood):
    # a short visit gap, so that the fingers come back to cells and visits carry over cuts
    model = SensorModel(neighbourhood=neighbourhood, visit_gap=0.25)
    points, times, fingers = fingertip_stream(21)
    n = len(points)
    reference = streamed_grid(points, times, fingers, [], model=model)
    assert reference.counts.invalid == 9 and reference.counts.outside == 30
    assert np.count_nonzero(np.abs(reference.log_odds) > 1.0) > 10   # evidence in play
    rng = np.random.default_rng(4)
    batchings = {
        'one point per message': list(range(1, n)),
        'one frame per message': list(range(3, n, 3)),
        'random splits': sorted(rng.choice(np.arange(1, n), 300, replace=False)),
        'few random splits': sorted(rng.choice(np.arange(1, n), 7, replace=False)),
    }
    for name, cuts in batchings.items():
        assert same_grid(streamed_grid(points, times, fingers, cuts, model=model),
                         reference), name


@pytest.mark.parametrize('touch_model', ['samples', 'path'])
def test_a_settled_copy_is_the_map_of_the_stream_so_far_and_leaves_the_stream_alone(
        touch_model):
    """What a save writes mid-stream (and a pause shows): the copy is the map of a stream
    ending there, and the grid it was copied from goes on as if nothing had happened.
    Flushing the live grid at each save instead ends every track early: here, and in 132
    cells of a 22 s bag saved every 10 s, the map changed."""
    model = SensorModel(touch_model=touch_model, visit_gap=0.25)
    points, times, fingers = fingertip_stream(21)
    reference = streamed_grid(points, times, fingers, [], model=model)
    live = OccupancyGrid(GridSpec(0.1, 0.005), model)
    flushed = OccupancyGrid(GridSpec(0.1, 0.005), model)
    bounds = [0, 1000, 2500, 4000, len(points)]
    for start, end in zip(bounds[:-1], bounds[1:]):
        live.integrate(points[start:end], times[start:end], fingers[start:end])
        flushed.integrate(points[start:end], times[start:end], fingers[start:end])
        held = live.pending
        settled = live.settled_copy()
        assert held > 0 and live.pending == held and settled.pending == 0
        assert same_grid(settled, streamed_grid(points[:end], times[:end], fingers[:end], [],
                                                model=model))
        flushed.flush()
    live.flush()
    assert same_grid(live, reference)
    if touch_model == 'path':    # the samples model weighs this slow walk alike either way
        assert not same_grid(flushed, reference)


# ============================================================================ dwell, visits

def weigh(dwell, points, times, fingers):
    """Weights of a whole stream: pushed at once, then flushed."""
    return WeightedSamples.joined([dwell.push(points, times, fingers), dwell.flush()]).weights


def test_dwell_weights_by_hand():
    period, cell = 1 / 15, 0.005
    # 15 Hz, sliding at 3 cm/s (2 mm per sample, under a cell per period): all 1
    t = np.arange(10) * period
    slow = np.outer(0.03 * t, [1.0, 0.0, 0.0])
    assert np.allclose(weigh(DwellWeights(period, cell), slow, t, np.zeros(10, int)), 1.0)
    # 240 Hz, the same slide: 1/16 each, the first one (no previous sample) 1
    t2 = np.arange(64) / 240.0
    w = weigh(DwellWeights(period, cell), np.outer(0.03 * t2, [0.0, 1.0, 0.0]), t2,
              np.ones(64, int))
    assert w[0] == 1.0 and np.allclose(w[1:], 1 / 16)
    # 15 Hz at 0.3 m/s: 2 cm per period, a cell crossed in 1/60 s: weight 1/4, the first
    # sample too (its speed comes from the next one)
    w = weigh(DwellWeights(period, cell), np.outer(0.3 * t, [0.0, 0.0, 1.0]), t,
              np.zeros(10, int))
    assert np.allclose(w, 0.25)
    # sliding, then lifting off at 0.3 m/s: the last sample on the surface is already
    # leaving it (1/4), as is every sample in the air
    lift = np.where(t > 4.5 * period, 0.3 * (t - 4 * period), 0.0)
    path = np.stack([0.03 * t, np.zeros(10), lift], axis=1)
    w = weigh(DwellWeights(period, cell), path, t, np.zeros(10, int))
    assert np.allclose(w[:4], 1.0) and np.allclose(w[4:], 0.25, rtol=0.02)
    # neighbours more than two periods away on both sides: the speed is unknown, and a
    # sample after a gap stands for one period at most
    t3 = np.array([10.0, 10.5, 10.5 + period, 11.0])
    p3 = np.array([[0, 0, 0.0], [0, 0, 0.1], [0, 0, 0.12], [0, 0, 0.3]])
    w = weigh(DwellWeights(period, cell), p3, t3, np.zeros(4, int))
    assert w[0] == 1.0 and w[3] == 1.0 and w[1:3] == pytest.approx([0.25, 0.25])
    with pytest.raises(ValueError):
        DwellWeights(0.0, cell)


def test_dwell_holds_samples_back_until_their_next_period_and_keeps_the_order():
    period, cell = 1 / 15, 0.005
    dwell = DwellWeights(period, cell)
    t = np.repeat(np.arange(6) * period, 2)                       # two fingers per frame
    fingers = np.tile([0, 1], 6)
    points = np.outer(0.03 * t, [1.0, 0.0, 0.0]) + fingers[:, None] * 0.05
    out = dwell.push(points, t, fingers)
    # frames 0-4 have their next period; frame 5 waits for frame 6
    assert np.array_equal(out.times, t[:10]) and np.array_equal(out.fingers, fingers[:10])
    assert dwell.pending == 2
    assert dwell.push(np.empty((0, 3)), np.empty(0), np.empty(0, int)).count == 0
    # finger 1 stops; finger 0 goes on: finger 1's last sample is settled once finger 0 is
    # more than two periods past it (nothing close enough to count can still come)
    t0 = 5 * period + np.arange(1, 4) * period
    out = dwell.push(np.outer(0.03 * t0, [1.0, 0.0, 0.0]), t0, np.zeros(3, int))
    assert list(out.fingers) == [0, 1, 0, 0] and np.allclose(out.weights, 1.0)
    assert dwell.pending == 1
    # a time going back more than a period (a looped bag) ends the stream: the held
    # sample is released as at its end, and the new stream starts afresh
    out = dwell.push(np.array([[0.0, 0, 0], [0.002, 0, 0]]), np.array([0.0, period]),
                     np.zeros(2, int))
    assert list(out.times) == [8 * period, 0.0] and dwell.pending == 1
    # unusable samples pass with weight 1, in their place
    out = dwell.push(np.array([[np.nan, 0, 0], [0.004, 0, 0]]), np.array([1.5 * period, np.nan]),
                     np.zeros(2, int))
    assert out.count == 0 and dwell.pending == 3
    out = dwell.flush()
    assert out.count == 3 and np.isnan(out.points[1, 0]) and np.isnan(out.times[2])
    assert dwell.pending == 0


def test_dwell_weights_do_not_depend_on_batching():
    rng = np.random.default_rng(3)
    points, times, fingers = fingertip_stream(8, count=1500)
    whole = weigh(DwellWeights(1 / 15, 0.005), points, times, fingers)
    cut = DwellWeights(1 / 15, 0.005)
    bounds = [0, *sorted(rng.choice(np.arange(1, 1500), 40, replace=False)), 1500]
    parts = [cut.push(points[a:b], times[a:b], fingers[a:b])
             for a, b in zip(bounds[:-1], bounds[1:])] + [cut.flush()]
    joined = WeightedSamples.joined(parts)
    assert np.array_equal(joined.weights, whole)
    assert np.array_equal(joined.times, times, equal_nan=True)
    assert 0 < whole.min() and whole.max() == 1.0 and len(np.unique(whole)) > 20


def test_one_finger_resting_on_a_spot_is_one_touch_at_any_rate():
    """A fingertip held still in a cell for 2 s, sampled at 15 and at 240 Hz: one visit,
    one measurement (0.69); the same spot touched again after the visit gap: two (0.83)."""
    cell = centre_of(10, 10, 10)
    for rate in (15.0, 240.0):
        grid = OccupancyGrid()
        t = np.arange(0.0, 2.0, 1.0 / rate)
        grid.integrate(np.repeat(cell[None], len(t), axis=0), t, np.zeros(len(t), int))
        grid.flush()
        assert grid.probabilities()[10, 10, 10] == pytest.approx(1 / (1 + C), abs=1e-12), rate
        assert grid.hits[10, 10, 10] == len(t)
        later = t + 2.0 + 3.5        # 3.5 s after the last sample: a new visit
        grid.integrate(np.repeat(cell[None], len(t), axis=0), later, np.zeros(len(t), int))
        grid.flush()
        assert grid.probabilities()[10, 10, 10] == pytest.approx(1 / (1 + C * C), abs=1e-12)


def test_repeated_lifts_at_one_place_are_one_visit_and_another_finger_is_another():
    cell = centre_of(20, 30, 40)
    above = cell + np.array([0.0, 0.0, 0.02])
    # the fingertip touches the cell, lifts 2 cm and comes back
    # (0.2 s on the spot, then 0.8 s up and down), three times in 3 s, at 15 Hz
    times = np.arange(0.0, 3.0, 1.0 / 15.0)
    phase = np.clip(((times % 1.0) - 0.2) / 0.8, 0.0, 1.0)
    path = cell + np.outer(np.sin(np.pi * phase), above - cell)
    grid = OccupancyGrid()
    grid.integrate(path, times, np.zeros(len(times), int))
    grid.flush()
    assert grid.hits[20, 30, 40] >= 9
    assert grid.probabilities()[20, 30, 40] == pytest.approx(1 / (1 + C), abs=1e-12)
    assert grid.probabilities().max() < 0.7      # nothing passes, in the air or on the spot
    # the paper's update would have made the spot and the top of the lifts occupied
    paper = OccupancyGrid(model=SensorModel(evidence_rate=0.0, visit_gap=0.0))
    paper.integrate(path, times, np.zeros(len(times), int))
    assert paper.probabilities()[20, 30, 40] > 0.9 and (paper.probabilities() > 0.8).sum() > 1
    # another finger touching the spot is independent evidence
    grid.integrate(cell[None], np.array([3.0]), np.array([1]))
    grid.flush()
    assert grid.probabilities()[20, 30, 40] == pytest.approx(1 / (1 + C * C), abs=1e-12)


def test_a_finger_flying_through_counts_for_little_and_sliding_counts_fully():
    """The same straight path through a row of cells, at 3 cm/s (sliding) and 0.3 m/s (a
    transit between strokes), sampled at 15 and 240 Hz."""
    start = centre_of(10, 35, 35)
    inner = {}
    for speed in (0.03, 0.3):
        for rate in (15.0, 240.0):
            grid = OccupancyGrid()
            t = np.arange(0.0, 0.15 / speed, 1.0 / rate)
            path = start + np.outer(speed * t, [1.0, 0.0, 0.0])
            grid.integrate(path, t, np.zeros(len(t), int))
            inner[speed, rate] = grid.log_odds[14:36, 35, 35]   # away from the path's ends
    full = -math.log(C)
    # sliding: every cell crossed gets one full measurement, at both rates
    for rate in (15.0, 240.0):
        assert inner[0.03, rate] == pytest.approx(np.full(22, full), rel=1e-9), rate
    # flying: 4 cells per 1/15 s, so a cell gets about a quarter of a measurement: at
    # 15 Hz every fourth cell gets one sample worth 1/4 (the others none), at 240 Hz every
    # cell gets 3-5 samples worth 1/16 each
    assert inner[0.3, 15.0].max() == pytest.approx(0.25 * full, rel=1e-9)
    assert np.count_nonzero(inner[0.3, 15.0]) in (5, 6)
    assert inner[0.3, 240.0].max() <= 5 / 16 * full * (1 + 1e-9)
    assert inner[0.3, 240.0].mean() == pytest.approx(0.25 * full, rel=0.1)


# ============================================================================ parameters

def test_grid_spec_refuses_a_size_that_is_not_whole_cells():
    assert GridSpec(0.35, 0.005).shape == (70, 70, 70)
    assert GridSpec(0.3, 0.003).cells_per_axis == 100
    for size, res in [(0.35, 0.004), (0.1, 0.003), (0.35, 0.0051), (0.35, -0.005),
                      (-0.35, 0.005), (0.0, 0.005)]:
        with pytest.raises(ValueError, match='whole number'):
            GridSpec(size, res)


def test_grid_spec_refuses_zero_resolution_with_value_error():
    with pytest.raises(ValueError):
        GridSpec(0.35, 0.0)


def test_sensor_model_refuses_bad_values():
    SensorModel(neighbourhood=1)
    SensorModel(neighbourhood=27)
    SensorModel(p_z_given_not_occupied=0.999, clamp_min=0.01, prior=0.3, clamp_max=0.31)
    bad = [dict(neighbourhood=5), dict(neighbourhood=26), dict(neighbourhood=0),
           dict(clamp_min=0.5), dict(clamp_min=0.6), dict(clamp_max=0.5), dict(clamp_max=1.0),
           dict(clamp_min=0.0), dict(prior=0.97), dict(p_z_given_not_occupied=0.0),
           dict(p_z_given_not_occupied=1.0), dict(p_z_given_not_occupied=1.2),
           dict(p_z_given_not_occupied=-0.1), dict(sigma=0.0), dict(sigma=-0.002),
           dict(sigma=1e-200),
           dict(distance_to='corner'), dict(evidence_rate=-1.0), dict(visit_gap=-0.1)]
    for kwargs in bad:
        with pytest.raises(ValueError):
            SensorModel(**kwargs)


# ============================================================================ object frame

def sphere_points(rng, count):
    v = rng.normal(size=(count, 3))
    return v / np.linalg.norm(v, axis=1)[:, None]


def test_centre_of_mass_of_a_spherical_shell_is_its_centre():
    rng = np.random.default_rng(2)
    centre = np.array([0.0213, -0.0337, 0.0121])   # off the origin and off the cell grid
    points = centre + 0.05 * sphere_points(rng, 100_000) + rng.normal(0, 0.0005, (100_000, 3))
    grid = OccupancyGrid()
    grid.integrate(points)
    centres, p, _, _ = grid.cells()
    frame = object_frame(centres, p, 0.8)
    assert frame.cells > 300
    assert np.linalg.norm(frame.centre_of_mass - centre) < 0.3 * RES
    assert np.allclose(frame.to_object_centric(centre), centre - frame.centre_of_mass)
    # a shell of radius r has the same spread r / sqrt(3) along any axis
    assert np.allclose(frame.principal_extents, 0.05 / math.sqrt(3), rtol=0.05)
    assert frame.mass == pytest.approx(p[p > 0.8].sum())


def test_principal_axes_of_an_elongated_ellipsoid_follow_its_axes():
    rng = np.random.default_rng(3)
    a, b = 0.5, 0.3
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    rotation = rz @ rx
    centre = np.array([-0.011, 0.017, 0.006])
    semi = np.array([0.08, 0.03, 0.015])
    points = (sphere_points(rng, 150_000) * semi) @ rotation.T + centre
    grid = OccupancyGrid()
    grid.integrate(points)
    frame = object_frame(*grid.cells()[:2], 0.8)
    assert np.linalg.norm(frame.centre_of_mass - centre) < 0.3 * RES
    axes = frame.principal_axes
    assert abs(axes[:, 0] @ rotation[:, 0]) > 0.999     # long axis along the long axis
    assert abs(axes[:, 1] @ rotation[:, 1]) > 0.99
    assert abs(axes[:, 2] @ rotation[:, 2]) > 0.99
    assert np.allclose(axes.T @ axes, np.eye(3), atol=1e-12)
    assert np.linalg.det(axes) == pytest.approx(1.0)
    extents = frame.principal_extents
    assert extents[0] > extents[1] > extents[2] > 0
    # the spread of the cells the points fall in (the map weighs cells, not points)
    cells = np.unique(np.floor(points / RES), axis=0)
    along = ((cells + 0.5) * RES) @ rotation[:, 0]
    assert extents[0] == pytest.approx(along.std(), rel=0.05)


def test_object_frame_weights_by_probability_and_is_none_when_nothing_is_occupied():
    centres = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.5, 0.5, 0.5]])
    p = np.array([0.9, 0.85, 0.6])
    frame = object_frame(centres, p, 0.8)
    assert frame.cells == 2 and frame.mass == pytest.approx(1.75)
    assert frame.centre_of_mass == pytest.approx([0.85 * 0.01 / 1.75, 0.0, 0.0])
    assert object_frame(centres, p, 0.95) is None
    assert object_frame(np.empty((0, 3)), np.empty(0), 0.8) is None
    grid = OccupancyGrid()
    grid.integrate(centre_of(3, 3, 3)[None])               # one stray point: p = 0.69
    assert object_frame(*grid.cells()[:2], 0.8) is None


# ============================================================================ entropy

def test_cell_entropy():
    assert cell_entropy(0.5) == pytest.approx(1.0, abs=1e-15)
    assert cell_entropy(0.0) == 0.0 and cell_entropy(1.0) == 0.0
    p = np.linspace(0.0, 1.0, 101)
    assert np.allclose(cell_entropy(p), cell_entropy(1.0 - p), atol=1e-15)
    assert np.all(cell_entropy(p) <= 1.0) and np.all(cell_entropy(p) >= 0.0)
    hand = -(0.2 * math.log2(0.2) + 0.8 * math.log2(0.8))
    assert cell_entropy(0.2) == pytest.approx(hand, abs=1e-15)
    assert map_entropy([0.5, 0.2, 1.0, 0.5]) == pytest.approx(2.0 + hand, abs=1e-12)


def test_eq10_entropy_is_the_literal_formula():
    p = [0.5, 0.25, 1.0, 0.0, 0.9]
    hand = -(0.5 * math.log2(0.5) + 0.25 * math.log2(0.25) + 0.9 * math.log2(0.9))
    assert eq10_entropy(p) == pytest.approx(hand, abs=1e-12)
    assert eq10_entropy([0.5, 0.25]) == pytest.approx(1.0, abs=1e-15)


def test_entropy_weights():
    confident = np.array([0.97, 0.03, 0.95, 0.5])
    unsure = np.array([0.6, 0.45, 0.5, 0.5])
    h = [map_entropy(confident), map_entropy(unsure)]
    w = entropy_weights(h)
    assert w.sum() == pytest.approx(1.0, abs=1e-15)
    assert w[0] > w[1]
    assert w[0] == pytest.approx(1 - h[0] / (h[0] + h[1]), abs=1e-15)   # eq. 11
    assert np.allclose(entropy_weights([3.0, 3.0]), [0.5, 0.5])
    assert np.allclose(entropy_weights([0.0, 0.0]), [0.5, 0.5])
    w3 = entropy_weights([1.0, 2.0, 3.0])
    assert w3.sum() == pytest.approx(1.0) and w3[0] > w3[1] > w3[2]
    assert np.allclose(w3, np.array([5, 4, 3]) / 12)    # (1 - h/6) normalised


# ============================================================================ map files

def example_grid(neighbourhood=27):
    spec = GridSpec(size=0.06, resolution=0.004, centre=(0.01, 0.0, -0.02))
    model = SensorModel(sigma=0.003, p_z_given_not_occupied=0.4, neighbourhood=neighbourhood)
    grid = OccupancyGrid(spec, model)
    rng = np.random.default_rng(8)
    for k in range(3):
        points = np.asarray(spec.centre) + rng.normal(0, 0.012, size=(500, 3))
        grid.integrate(points, np.linspace(k, k + 0.9, 500))
    grid.integrate(np.array([[np.nan, 0, 0], [1.0, 1.0, 1.0]]))
    return grid


def test_npz_round_trip_and_the_loaded_map_keeps_integrating_identically(tmp_path):
    grid = example_grid()
    path = map_io.save_npz(grid, tmp_path / 'maps' / 'map.npz', frame_id='object',
                           extra={'bag': 'run3.mcap'})
    assert path.exists() and [p.name for p in path.parent.iterdir()] == ['map.npz']
    loaded, metadata = map_io.load_npz(path)
    assert loaded.spec == grid.spec and loaded.model == grid.model
    assert loaded.counts == grid.counts and grid.counts.invalid == 1
    for name in ('log_odds', 'hits', 'first_touch', 'contact_sum'):
        a, b = getattr(grid, name), getattr(loaded, name)
        assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), name
    assert grid.contact_sum.any()
    assert metadata['frame_id'] == 'object' and metadata['extra'] == {'bag': 'run3.mcap'}
    assert metadata['format_version'] == map_io.FORMAT_VERSION
    # A loaded map starts new visits: later data (past the visit gap) lands identically.
    more = np.asarray(grid.spec.centre) + np.random.default_rng(9).normal(0, 0.01, (700, 3))
    for g in (grid, loaded):
        g.integrate(more, np.linspace(10.0, 12.0, 700))
    assert same_grid(grid, loaded)


def test_a_version_1_map_loads_with_the_model_it_was_built_with(tmp_path):
    path = map_io.save_npz(example_grid(), tmp_path / 'old.npz')
    with np.load(path) as data:
        arrays = dict(data)
    meta = json.loads(bytes(arrays['metadata']).decode())
    for name in ('distance_to', 'evidence_rate', 'visit_gap'):
        del meta[name]
    meta['format_version'] = 1
    arrays['metadata'] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(path, **arrays)
    loaded, metadata = map_io.load_npz(path)
    assert (loaded.model.distance_to, loaded.model.evidence_rate, loaded.model.visit_gap) == \
        ('centre', 0.0, 0.0)
    assert loaded.model.sigma == 0.003 and np.array_equal(loaded.log_odds, example_grid().log_odds)


def test_loading_a_non_map_file_raises_value_error_naming_it(tmp_path):
    cases = {}
    cases['text.npz'] = b'this is not a map\n' * 10
    np.savez(tmp_path / 'other.npz', a=np.zeros(3))
    future = tmp_path / 'future.npz'
    map_io.save_npz(example_grid(), future)
    with np.load(future) as data:
        arrays = dict(data)
    meta = json.loads(bytes(arrays['metadata']).decode())
    meta['format_version'] = 99
    arrays['metadata'] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(future, **arrays)
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
    for name in ('text.npz', 'other.npz', 'future.npz', 'missing.npz'):
        with pytest.raises(ValueError) as error:
            map_io.load_npz(tmp_path / name)
        assert str(tmp_path / name) in str(error.value)


@pytest.mark.parametrize('kind', ['empty', 'corrupt zip', 'npy'])
def test_loading_other_non_map_files_raises_value_error(tmp_path, kind):
    path = tmp_path / 'bad.npz'
    if kind == 'empty':
        path.write_bytes(b'')
    elif kind == 'corrupt zip':
        path.write_bytes(b'PK\x03\x04' + b'\x00' * 40)
    else:
        with open(path, 'wb') as stream:
            np.save(stream, np.zeros(3))
    with pytest.raises(ValueError, match=str(path)):
        map_io.load_npz(path)


def test_ply_round_trip_with_read_ply_and_plyfile(tmp_path):
    grid = example_grid()
    centres, p, hits, first = grid.cells()
    assert np.isnan(first).any() and (hits == 0).any()   # neighbours: touched, never hit
    path = map_io.save_ply(tmp_path / 'map.ply', centres, p, hits, first, frame_id='object')
    vertices = map_io.read_ply(path)
    assert vertices.dtype.names == ('x', 'y', 'z', 'intensity', 'hits', 'first_touch')
    assert len(vertices) == len(p)
    for axis, name in enumerate('xyz'):
        assert np.array_equal(vertices[name], centres[:, axis].astype(np.float32))
    assert np.array_equal(vertices['intensity'], p.astype(np.float32))
    assert np.array_equal(vertices['hits'], hits)
    assert np.array_equal(vertices['first_touch'], first, equal_nan=True)
    # a third-party reader sees the same
    ply = PlyData.read(str(path))
    assert ply.text is False and ply.byte_order == '<'
    assert any('frame_id object' in c for c in ply.comments)
    element = ply['vertex']
    assert [prop.name for prop in element.properties] == list(vertices.dtype.names)
    assert element.count == len(p)
    for name in vertices.dtype.names:
        assert np.array_equal(element[name], vertices[name], equal_nan=True), name
    assert element['hits'].dtype == np.uint32 and element['x'].dtype == np.float32
    assert [p.name for p in tmp_path.iterdir()] == ['map.ply']


def test_ply_of_an_empty_map(tmp_path):
    path = map_io.save_ply(tmp_path / 'empty.ply', np.empty((0, 3)), [], [], [])
    assert len(map_io.read_ply(path)) == 0
    assert PlyData.read(str(path))['vertex'].count == 0


class Unpicklable:
    def __reduce__(self):
        raise pickle.PicklingError('cannot serialize this')


def test_atomic_write_leaves_no_partial_map_nor_temp_file(tmp_path):
    grid = example_grid()
    target = tmp_path / 'map.npz'
    # a map that fails to serialize half way: log_odds and hits are written, then this fails
    grid.first_touch = np.array([Unpicklable()], dtype=object)
    with pytest.raises(pickle.PicklingError):
        map_io.save_npz(grid, target)
    assert list(tmp_path.iterdir()) == []
    # an existing map is left exactly as it was
    good = example_grid()
    map_io.save_npz(good, target)
    before = target.read_bytes()
    with pytest.raises(pickle.PicklingError):
        map_io.save_npz(grid, target)
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ['map.npz']
    # failing at the rename (the target is a folder) leaves no temp file either
    folder = tmp_path / 'taken.ply'
    folder.mkdir()
    (folder / 'keep').write_text('x')
    with pytest.raises(OSError):
        map_io.save_ply(folder, np.zeros((1, 3)), [0.9], [1], [0.0])
    assert sorted(p.name for p in tmp_path.iterdir()) == ['map.npz', 'taken.ply']
    assert [p.name for p in folder.iterdir()] == ['keep']
    assert not any(name.endswith('.tmp') for name in os.listdir(tmp_path))


# ============================================================================ PointCloud2

CLOUD_DTYPE = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4'),
                        ('hits', '<u4'), ('first_touch', '<f8')])


def cloud_array(count=257, dtype=CLOUD_DTYPE, seed=0):
    rng = np.random.default_rng(seed)
    points = np.zeros(count, dtype=dtype)
    for name in dtype.names:
        if dtype[name].kind == 'u':
            points[name] = rng.integers(0, 2 ** 32 - 1, count, dtype=np.uint64)
        else:
            points[name] = rng.normal(0, 0.1, count)
    if count:
        points['first_touch'][0] = np.nan
    return points


def test_point_cloud2_fields_and_layout_are_what_sensor_msgs_expects():
    points = cloud_array()
    msg = to_point_cloud2(points, 'object', Time(sec=12, nanosec=345))
    assert isinstance(msg, PointCloud2)
    assert msg.header.frame_id == 'object'
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (12, 345)
    layout = [(f.name, f.offset, f.datatype, f.count) for f in msg.fields]
    assert layout == [('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 7, 1), ('intensity', 12, 7, 1),
                      ('hits', 16, 6, 1), ('first_touch', 20, 8, 1)]
    assert (PointField.FLOAT32, PointField.UINT32, PointField.FLOAT64) == (7, 6, 8)
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, 257, 28, 28 * 257)
    assert msg.is_bigendian is False and msg.is_dense is True
    assert len(msg.data) == 28 * 257 and bytes(msg.data) == points.tobytes()


def test_point_cloud2_round_trip_directly_and_through_cdr():
    points = cloud_array()
    msg = to_point_cloud2(points, 'object', Time(sec=1, nanosec=2))
    back = from_point_cloud2(msg)
    assert back.dtype.names == points.dtype.names
    for name in points.dtype.names:
        assert np.array_equal(back[name], points[name], equal_nan=True), name
    raw = serialize_message(msg)
    received = deserialize_message(raw, PointCloud2)
    assert [(f.name, f.offset, f.datatype) for f in received.fields] == \
        [(f.name, f.offset, f.datatype) for f in msg.fields]
    again = from_point_cloud2(received)
    assert again.tobytes() == points.tobytes()


def test_point_cloud2_with_padding_and_no_points():
    padded = np.dtype({'names': ['x', 'hits', 'first_touch'],
                       'formats': ['<f4', '<u4', '<f8'], 'offsets': [0, 8, 16], 'itemsize': 32})
    points = cloud_array(dtype=padded, count=10)
    msg = to_point_cloud2(points, 'object', Time())
    assert [(f.name, f.offset) for f in msg.fields] == [('x', 0), ('hits', 8),
                                                        ('first_touch', 16)]
    assert msg.point_step == 32
    back = from_point_cloud2(deserialize_message(serialize_message(msg), PointCloud2))
    for name in padded.names:
        assert np.array_equal(back[name], points[name], equal_nan=True), name
    empty = to_point_cloud2(cloud_array(count=0), 'object', Time())
    assert empty.width == 0 and len(from_point_cloud2(empty)) == 0
    with pytest.raises(TypeError):
        to_point_cloud2(np.zeros((4, 3), dtype=np.float32), 'object', Time())
    big = to_point_cloud2(points, 'object', Time())   # a big-endian writer's cloud
    big.is_bigendian = True
    big.data = points.astype(padded.newbyteorder('>')).tobytes()
    back = from_point_cloud2(big)
    assert back.dtype.isnative
    for name in padded.names:
        assert np.array_equal(back[name], points[name], equal_nan=True), name


def test_point_cloud2_from_a_big_endian_array_keeps_its_values():
    points = np.zeros(3, dtype=[('x', '>f4'), ('hits', '>u4')])
    points['x'] = [1.5, -2.25, 3.0]
    points['hits'] = [1, 2, 3]
    back = from_point_cloud2(to_point_cloud2(points, 'object', Time()))
    assert np.array_equal(back['x'], points['x']) and np.array_equal(back['hits'], [1, 2, 3])


def test_pack_rgb_gives_float32_holding_0x00rrggbb():
    one = pack_rgb(255, 128, 1)
    assert one.dtype == np.float32
    assert int(np.asarray(one).view(np.uint32)) == 0x00FF8001
    many = pack_rgb([0, 255, 0x12, 255], [0, 0, 0x34, 255], [0, 255, 0x56, 255])
    assert many.dtype == np.float32
    assert list(many.view(np.uint32)) == [0x000000, 0xFF00FF, 0x123456, 0xFFFFFF]
    # and the bits survive a cloud's trip through CDR
    points = np.zeros(4, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('rgb', '<f4')])
    points['rgb'] = many
    raw = serialize_message(to_point_cloud2(points, 'object', Time()))
    back = from_point_cloud2(deserialize_message(raw, PointCloud2))
    assert list(back['rgb'].view(np.uint32)) == [0x000000, 0xFF00FF, 0x123456, 0xFFFFFF]
    assert [f.datatype for f in to_point_cloud2(points, 'object', Time()).fields] == [7] * 4


# ============================================================================ colour (texture)

OLD_PLY_HEADER = [
    'ply', 'format binary_little_endian 1.0', 'comment frame_id object',
    'comment intensity = occupancy probability; first_touch in seconds (nan = none)',
    'element vertex {count}', 'property float x', 'property float y', 'property float z',
    'property float intensity', 'property uint hits', 'property double first_touch',
    'end_header']


def painted(count, seed=4):
    """Colours (count, 3) uint8 and a textured mask with both values; colours are given
    (non-zero) even where not textured, which the writers must store as 0."""
    rng = np.random.default_rng(seed)
    colours = rng.integers(1, 256, (count, 3), dtype=np.uint8)
    textured = rng.random(count) < 0.6
    textured[:2] = [True, False]
    return colours, textured


def split_ply(path):
    data = path.read_bytes()
    end = data.index(b'end_header\n') + len(b'end_header\n')
    return data[:end].decode('ascii').splitlines(), data[end:]


def test_ply_with_colours_has_uchar_red_green_blue_and_textured(tmp_path):
    grid = example_grid()
    centres, p, hits, first = grid.cells()
    colours, textured = painted(len(p))
    path = map_io.save_ply(tmp_path / 'map.ply', centres, p, hits, first, frame_id='object',
                           colours=colours, textured=textured)
    ply = PlyData.read(str(path))
    element = ply['vertex']
    assert [prop.name for prop in element.properties] == \
        ['x', 'y', 'z', 'intensity', 'hits', 'first_touch', 'red', 'green', 'blue', 'textured']
    for name in ('red', 'green', 'blue', 'textured'):
        assert element[name].dtype == np.uint8, name
    expected = np.where(textured[:, None], colours, 0)
    assert np.array_equal(np.stack([element['red'], element['green'], element['blue']], 1),
                          expected)
    assert np.array_equal(element['textured'], textured.astype(np.uint8))
    # the other fields are untouched
    assert np.array_equal(element['x'], centres[:, 0].astype(np.float32))
    assert np.array_equal(element['first_touch'], first, equal_nan=True)
    assert np.array_equal(element['hits'], hits)
    # and our own reader sees the same
    vertices = map_io.read_ply(path)
    assert np.array_equal(vertices['textured'], element['textured'])
    assert np.array_equal(vertices['red'], element['red'])
    header, _ = split_ply(path)
    assert header[:4] == OLD_PLY_HEADER[:4] and any(line.startswith('comment red green blue')
                                                     for line in header)


def test_a_ply_without_colours_is_byte_for_byte_what_it_always_was(tmp_path):
    grid = example_grid()
    centres, p, hits, first = grid.cells()
    path = map_io.save_ply(tmp_path / 'map.ply', centres, p, hits, first)
    header, body = split_ply(path)
    assert header == [line.format(count=len(p)) for line in OLD_PLY_HEADER]
    old = np.empty(len(p), dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                                  ('intensity', '<f4'), ('hits', '<u4'),
                                  ('first_touch', '<f8')])
    old['x'], old['y'], old['z'] = centres.T
    old['intensity'], old['hits'], old['first_touch'] = p, hits, first
    assert body == old.tobytes()


# The last commit whose map writer knew no colours.
WRITER_BEFORE_COLOURS = '698a06350101ff6578184fe3376a90d4870a0cab'


def map_io_before_colours():
    """map_io as it was before colours (WRITER_BEFORE_COLOURS), or None without git."""
    try:
        source = subprocess.run(
            ['git', 'show', f'{WRITER_BEFORE_COLOURS}:src/inhand_mapping/inhand_mapping/map_io.py'],
            cwd=os.path.dirname(__file__), capture_output=True, text=True, timeout=30,
            check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    module = types.ModuleType('map_io_before_colours')
    sys.modules[module.__name__] = module     # dataclasses look their module up there
    try:
        exec(compile(source, 'map_io_before_colours.py', 'exec'), module.__dict__)
    finally:
        del sys.modules[module.__name__]
    return module


def test_maps_without_colour_match_the_writer_before_colours_and_its_files_still_load(tmp_path):
    old = map_io_before_colours()
    if old is None:
        pytest.skip('git or the repository history is not available')
    grid = example_grid()
    centres, p, hits, first = grid.cells(threshold=0.6)
    old.save_ply(tmp_path / 'old.ply', centres, p, hits, first)
    map_io.save_ply(tmp_path / 'new.ply', centres, p, hits, first)
    assert (tmp_path / 'old.ply').read_bytes() == (tmp_path / 'new.ply').read_bytes()
    # NPZ (zip entries carry a time stamp, so the same arrays and metadata, not bytes)
    old.save_npz(grid, tmp_path / 'old.npz', extra={'a': 1})
    map_io.save_npz(grid, tmp_path / 'new.npz', extra={'a': 1})
    with np.load(tmp_path / 'old.npz') as a, np.load(tmp_path / 'new.npz') as b:
        assert a.files == [name for name in b.files if name != 'contact_sum']   # added since
        for name in a.files:
            assert a[name].dtype == b[name].dtype
            assert np.array_equal(a[name], b[name], equal_nan=True), name
    # a file of the old writer loads, without colours
    loaded, metadata = map_io.load_npz(tmp_path / 'old.npz')
    assert same_grid(loaded, grid, contact_sum=False) and metadata['extra'] == {'a': 1}
    # its hits count at their cells' centres
    assert np.allclose(loaded.contact_centroids(), loaded.cells()[0], rtol=0, atol=1e-12)
    assert map_io.load_colours(tmp_path / 'old.npz') is None
    # and a coloured map still loads in the old reader (it ignores the colour arrays)
    colours, textured = painted(len(p))
    map_io.save_npz(grid, tmp_path / 'coloured.npz',
                    colours=map_io.GridColours.from_cells(grid.spec, centres, colours, textured))
    again, _ = old.load_npz(tmp_path / 'coloured.npz')
    assert same_grid(again, grid, contact_sum=False)


def test_npz_round_trip_of_the_colours(tmp_path):
    grid = example_grid()
    centres, p, _, _ = grid.cells(threshold=0.6)
    colours, textured = painted(len(p))
    cell_colours = map_io.GridColours.from_cells(grid.spec, centres, colours, textured)
    assert cell_colours.rgb.shape == (*grid.spec.shape, 3) and cell_colours.rgb.dtype == np.uint8
    assert cell_colours.textured.sum() == textured.sum()
    path = map_io.save_npz(grid, tmp_path / 'map.npz', colours=cell_colours)
    with np.load(path) as data:
        assert sorted(data.files) == ['contact_sum', 'first_touch', 'hits', 'log_odds', 'metadata',
                                      'rgb', 'textured']
    loaded = map_io.load_colours(path)
    assert loaded is not None
    assert np.array_equal(loaded.rgb, cell_colours.rgb)
    assert np.array_equal(loaded.textured, cell_colours.textured)
    back, mask = loaded.at(grid.spec, centres)
    assert np.array_equal(mask, textured)
    assert np.array_equal(back, np.where(textured[:, None], colours, 0))
    # the grid itself is unchanged by the colours, and the format version is the same
    grid_back, metadata = map_io.load_npz(path)
    assert same_grid(grid_back, grid) and metadata['format_version'] == 2
    # cells never textured (outside the given ones) read as untextured
    _, others = loaded.at(grid.spec, grid.cells()[0])
    assert others.sum() == textured.sum()


def test_colours_of_the_wrong_size_or_alone_are_refused(tmp_path):
    grid = example_grid()
    centres, p, hits, first = grid.cells(threshold=0.6)
    colours, textured = painted(len(p))
    with pytest.raises(ValueError, match='together'):
        map_io.save_ply(tmp_path / 'a.ply', centres, p, hits, first, colours=colours)
    with pytest.raises(ValueError, match='colours must be'):
        map_io.save_ply(tmp_path / 'a.ply', centres, p, hits, first, colours=colours[1:],
                        textured=textured[1:])
    with pytest.raises(ValueError):
        map_io.GridColours.from_cells(grid.spec, centres + 1.0, colours, textured)
    with pytest.raises(ValueError, match='together'):
        save_map(grid, tmp_path, 'map', 0.6, textured=textured)
    with pytest.raises(ValueError, match='colours must be'):
        save_map(grid, tmp_path, 'map', 0.6, colours=colours[1:], textured=textured[1:])
    small = OccupancyGrid(GridSpec(size=0.04, resolution=0.004))
    with pytest.raises(ValueError, match='grid'):
        map_io.save_npz(small, tmp_path / 'b.npz',
                        colours=map_io.GridColours.from_cells(grid.spec, centres, colours,
                                                              textured))
    assert list(tmp_path.iterdir()) == []


def test_save_map_passes_the_colours_to_every_file(tmp_path):
    grid = example_grid()
    threshold = 0.6
    centres, p, hits, first = grid.cells(threshold=threshold)
    colours, textured = painted(len(p))
    plain = save_map(grid, tmp_path / 'plain', 'map', threshold)
    coloured = save_map(grid, tmp_path / 'coloured', 'map', threshold, colours=colours,
                        textured=textured)
    assert [path.name for path in coloured] == [path.name for path in plain] == \
        ['map.npz', 'map.ply', 'map_object_centric.ply']
    expected = np.where(textured[:, None], colours, 0)
    for path in coloured[1:]:
        element = PlyData.read(str(path))['vertex']
        assert np.array_equal(np.stack([element['red'], element['green'], element['blue']], 1),
                              expected)
        assert np.array_equal(element['textured'], textured)
    # the same cells in the same order as the PLY without colours
    for old, new in zip(plain[1:], coloured[1:]):
        a, b = map_io.read_ply(old), map_io.read_ply(new)
        for name in a.dtype.names:
            assert np.array_equal(a[name], b[name], equal_nan=True), name
    # without colours the PLYs are the bare save_ply output (no colour fields)
    map_io.save_ply(tmp_path / 'bare.ply', centres, p, hits, first)
    assert plain[1].read_bytes() == (tmp_path / 'bare.ply').read_bytes()
    loaded = map_io.load_colours(coloured[0])
    assert loaded is not None and np.array_equal(loaded.at(grid.spec, centres)[0], expected)
    assert map_io.load_colours(plain[0]) is None


def test_textured_cloud_layout_packs_rgb_as_pcl_does():
    grid = example_grid()
    _, occupied = MapProducts(grid, 0.6).cells()
    colours, textured = painted(len(occupied))
    points = textured_cells(occupied, colours, textured)
    assert points.dtype == TEXTURED_CELL_DTYPE and points.dtype.itemsize == 24
    assert [(name, points.dtype.fields[name][1]) for name in points.dtype.names] == \
        [('x', 0), ('y', 4), ('z', 8), ('intensity', 12), ('rgb', 16), ('textured', 20)]
    for name in ('x', 'y', 'z', 'intensity'):
        assert np.array_equal(points[name], occupied[name]), name
    expected = pack_rgb(colours[:, 0], colours[:, 1], colours[:, 2]).view(np.uint32)
    bits = points['rgb'].view(np.uint32)
    assert np.array_equal(bits[textured], expected[textured])
    assert not bits[~textured].any()
    assert np.array_equal(points['textured'], textured.astype(np.uint8))
    # in a PointCloud2: FLOAT32 rgb and UINT8 textured, the bits survive CDR
    msg = to_point_cloud2(points, 'object', Time())
    assert [(f.name, f.offset, f.datatype) for f in msg.fields] == \
        [('x', 0, 7), ('y', 4, 7), ('z', 8, 7), ('intensity', 12, 7), ('rgb', 16, 7),
         ('textured', 20, 2)]
    assert msg.point_step == 24
    back = from_point_cloud2(deserialize_message(serialize_message(msg), PointCloud2))
    assert back.tobytes() == points.tobytes()
    # the occupied cells as the saved PLY lists them: the same order
    centres, _, _, _ = grid.cells(threshold=0.6)
    assert np.array_equal(np.stack([points['x'], points['y'], points['z']], 1),
                          centres.astype(np.float32))
    # no cells, and sizes that do not match
    empty = textured_cells(np.zeros(0, MAP_CELL_DTYPE), np.zeros((0, 3), np.uint8), [])
    assert empty.shape == (0,) and empty.dtype == TEXTURED_CELL_DTYPE
    with pytest.raises(ValueError):
        textured_cells(occupied, colours[1:], textured)


SAVE_UNDER_A_FILE_SIZE_LIMIT = r'''
import resource, signal, sys
import numpy as np
from inhand_mapping.map_products import save_map
from inhand_mapping.occupancy import GridSpec, OccupancyGrid, SensorModel
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)     # past the limit: EFBIG, as a full disk
limit = int(sys.argv[2])
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
grid = OccupancyGrid(GridSpec(0.1, 0.002), SensorModel(touch_model='samples'))
points = np.random.default_rng(5).uniform(-0.04, 0.04, (20000, 3))
for _ in range(3):
    grid.integrate(points)
try:
    save_map(grid, sys.argv[1], 'map', 0.8)
except OSError as error:
    print('refused:', error)
'''


def _map_files(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_a_map_save_replaces_the_whole_set_or_changes_nothing(tmp_path):
    """On a full disk the save used to fail with the new NPZ beside the old PLYs, and a map
    without occupied cells left a stale _object_centric.ply. The three files are one set."""
    from inhand_mapping.map_products import save_map
    folder = tmp_path / 'maps'
    old = OccupancyGrid(GridSpec(0.1, 0.002), SensorModel(touch_model='samples'))
    for _ in range(3):
        old.integrate(np.array([[0.001, 0.001, 0.001], [0.011, 0.001, 0.001]]))
    save_map(old, folder, 'map', 0.8)
    before = _map_files(folder)
    assert set(before) == {'map.npz', 'map.ply', 'map_object_centric.ply'}
    # How big the new set is, written where nothing limits it.
    probe = tmp_path / 'probe'
    subprocess.run([sys.executable, '-c', SAVE_UNDER_A_FILE_SIZE_LIMIT, str(probe), str(2**40)],
                   check=True)
    sizes = {p.name: p.stat().st_size for p in probe.iterdir()}
    assert sizes['map.ply'] > sizes['map.npz']   # so the NPZ is written, then the PLY fails
    result = subprocess.run([sys.executable, '-c', SAVE_UNDER_A_FILE_SIZE_LIMIT, str(folder),
                             str(sizes['map.npz'] + 1)], capture_output=True, text=True,
                            check=True)
    assert 'refused:' in result.stdout, result.stdout + result.stderr
    assert _map_files(folder) == before       # nothing changed, no temporary file left
    # A map with no occupied cells: the set has no object-centric PLY any more.
    save_map(OccupancyGrid(GridSpec(0.1, 0.002)), folder, 'map', 0.8)
    assert set(_map_files(folder)) == {'map.npz', 'map.ply'}


WARM_UP_CHECK = '''
import sys, numba, numpy as np
from inhand_mapping import cell_judge, occupancy_kernels, path_kernels, surface_layer
from inhand_mapping.occupancy import GridSpec, OccupancyGrid, SensorModel, warm_up

def loaded():
    return {(module.__name__, name, sig)
            for module in (occupancy_kernels, path_kernels, surface_layer, cell_judge)
            for name, f in vars(module).items()
            if isinstance(f, numba.core.registry.CPUDispatcher) for sig in f.signatures}

model = SensorModel(touch_model=sys.argv[1])
assert not loaded(), 'kernels loaded before the warm-up'
warm_up(model, 0.005)
after_warm_up = loaded()
grid = OccupancyGrid(GridSpec(0.35, 0.005), model)   # a real grid and a real stroke
rng = np.random.default_rng(1)
points = np.cumsum(rng.normal(0, 0.0005, (480, 3)), axis=0)
grid.integrate(points, 100.0 + np.arange(480) / 240.0, np.arange(480) % 4)
grid.held_points()
grid.probabilities()                                  # the map read: the layer, the judge
grid.integrate(points[:240] + 0.001, 103.0 + np.arange(240) / 240.0, np.arange(240) % 4)
grid.probabilities()                                  # and read again, around what changed
grid.integrate(points[:3])                            # untimed points
grid.flush()
grid.probabilities()
print(len(after_warm_up), sorted(loaded() - after_warm_up))
'''


@pytest.mark.parametrize('touch_model', ['path', 'samples'])
def test_warm_up_loads_every_kernel_a_session_calls(touch_model):
    """occupancy_node calls warm_up at start so that the first touch does not wait for numba
    (0.35-0.56 s): a session afterwards must need no kernel the warm-up did not load. A
    fresh interpreter, so that no other test loaded them first."""
    result = subprocess.run([sys.executable, '-c', WARM_UP_CHECK, touch_model],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    count, missing = result.stdout.split(' ', 1)
    assert int(count) > 0 and missing.strip() == '[]', result.stdout
