"""Map metrics against ground truth, the truth files, and the map pictures.

Metrics on hand-made cases whose values are worked out in the comments; ``map_metrics``
and ``render_map`` on maps that ``build_map`` made from sphere bags, with synthetic truth
files written here (no simulator needed).
"""

from __future__ import annotations

import json
import math
import subprocess

import cv2
import numpy as np
import pytest

from inhand_common.ground_truth import (
    CONTACT_TRUTH_EXPLORED,
    TRUTH_KEYS,
    GroundTruth,
    default_frame,
    in_frame,
    load_truth,
    truth_path,
    write_truth,
)
from inhand_mapping.map_io import save_ply
from inhand_tools import drawing as render
from inhand_tools.commands.map_metrics import main as map_metrics_main
from inhand_tools.commands.render_map import main as render_map_main
from inhand_tools.map_cells import Lattice, MapCells, cell_indices, infer_lattice, load_map
from inhand_tools.map_figures import default_up, draw_all, map_view_box, raw_view_box, regions
from inhand_tools.map_quality import (
    SurfaceTruth,
    explored_mask,
    map_metrics,
    point_metrics,
    touch_coverage,
)
from pose_sessions import (
    fingertip_on_sphere,
    sphere_session,
    sphere_surface_points,
    spot_tour,
    write_pose_bag,
)
from ros_helpers import WORKSPACE, executable_path

CONFIG = WORKSPACE / 'config' / 'mapping.yaml'
STATIC_CONFIG = WORKSPACE / 'config' / 'mapping_static.yaml'
H = 0.005  # cell edge of every hand-made case
RADIUS = 0.04


def fibonacci_sphere(count: int, radius: float, centre=(0.0, 0.0, 0.0)):
    """Deterministic samples uniform by area on a sphere, and their normals."""
    i = np.arange(count) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / count)
    azimuth = math.pi * (1.0 + math.sqrt(5.0)) * i
    normals = np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar),
                        np.cos(polar)], axis=1)
    return radius * normals + np.asarray(centre), normals


def voxel_centres(points, lattice: Lattice) -> np.ndarray:
    cells = np.unique(cell_indices(points, lattice), axis=0)
    return np.asarray(lattice.origin) + (cells + 0.5) * lattice.resolution


@pytest.fixture(scope='module')
def sphere_truth():
    points, normals = fibonacci_sphere(200_000, RADIUS)
    # Explored everywhere: contacts all over the sphere.
    return SurfaceTruth(points, points[::40], normals, explored_radius=0.005)


@pytest.fixture(scope='module')
def perfect_sphere_map():
    """Cells holding the sphere's surface, found from other samples than the truth's."""
    other, _ = fibonacci_sphere(333_333, RADIUS)
    return voxel_centres(other, Lattice(H))


# ------------------------------------------------------------------ metrics by hand

def test_perfect_sphere_map_scores_one(sphere_truth, perfect_sphere_map):
    scores = map_metrics(perfect_sphere_map, np.full(len(perfect_sphere_map), 0.9), Lattice(H),
                         sphere_truth)
    assert scores['occupied_cells'] == len(perfect_sphere_map) > 1000
    for key in ('precision_at_5mm', 'recall_at_5mm', 'fscore_at_5mm', 'cell_precision',
                'cell_recall', 'cell_fscore'):
        assert scores[key] >= 0.999, (key, scores[key])
    assert scores['iou'] >= 0.95
    # A cell centre is at most half a diagonal (4.3 mm) from the surface it holds; on
    # average much less: under half a cell.
    assert scores['chamfer_mm'] < H * 1000 / 2
    assert scores['com_error_mm'] < 0.05  # the voxelisation is symmetric about the centre
    assert abs(scores['normal_offset_mm']) < 0.3
    assert scores['stray_cells'] == scores['off_surface_cells'] == 0
    assert 0.1 < scores['sample_spacing_mm'] < 0.5


def test_centre_of_mass_error_of_a_shifted_map_is_the_shift(sphere_truth, perfect_sphere_map):
    shift = np.array([0.003, -0.004, 0.0012])
    scores = map_metrics(perfect_sphere_map + shift, np.full(len(perfect_sphere_map), 0.95),
                         Lattice(H), sphere_truth)
    assert scores['com_error_mm'] == pytest.approx(np.linalg.norm(shift) * 1000, abs=0.05)
    assert np.allclose(np.subtract(scores['com_map'], scores['com_truth']), shift, atol=5e-5)


def test_centre_of_mass_is_weighted_by_probability(sphere_truth):
    # Two cells on the surface at +-x; weights 0.9 and 0.81: CoM at x = R (0.9 - 0.81) / 1.71.
    centres = np.array([[RADIUS, 0.0, 0.0], [-RADIUS, 0.0, 0.0]])
    scores = map_metrics(centres, [0.9, 0.81], Lattice(H), sphere_truth)
    assert scores['com_map'][0] == pytest.approx(RADIUS * 0.09 / 1.71)
    assert scores['com_error_mm'] == pytest.approx(RADIUS * 0.09 / 1.71 * 1000, abs=0.01)


def plane_case():
    """20 lines of samples on the plane z = 2.5 mm (the cell-centre plane of the cell layer
    k = 0), at y = 2.5 + 5 j mm, x = 0.05 + 0.1 i mm (1,000 per line, x in [0, 100) mm); all
    explored. The perfect map: the 20 x 20 cells of that layer."""
    x = (np.arange(1000) + 0.5) * 1e-4
    y = 0.0025 + H * np.arange(20)
    xx, yy = np.meshgrid(x, y, indexing='ij')
    surface = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, 0.0025)], axis=1)
    normals = np.tile([0.0, 0.0, 1.0], (len(surface), 1))
    ci, cj = np.meshgrid(np.arange(20), np.arange(20), indexing='ij')
    centres = np.stack([(ci.ravel() + 0.5) * H, (cj.ravel() + 0.5) * H,
                        np.full(ci.size, 0.0025)], axis=1)
    return surface, normals, centres


def test_plane_map_shifted_by_one_centimetre_scores_as_computed_by_hand():
    surface, normals, centres = plane_case()
    truth = SurfaceTruth(surface, surface, normals, explored_radius=0.005)
    perfect = map_metrics(centres, np.full(len(centres), 0.9), Lattice(H), truth)
    assert perfect['fscore_at_5mm'] == 1.0 and perfect['iou'] == 1.0
    assert perfect['chamfer_mm'] < 1.3

    shifted = map_metrics(centres + [0.01, 0.0, 0.0], np.full(len(centres), 0.9), Lattice(H),
                          truth)
    # Centre columns now at x = 12.5 ... 107.5 mm. Precision @ 5 mm: the column at 102.5 mm
    # is 2.55 mm from the last sample (99.95 mm), the one at 107.5 mm is 7.55 mm away:
    # 19 of 20 columns.
    assert shifted['precision_at_5mm'] == pytest.approx(19 / 20)
    # Recall @ 5 mm: samples left of 7.5 mm are more than 5 mm from every centre (the
    # nearest is at 12.5 mm on the same line; other lines are 5 mm away sideways):
    # 75 of each 1,000.
    assert shifted['recall_at_5mm'] == pytest.approx(925 / 1000)
    assert shifted['fscore_at_5mm'] == pytest.approx(2 * 0.95 * 0.925 / (0.95 + 0.925))
    # Map -> surface: 18 columns 0.05 mm from the nearest sample (centres fall halfway
    # between samples), then 2.55 and 7.55 mm.
    assert shifted['map_to_surface_mm'] == pytest.approx((18 * 0.05 + 2.55 + 7.55) / 20)
    # Cells: occupied x-indices 2..21 against the surface's 0..19. IoU 18/22; with the
    # one-cell tolerance index 21 is wrong (precision 19/20) and index 0 is not recalled
    # (recall 19/20).
    assert shifted['iou'] == pytest.approx(18 / 22)
    assert shifted['cell_precision'] == pytest.approx(19 / 20)
    assert shifted['cell_recall'] == pytest.approx(19 / 20)
    assert shifted['com_error_mm'] == pytest.approx(10.0, abs=1e-6)
    assert shifted['normal_offset_mm'] == pytest.approx(0.0, abs=1e-9)
    lifted = map_metrics(centres + [0.0, 0.0, 0.003], np.full(len(centres), 0.9), Lattice(H),
                         truth)
    assert lifted['normal_offset_mm'] == pytest.approx(3.0)


def test_stray_cells_are_occupied_cells_holding_a_far_stray_and_no_surface():
    surface, normals, centres = plane_case()
    # The surface cells G are the layer k = 0, (0..19, 0..19, 0); the map occupies them all.
    strays = np.array([[0.0525, 0.0525, 0.0225],   # 20 mm above the plane: cell (10, 10, 4)
                       [0.0325, 0.0325, 0.0085],   # 6 mm above: cell (6, 6, 1), next to the
                                                   # occupied surface cells (5..7, 5..7, 0)
                       [0.0525, 0.0575, 0.0225],   # 20 mm above: cell (10, 11, 4)
                       [0.0725, 0.0725, 0.0055]])  # 3 mm above: not a stray for the metric
    truth = SurfaceTruth(surface, surface, normals, strays, explored_radius=0.005)
    extra = np.array([[10, 10, 4],   # holds the first far stray, no surface: counted
                      [11, 9, 5],    # a diagonal neighbour of its cell, holds neither: not
                                     # counted (but off the surface)
                      [10, 10, 6],   # two cells away: not counted (but off the surface)
                      [14, 14, 1],   # holds the near stray (3 mm off): not counted
                      [10, 11, 4],   # holds a far stray, below the threshold
                      [6, 6, 1]])    # holds the 6 mm stray, below the threshold
    cells = np.concatenate([centres, (extra + 0.5) * H])
    probabilities = np.concatenate([np.full(len(centres), 0.9),
                                    [0.97, 0.85, 0.9, 0.9, 0.7, 0.75]])
    scores = map_metrics(cells, probabilities, Lattice(H), truth, threshold=0.8)
    assert scores['strays'] == 4 and scores['strays_far_from_surface'] == 3
    # Only (10, 10, 4): the surface cells next to the 6 mm stray hold surface, and
    # (11, 9, 5) only touches a stray's cell (counting neighbours would give 11).
    assert scores['stray_cells'] == 1
    # Off the surface by more than a cell: the three cells above layer k = 1.
    assert scores['off_surface_cells'] == 3
    lower = map_metrics(cells, probabilities, Lattice(H), truth, threshold=0.6)
    # Now also (10, 11, 4) and (6, 6, 1), which hold far strays and no surface; (6, 6, 1)
    # is within a cell of the surface, so not off it.
    assert lower['stray_cells'] == 3
    assert lower['off_surface_cells'] == 4


def test_a_surface_cell_holding_a_far_stray_is_not_a_stray_cell():
    # Surface: a line of samples along x at y = z = 0.1 mm, in the cells (0..19, 0, 0).
    x = (np.arange(1000) + 0.5) * 1e-4
    surface = np.stack([x, np.full(x.size, 1e-4), np.full(x.size, 1e-4)], axis=1)
    strays = np.array([[0.0525, 0.0049, 0.0049],   # 6.8 mm off the line, in its cell (10, 0, 0)
                       [0.0725, 0.0075, 0.0075]])  # 10.5 mm off, in cell (14, 1, 1)
    truth = SurfaceTruth(surface, surface, None, strays, explored_radius=0.005)
    assert truth.distance(strays)[0].min() > 0.006
    cells = np.array([(i, 0, 0) for i in range(20)]
                     + [(14, 1, 1),    # holds the second stray, no surface: counted
                        (15, 1, 1)])   # next to it, holds neither: not counted
    scores = map_metrics((cells + 0.5) * H, np.full(len(cells), 0.9), Lattice(H), truth)
    assert scores['strays_far_from_surface'] == 2
    # The surface cell (10, 0, 0) holds a far stray but is right to be occupied; counting
    # the cells within one of a stray's cell would give 8.
    assert scores['stray_cells'] == 1
    assert scores['off_surface_cells'] == 0


def test_a_cell_the_surface_grazes_within_the_tracker_noise_is_not_a_stray_cell():
    """A far stray in the cell above a line of surface: the surface runs 0.5 mm below
    that cell (its noisy contacts fill it), or 1.5 mm below (more than the 1 mm margin)."""
    x = (np.arange(1000) + 0.5) * 1e-4
    for surface_z, margin, counted in [(0.0045, 0.001, 0), (0.0045, 0.0, 1),
                                       (0.0035, 0.001, 1)]:
        surface = np.stack([x, np.full(x.size, 0.0025), np.full(x.size, surface_z)], axis=1)
        stray = np.array([[0.0525, 0.0025, 0.0098]])          # cell (10, 0, 1)
        truth = SurfaceTruth(surface, surface, None, stray, explored_radius=0.005)
        assert truth.distance(stray)[0][0] > 0.005
        cells = np.array([(i, 0, 0) for i in range(20)] + [(10, 0, 1)])
        scores = map_metrics((cells + 0.5) * H, np.full(len(cells), 0.9), Lattice(H), truth,
                             surface_margin=margin)
        assert scores['stray_cells'] == counted, (surface_z, margin)


def test_a_perfect_map_has_no_stray_cells_with_strays_6_mm_off(perfect_sphere_map):
    # The simulator's off-surface samples start 6 mm from the surface: their neighbouring
    # cells are often surface cells, which a perfect map rightly occupies.
    points, normals = fibonacci_sphere(200_000, RADIUS)
    strays = (RADIUS + 0.006) * normals[::500]
    truth = SurfaceTruth(points, points[::40], normals, strays, explored_radius=0.005)
    lattice = Lattice(H)
    occupied = np.unique(cell_indices(perfect_sphere_map, lattice), axis=0)
    stray_cells = np.unique(cell_indices(strays, lattice), axis=0)
    chebyshev = np.abs(occupied[:, None, :] - stray_cells[None, :, :]).max(axis=2)
    assert np.count_nonzero(chebyshev.min(axis=1) <= 1) > 100  # the case the metric must pass
    scores = map_metrics(perfect_sphere_map, np.full(len(perfect_sphere_map), 0.9), lattice,
                         truth)
    assert scores['strays_far_from_surface'] == len(strays) == 400
    assert scores['stray_cells'] == 0 and scores['off_surface_cells'] == 0


def test_explored_part_and_its_cells():
    surface, normals, _ = plane_case()
    contact = np.array([[0.05, 0.0525, 0.0025]])
    mask = explored_mask(surface, contact, 0.005)
    # On the contact's line, x in [45, 55] mm: samples 45.05 ... 54.95 mm (100 of them); the
    # lines 5 mm to each side hold no sample at exactly x = 50 mm, so none of theirs.
    assert mask.sum() == 100
    assert np.array_equal(mask, np.linalg.norm(surface - contact, axis=1) <= 0.005)
    truth = SurfaceTruth(surface, contact, normals, explored_radius=0.005)
    # Those samples lie in cells x = 9 and 10; a map holding only the contact's cell
    # (x = 10) recalls both at the one-cell tolerance.
    scores = map_metrics([[0.0525, 0.0525, 0.0025]], [0.9], Lattice(H), truth)
    assert scores['explored_cells'] == 2 and scores['cell_recall'] == 1.0
    assert scores['iou'] == pytest.approx(1 / 2)
    assert explored_mask(surface, np.empty((0, 3)), 0.005).sum() == 0


def test_empty_map_scores_zero_or_undefined(sphere_truth):
    scores = map_metrics(np.empty((0, 3)), np.empty(0), Lattice(H), sphere_truth)
    assert scores['occupied_cells'] == 0 and scores['recall_at_5mm'] == 0.0
    assert math.isnan(scores['precision_at_5mm']) and math.isnan(scores['chamfer_mm'])
    with pytest.raises(ValueError):
        map_metrics(np.zeros((2, 3)), [0.9], Lattice(H), sphere_truth)


def test_registered_point_metrics(sphere_truth):
    rng = np.random.default_rng(2)
    on_surface = sphere_surface_points(900, RADIUS, seed=4)
    off = sphere_surface_points(100, RADIUS + 0.01, seed=5)  # 10 mm outside
    scores = point_metrics(np.concatenate([on_surface, off, [[np.nan, 0.0, 0.0]]]),
                           sphere_truth)
    assert scores['points'] == 1000
    assert scores['precision_at_5mm'] == pytest.approx(0.9)
    assert scores['median_to_surface_mm'] < 0.3
    assert scores['p95_to_surface_mm'] == pytest.approx(10.0, abs=0.3)
    noisy = on_surface + rng.normal(0, 0.001, on_surface.shape)
    assert point_metrics(noisy, sphere_truth)['precision_at_5mm'] == 1.0


def test_lattice_inferred_from_centres():
    centres = (np.array([[3, 4, 5], [4, 4, 5], [3, 6, 7]]) + 0.5) * 0.005 + [0.001, 0.0, -0.002]
    lattice = infer_lattice(centres.astype(np.float32))
    assert lattice.resolution == pytest.approx(0.005)
    assert np.array_equal(cell_indices(centres, lattice) - cell_indices(centres, lattice)[0],
                          [[0, 0, 0], [1, 0, 0], [0, 2, 2]])
    with pytest.raises(ValueError, match='single cell'):
        infer_lattice(centres[:1])


# ------------------------------------------------------------------ truth files

def make_truth(path, surface_centre, contacts, contact_times, poses, static=False,
                strays=None, count=100_000, **overrides):
    surface, normals = fibonacci_sphere(count, RADIUS, surface_centre)
    times = np.array([t for t, _, _ in poses])
    arrays = dict(object_name='sphere', static=static, rate=240.0, seed=0,
                  settings={'radius': RADIUS}, surface_points=surface, surface_normals=normals,
                  contacts=np.asarray(contacts, dtype=float),
                  contact_times=np.asarray(contact_times, dtype=float),
                  stray_points=np.empty((0, 3)) if strays is None else strays[0],
                  stray_times=np.empty(0) if strays is None else strays[1],
                  object_times=times, object_positions=np.array([p for _, p, _ in poses]),
                  object_quaternions=np.array([q for _, _, q in poses]))
    arrays.update(overrides)
    return write_truth(path, arrays)


def test_truth_file_round_trip_and_tracker_frame(tmp_path):
    quarter = np.array([0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)])  # 90 deg z
    poses = [(0.0, np.array([0.25, 0.0, 0.05]), quarter),
             (1.0, np.array([0.35, 0.0, 0.05]), quarter)]
    path = make_truth(tmp_path / 'bag.truth.npz', (0.0, 0.0, 0.0), [[0.04, 0.0, 0.0]], [0.5],
                       poses, strays=(np.array([[0.0, 0.06, 0.0]]), np.array([1.0])))
    assert truth_path(tmp_path / 'bag') == path
    truth = load_truth(path)
    assert truth.object_name == 'sphere' and truth.static is False and truth.rate == 240.0
    assert truth.settings == {'radius': RADIUS} and truth.frame == 'object'
    assert default_frame(truth) == 'object'
    assert in_frame(truth, 'object') is truth
    moved = in_frame(truth, 'tracker')
    # Surface by the first pose: (x, y, z) -> (0.25 - y, x, z + 0.05).
    first = truth.surface_points[0]
    assert np.allclose(moved.surface_points[0], [0.25 - first[1], first[0], first[2] + 0.05])
    assert np.allclose(moved.surface_normals[0], [-truth.surface_normals[0][1],
                                                 truth.surface_normals[0][0],
                                                 truth.surface_normals[0][2]])
    # The contact at t = 0.5 by the pose halfway: position 0.30.
    assert np.allclose(moved.contacts[0], [0.30, 0.04, 0.05])
    assert np.allclose(moved.stray_points[0], [0.35 - 0.06, 0.0, 0.05])
    assert truth.object_motion == pytest.approx(0.1)
    with pytest.raises(ValueError, match='frame must be one of'):
        in_frame(truth, 'camera')


def test_bad_truth_files_are_refused_clearly(tmp_path):
    with pytest.raises(ValueError, match='no such truth file'):
        load_truth(tmp_path / 'absent.truth.npz')
    (tmp_path / 'text.npz').write_text('hello')
    with pytest.raises(ValueError, match='not a truth file'):
        load_truth(tmp_path / 'text.npz')
    np.savez(tmp_path / 'partial.npz', surface_points=np.zeros((5, 3)), contacts=np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r'missing key.*object_name.*stray_points'):
        load_truth(tmp_path / 'partial.npz')
    poses = [(0.0, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))]
    bad = make_truth(tmp_path / 'bad.npz', (0, 0, 0), np.zeros((3, 2)), np.zeros(3), poses,
                      count=200)
    with pytest.raises(ValueError, match=r"'contacts' has shape \(3, 2\)"):
        load_truth(bad)
    bad = make_truth(tmp_path / 'bad2.npz', (0, 0, 0), [[0.04, 0, 0]], [0.0, 1.0], poses,
                      count=200)
    with pytest.raises(ValueError, match='contacts has 1 rows but contact_times has 2'):
        load_truth(bad)
    assert len(TRUTH_KEYS) == 14


def contact_truth(path, surface, contacts, times, mode, **extra):
    """A truth file of the plainer format other session generators write (as
    ../shared/data/validation_sessions holds)."""
    np.savez(path, surface=surface, contacts=np.asarray(contacts, dtype=float),
             contact_t=np.asarray(times, dtype=float), contact_finger=np.zeros(len(times), int),
             mode=np.array(mode), **{k: np.array(v) for k, v in extra.items()})
    return path


def open_ball(count: int, radius: float, wall: float):
    """Samples of a ball of ``radius`` with a 60-degree opening at the top and hollow inside
    (a bowl with a ``wall`` thick side): outer, inner and rim samples, and the outer ones'
    normals."""
    outer, normals = fibonacci_sphere(count, radius)
    inner, _ = fibonacci_sphere(count, radius - wall)
    keep_outer, keep_inner = outer[:, 2] < radius * 0.5, inner[:, 2] < (radius - wall) * 0.5
    return outer[keep_outer], inner[keep_inner], normals[keep_outer]


def test_the_surface_and_contacts_format_is_read_as_a_truth(tmp_path):
    outer, inner, normals = open_ball(20_000, RADIUS, 0.005)
    path = contact_truth(tmp_path / 'ball_tr_v5_r30_T120_s7_truth.npz',
                         np.concatenate([outer, inner]), outer[:50], np.arange(50) / 30.0,
                         'tracked', rate=30.0, seconds=120.0, speed_cms=5.0)
    truth = load_truth(path)
    assert (truth.object_name, truth.seed, truth.rate, truth.static) == ('ball', 7, 30.0, False)
    assert truth.settings['explored_radius'] == CONTACT_TRUTH_EXPLORED == 0.01
    assert len(truth.stray_points) == 0 and len(truth.contacts) == len(truth.contact_times) == 50
    # normals estimated: outward on the outer wall, towards the middle on the inner wall
    # (into the bowl, where the air is), away from the material between them
    n = len(outer)
    assert np.mean(np.einsum('ij,ij->i', truth.surface_normals[:n], normals) > 0.9) > 0.98
    inward = -inner / np.linalg.norm(inner, axis=1, keepdims=True)
    assert np.mean(np.einsum('ij,ij->i', truth.surface_normals[n:], inward) > 0.9) > 0.98
    # the map's frame needs no move: one identity object pose
    assert np.array_equal(in_frame(truth, 'tracker').surface_points, truth.surface_points)
    # found beside a bag of that name when there is no simulator sidecar
    assert truth_path(tmp_path / 'ball_tr_v5_r30_T120_s7') == path
    bad = contact_truth(tmp_path / 'odd_truth.npz', outer, outer[:2], [0.0], 'rolling')
    with pytest.raises(ValueError, match=r"'mode' is 'rolling', expected 'static' or 'tracked'"):
        load_truth(bad)
    bad = contact_truth(tmp_path / 'odd2_truth.npz', outer, outer[:2], [0.0], 'static')
    with pytest.raises(ValueError, match='contacts has 2 rows but contact_t has 1'):
        load_truth(bad)


def test_map_metrics_scores_a_map_against_the_surface_and_contacts_format(tmp_path, capsys):
    surface, _ = fibonacci_sphere(40_000, RADIUS)
    touched = surface[surface[:, 2] > 0.02]          # a cap was explored
    path = contact_truth(tmp_path / 'cap_st_v5_r30_T60_s1_truth.npz', surface, touched[::20],
                         np.arange(len(touched[::20])) / 30.0, 'static')
    lattice = Lattice(H)
    cells = voxel_centres(surface, lattice)        # the whole sphere: recall 1 either way
    ones = np.ones(len(cells))
    save_ply(tmp_path / 'cap.ply', cells, ones, ones, ones, frame_id='polhemus_source')
    code = map_metrics_main([str(tmp_path / 'cap.ply'), '--truth', str(path), '--json',
                             str(tmp_path / 'cap.json')])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    assert "object 'cap', static session" in printed.out and 'tracker frame' in printed.out
    assert 'within 10 mm of a true contact' in printed.out   # that format's explored surface
    scores = json.loads((tmp_path / 'cap.json').read_text())
    assert scores['explored_radius_mm'] == 10.0
    assert scores['thresholds']['0.8']['precision_at_5mm'] == 1.0
    assert scores['thresholds']['0.8']['recall_at_5mm'] == 1.0
    code = map_metrics_main([str(tmp_path / 'cap.ply'), '--truth', str(path),
                             '--explored-radius', '0.005', '--json', str(tmp_path / 'five.json')])
    five = json.loads((tmp_path / 'five.json').read_text())
    assert code == 0 and five['explored_radius_mm'] == 5.0
    # the cap's explored band is narrower by 5 mm all round
    assert five['thresholds']['0.8']['explored_samples'] \
        < scores['thresholds']['0.8']['explored_samples']


# ------------------------------------------------------------------ the CLIs on real maps

def build_map(bag, config, out, name):
    result = subprocess.run([executable_path('build_map'), str(bag), '--config', str(config),
                             '--output-dir', str(out), '--name', name, '--quiet'],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    return out / f'{name}.npz'


SPOTS = 40   # spots on the sphere of the CLI sessions (the fingers slide from spot to spot)


def session_truth(path, frames, centre, seed, static, strays=None):
    tour = spot_tour(sphere_surface_points(SPOTS, RADIUS, seed))
    contacts, times = [], []
    for k, (t, _) in enumerate(frames):
        for f in range(3):
            contacts.append(centre + fingertip_on_sphere(k, f, tour))
            times.append(t)
    poses = [(t, frame['object'][0], frame['object'][1]) for t, frame in frames]
    return make_truth(path, centre, contacts, times, poses, static=static, strays=strays)


@pytest.fixture(scope='module')
def sessions(tmp_path_factory):
    """A moving (tracked) and a still (static) sphere session: bags, maps, truth files."""
    root = tmp_path_factory.mktemp('metrics')
    out = {}
    for name, moving, config in (('moving', True, CONFIG), ('still', False, STATIC_CONFIG)):
        frames, centre = sphere_session(seconds=5.0, surface_points=SPOTS, moving=moving, seed=1)
        bag = write_pose_bag(root / name, frames)
        strays = (centre + np.array([[0.0, 0.0, -0.07]]), np.array([frames[0][0]]))
        truth = session_truth(truth_path(bag), frames, centre, 1, not moving, strays)
        out[name] = {'bag': bag, 'truth': truth, 'map': build_map(bag, config, root, name),
                     'frames': frames, 'centre': centre, 'root': root}
    return out


def test_map_metrics_on_a_tracked_build_map(sessions, tmp_path, capsys):
    s = sessions['moving']
    out = tmp_path / 'metrics.json'
    code = map_metrics_main([str(s['map']), '--truth', str(s['truth']), '--bag', str(s['bag']),
                             '--threshold', '0', '0.8', '--json', str(out)])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    assert 'compared in the object frame' in printed.out
    assert 'F-score @ 5 mm' in printed.out and 'map > 0.8' in printed.out
    document = json.loads(out.read_text())
    assert document['frame'] == 'object' and document['map_kind'] == 'npz'
    occupied = document['thresholds']['0.8']
    grid_cells = int((load_map(s['map']).probabilities > 0.8).sum())
    assert occupied['occupied_cells'] == grid_cells > 20
    # Every occupied cell holds spots of the sphere: within one cell, and its centre within
    # half a diagonal (4.3 mm) of the surface.
    assert occupied['cell_precision'] == 1.0 and occupied['precision_at_5mm'] == 1.0
    assert occupied['off_surface_cells'] == 0 and occupied['stray_cells'] == 0
    assert occupied['strays_far_from_surface'] == 1
    assert occupied['com_error_mm'] < 10
    assert document['thresholds']['0']['cell_recall'] == 1.0  # every touched cell
    points = document['points']
    assert points['points'] == 3 * len(s['frames'])
    assert points['precision_at_5mm'] == 1.0 and points['median_to_surface_mm'] < 0.5


def test_map_metrics_static_session_in_the_tracker_frame(sessions, capsys):
    s = sessions['still']
    # The truth says static: the map is compared in the tracker frame, the points are
    # registered statically; the truth is the sidecar of --bag.
    code = map_metrics_main([str(s['map']), '--bag', str(s['bag'])])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    assert 'static session' in printed.out and 'tracker frame' in printed.out
    assert '(static)' in printed.out
    row = next(line for line in printed.out.splitlines() if line.startswith('precision @ 5 mm'))
    assert row.split()[-1] == '1.000'
    # The same map read as if it were in the object frame misses the surface by 25 cm,
    # and says so.
    code = map_metrics_main([str(s['map']), '--truth', str(s['truth']), '--frame', 'object'])
    printed = capsys.readouterr()
    assert code == 0 and 'try --frame tracker' in printed.err


def test_map_metrics_reads_ply_and_a_recorded_cloud_alike(sessions, tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from inhand_common.point_cloud import serialize_point_cloud2
    from inhand_mapping.cloud_layouts import map_cells
    from inhand_mapping.map_io import load_npz
    s = sessions['moving']
    grid, _ = load_npz(s['map'])
    bag = tmp_path / 'recorded'
    store = get_typestore(Stores.ROS2_JAZZY)
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/occupancy/occupied', 'sensor_msgs/msg/PointCloud2',
                                           typestore=store)
        writer.write(connection, 1, serialize_point_cloud2(map_cells(grid, 0.5)[:3], 'object',
                                                           0, 1))
        writer.write(connection, 2, serialize_point_cloud2(map_cells(grid, 0.8), 'object', 0, 2))
    results = {}
    for name, source in (('npz', s['map']), ('ply', s['map'].with_suffix('.ply')),
                         ('bag', bag)):
        out = tmp_path / f'{name}.json'
        assert map_metrics_main([str(source), '--truth', str(s['truth']), '--json',
                                 str(out)]) == 0
        results[name] = json.loads(out.read_text())['thresholds']['0.8']
    cells = load_map(bag)
    assert cells.kind == 'bag cloud' and not cells.complete and len(cells.centres) > 3
    assert cells.lattice.resolution == pytest.approx(0.005)
    for key in ('occupied_cells', 'iou', 'cell_precision', 'cell_recall', 'fscore_at_5mm'):
        assert results['ply'][key] == pytest.approx(results['npz'][key]), key
        assert results['bag'][key] == pytest.approx(results['npz'][key]), key
    assert results['bag']['chamfer_mm'] == pytest.approx(results['npz']['chamfer_mm'], abs=1e-3)


def test_map_metrics_executable_and_bad_inputs(sessions, tmp_path):
    s = sessions['moving']
    result = subprocess.run([executable_path('map_metrics'), str(s['map']), '--truth',
                             str(s['truth'])], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert 'voxel IoU' in result.stdout and 'Chamfer distance (mm)' in result.stdout

    def refused(*args):
        completed = subprocess.run([executable_path('map_metrics'), *map(str, args)],
                                   capture_output=True, text=True, timeout=60)
        assert completed.returncode == 2, completed.stdout + completed.stderr
        return completed.stderr

    assert 'no such map file' in refused(tmp_path / 'nothing.npz', '--truth', s['truth'])
    # The truth file given as the map: a foreign NPZ.
    assert 'ground-truth file, not a map' in refused(s['truth'], '--truth', s['truth'])
    np.savez(tmp_path / 'other.npz', a=np.zeros(3))
    assert 'not a map saved by this software' in refused(tmp_path / 'other.npz', '--truth',
                                                         s['truth'])
    (tmp_path / 'notes.txt').write_text('not a map')
    assert 'not a map' in refused(tmp_path / 'notes.txt', '--truth', s['truth'])
    assert 'no ground truth' in refused(s['map'])
    assert 'missing key' in refused(s['map'], '--truth', s['map'])
    assert 'no map cloud' in refused(s['bag'], '--truth', s['truth'])
    assert 'no such bag' in refused(s['map'], '--truth', s['truth'], '--bag',
                                    tmp_path / 'absent')
    assert 'must be in [0, 1)' in refused(s['map'], '--truth', s['truth'], '--threshold', '1.5')


def test_map_metrics_without_a_stereo_pair_says_so_in_one_line_each(sessions, tmp_path,
                                                                    capsys):
    # A session without a camera: no colours in the map, no stereo keys in the truth, no
    # pair in the bag. Repeated --config files (the stereo rig's too) still register the
    # points.
    s = sessions['moving']
    out = tmp_path / 'metrics.json'
    code = map_metrics_main([str(s['map']), '--truth', str(s['truth']), '--bag', str(s['bag']),
                             '--config', str(CONFIG), '--config',
                             str(WORKSPACE / 'config' / 'stereo.yaml'), '--json', str(out)])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    notes = [line for line in printed.out.splitlines() if 'n/a (' in line]
    assert [line.split(':')[0] for line in notes] == ['map colours', 'stereo shot'], notes
    assert 'carries no colours' in notes[0] and 'no stereo keys' in notes[1]
    assert 'Traceback' not in printed.err
    document = json.loads(out.read_text())
    assert document['colour'] is None and document['stereo'] is None
    assert 'no colours' in document['colour_note'] and 'stereo' in document['stereo_note']
    assert document['points']['points'] == 3 * len(s['frames'])
    # Without --bag the shot's line asks for it; with a truth that has stereo keys (a
    # bundled cat's, foreign to this map), it says the bag holds no pair.
    code = map_metrics_main([str(s['map']), '--truth', str(s['truth'])])
    printed = capsys.readouterr()
    assert code == 0 and 'stereo shot: n/a (give --bag BAG' in printed.out
    code = map_metrics_main([str(s['map']), '--truth',
                             str(WORKSPACE / 'bags' / 'cat_moving.truth.npz'), '--bag',
                             str(s['bag'])])
    printed = capsys.readouterr()
    assert code == 0 and f'stereo shot: n/a ({s["bag"]} holds no stereo pair)' in printed.out


# ------------------------------------------------------------------ pictures

def test_higher_probability_cubes_are_darker():
    cells = voxel_centres(sphere_surface_points(3000, 0.03, seed=0), Lattice(H))
    camera = render.Camera(render.OBLIQUE, np.zeros(3), 0.035, 240)
    means = []
    for probability in (0.3, 0.7, 0.85, 0.97):
        image = render.render_cells(camera, cells, H, render.probability_colours(
            np.full(len(cells), probability)))
        drawn = np.any(image < 250, axis=2)
        assert drawn.mean() > 0.2
        means.append(image[drawn].mean())
    assert means == sorted(means, reverse=True)
    assert means[0] - means[-1] > 60


def framing_case():
    """A 4 cm sphere's truth (surface samples, strays: 6 just off the surface, 5 far away)
    and its map: the surface's cells (p 0.9) plus 3 confident cells 15-20 cm away."""
    surface, normals = fibonacci_sphere(40_000, RADIUS)
    near = normals[::6667][:6] * (RADIUS + 0.004)
    far = np.array([[0.2, 0.0, 0.0], [0.0, -0.2, 0.05], [0.15, 0.15, 0.15],
                    [-0.18, 0.1, -0.1], [0.0, 0.0, 0.25]])
    strays = np.concatenate([near, far])
    truth = GroundTruth('sphere', False, 240.0, 0, {}, surface, normals, surface[::400],
                        np.zeros(len(surface[::400])), strays, np.zeros(len(strays)),
                        np.zeros(1), np.zeros((1, 3)), np.array([[0.0, 0.0, 0.0, 1.0]]))
    lattice = Lattice(H)
    cells = np.concatenate([voxel_centres(surface, lattice),
                            voxel_centres(np.array([[0.15, 0.15, 0.0], [0.16, 0.15, 0.0],
                                                    [-0.1, -0.17, 0.05]]), lattice)])
    probabilities = np.full(len(cells), 0.9)
    probabilities[-3:] = 0.95
    hits = np.full(len(cells), 3)
    first = np.linspace(0.0, 10.0, len(cells))
    return truth, MapCells(cells, probabilities, hits, first, lattice, 'npz', 'framing case',
                           True)


def test_view_box_is_the_truths_extent_not_the_strays():
    truth, cells = framing_case()
    box = map_view_box(cells, [0.0, 0.8], truth)
    margin = render.default_margin(render.ViewBox(-np.full(3, RADIUS), np.full(3, RADIUS)))
    assert margin == pytest.approx(0.01)
    assert np.allclose(box.low, truth.surface_points.min(axis=0) - margin)
    assert np.allclose(box.high, truth.surface_points.max(axis=0) + margin)
    inside = box.contains(truth.stray_points)
    assert inside.tolist() == [True] * 6 + [False] * 5
    assert not box.contains(cells.centres[-3:]).any()
    # Without the truth: a robust box of the confident cells, the far ones ignored; it
    # holds the sphere's cells and is not much bigger than the sphere.
    robust = map_view_box(cells, [0.0, 0.8])
    assert robust.contains(cells.centres[:-3]).all()
    assert not robust.contains(cells.centres[-3:]).any()
    assert np.all(robust.extent < 2 * RADIUS + 2 * 0.02)
    # Raw points: the dense cloud on the object framed, the far excursions not.
    rng = np.random.default_rng(0)
    raw = np.concatenate([truth.surface_points[::20] + [0.25, 0.0, 0.05],
                          rng.uniform(-0.3, 0.3, (60, 3)) + [0.25, 0.0, 0.05]])
    raw_box = raw_view_box(raw)
    assert raw_box.contains(truth.surface_points[::20] + [0.25, 0.0, 0.05]).mean() > 0.97
    assert np.all(raw_box.extent < 2 * RADIUS + 2 * 0.02)


def test_camera_fills_the_panel_with_the_view_box():
    truth, _ = framing_case()
    box = render.box_of(truth.surface_points)
    for view in (render.OBLIQUE, render.SIDE):
        camera = render.Camera.for_box(view, box, 400, 'z')
        pixels, _ = camera.project(truth.surface_points)
        left, top, right, bottom = camera.area
        assert camera.in_view(truth.surface_points).all()
        span = np.ptp(pixels, axis=0) / np.array([right - left, bottom - top])
        # The sphere with a 1 cm margin: 8 of 10 cm across the free area's smaller side.
        assert span.max() == pytest.approx(0.8, abs=0.02)
        assert not camera.in_view(truth.stray_points[6:]).all()


def test_render_map_counts_what_is_outside_the_view(tmp_path, panel_labels):
    labels = panel_labels
    truth, cells = framing_case()
    written = draw_all(cells, tmp_path, [0.0, 0.6, 0.8], None, truth, 'object', size=240)
    assert tmp_path / 'figure.png' in written
    truth_panels = [subtitle for title, subtitle in labels if 'stray points' in subtitle]
    cell_panels = [subtitle for title, subtitle in labels
                   if subtitle.startswith(f'{len(cells.centres)} cells')]
    # truth.png (2 views) and the figure's ground-truth panel; for each of the 3
    # thresholds: map_above_<t>.png (2 views) and its panel of map_thresholds.png.
    assert len(truth_panels) == 3 and len(cell_panels) == 9, labels
    for subtitle in truth_panels:
        assert '+ 5 stray points outside the view' in subtitle, subtitle
    for subtitle in cell_panels:
        assert subtitle.endswith('+ 3 cells outside the view'), subtitle
    figure_truth = [subtitle for title, subtitle in labels if title == 'ground truth']
    assert figure_truth == ['green: explored, red: strays\n+ 5 stray points outside the view']
    # The strays near the surface are drawn (red), in front of the sphere or beside it.
    image = cv2.imread(str(tmp_path / 'truth.png'))
    red = (image[..., 2] > 180) & (image[..., 1] < 80) & (image[..., 0] < 80)
    assert red.sum() > 6
    assert render.outside_note(1, 'cells') == '+ 1 cell outside the view'
    assert render.outside_note(812) == '+ 812 points outside the view'


def test_the_lowest_threshold_shows_what_was_explored_not_what_the_camera_saw_free(
        tmp_path, panel_labels):
    """A fused map: every cell the vision map saw free has p > 0 (here 0.12, no hits); the
    p > 0 picture shows the touched cells and those observed occupied, as the paper's
    fig. 5 does."""
    truth, cells = framing_case()
    free = voxel_centres(np.random.default_rng(0).uniform(-0.1, 0.1, (3000, 3)), cells.lattice)
    free = free[np.linalg.norm(free, axis=1) > RADIUS + 0.01]
    seen = np.array([[0.0, 0.0, RADIUS + 0.006]])                # vision: occupied, no hits
    fused = MapCells(np.concatenate([cells.centres, free, seen]),
                     np.concatenate([cells.probabilities, np.full(len(free), 0.12), [0.9]]),
                     np.concatenate([cells.hits, np.zeros(len(free) + 1, dtype=int)]),
                     np.concatenate([cells.first_touch, np.full(len(free) + 1, np.nan)]),
                     cells.lattice, 'npz', 'fused', True)
    draw_all(fused, tmp_path, [0.0, 0.8], None, truth, 'object', size=160)
    explored = len(cells.centres) + 1
    counted = {subtitle.split(' cells')[0] for _, subtitle in panel_labels
               if ' cells' in subtitle and subtitle[0].isdigit()}
    assert str(explored) in counted and str(len(fused.centres)) not in counted, counted


def test_pictures_stand_the_object_upright():
    # The simulator's object frame has +z up; the tracker frame's z points down.
    assert default_up('object') == 'z'
    assert default_up('tracker') == '-z' and default_up(None) == '-z'
    for up, vertical in (('z', [0.0, 0.0, 1.0]), ('-z', [0.0, 0.0, -1.0])):
        camera = render.Camera(render.SIDE, np.zeros(3), 0.05, 200, up)
        assert camera.direction(np.array(vertical))[0, 1] < -0.9 * camera.scale  # screen up


def test_regions_most_explored_and_first_touched():
    hits = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 100])
    first = np.array([np.nan, 5, 4, 3, 2, 1, 6, 7, 8, 9, 0.0])
    most, earliest, hit_cut, first_cut = regions(hits, first, 0.2, 0.2)
    assert hit_cut == 9 and np.flatnonzero(most).tolist() == [9, 10]
    assert first_cut == 1.0 and np.flatnonzero(earliest).tolist() == [5, 10]


def test_render_map_writes_the_pictures(sessions, tmp_path, capsys):
    s = sessions['moving']
    out = tmp_path / 'pictures'
    code = render_map_main([str(s['map']), '--bag', str(s['bag']), '--output', str(out),
                            '--size', '200'])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    names = ['raw_points', 'registered_points', 'map_above_0', 'map_above_0.6',
             'map_above_0.8', 'map_thresholds', 'regions', 'truth', 'figure']
    listed = printed.out.split()
    for name in names:
        path = out / f'{name}.png'
        assert str(path) in listed
        image = cv2.imread(str(path))
        assert image is not None and image.ndim == 3
        if name in ('map_thresholds',):
            assert image.shape[1] == 3 * 200
        elif name == 'figure':
            assert image.shape[1] == 4 * 200  # 7 panels in rows of 4
        else:
            assert image.shape[1] == 2 * 200  # oblique and side view
        assert 200 + 40 < image.shape[0] < 3 * 200
        assert (image < 200).any(axis=2).mean() > 0.01, name  # something was drawn
    # Darker = more probable, over the whole range the maps use.
    ramp = render.probability_colours(np.array([0.12, 0.5, 0.69, 0.8, 0.83, 0.92, 0.97]))
    assert np.all(np.diff(np.asarray(ramp, dtype=float).sum(axis=1)) < 0)


def test_render_map_executable_and_bad_inputs(sessions, tmp_path):
    s = sessions['still']
    result = subprocess.run([executable_path('render_map'), str(s['map'].with_suffix('.ply')),
                             '--output', str(tmp_path / 'ply'), '--size', '160'],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    written = [line for line in result.stdout.splitlines() if line.endswith('.png')]
    # No bag: no point pictures; a PLY has no sidecar truth: no truth picture.
    assert len(written) == 6
    for line in written:
        assert cv2.imread(line).shape[1] in (160 * 2, 160 * 3)

    def refused(*args):
        completed = subprocess.run([executable_path('render_map'), *map(str, args)],
                                   capture_output=True, text=True, timeout=60)
        assert completed.returncode == 2, completed.stdout + completed.stderr
        return completed.stderr

    assert 'no such map file' in refused(tmp_path / 'absent.npz', '--output', tmp_path)
    assert 'ground-truth file, not a map' in refused(s['truth'], '--output', tmp_path)
    assert '--size 10' in refused(s['map'], '--output', tmp_path, '--size', '10')
    assert 'must be in [0, 1)' in refused(s['map'], '--output', tmp_path, '--thresholds', '2')


def test_touch_coverage_counts_touches_of_the_explored_surface_by_episode():
    # a flat patch of 4 x 1 cells (5 mm), sampled densely; contacts in three of its cells:
    # cell 0 twice 1 s apart (one touch), cell 1 at 0 s and 5 s (two touches), cell 2 once
    grid = np.mgrid[0.0005:0.02:0.001, 0.0005:0.005:0.001].reshape(2, -1).T
    surface = np.column_stack([grid, np.full(len(grid), 0.0025)])
    contacts = np.array([[0.0025, 0.0025, 0.0025], [0.0026, 0.0025, 0.0025],
                         [0.0075, 0.0025, 0.0025], [0.0076, 0.0025, 0.0025],
                         [0.0125, 0.0025, 0.0025]])
    times = np.array([0.0, 1.0, 0.0, 5.0, 2.0])
    truth = SurfaceTruth(surface, contacts, explored_radius=0.004)
    lattice = Lattice(0.005)
    coverage = touch_coverage(truth, times, lattice)
    cells = cell_indices(truth.explored_points, lattice)[:, 0]
    assert set(np.unique(cells)) == {0, 1, 2, 3}          # 3.5 mm of cell 3 is explored too
    assert coverage['once'] == pytest.approx(np.mean(cells <= 2))
    assert coverage['twice'] == pytest.approx(np.mean(cells == 1))
    # a longer gap makes the two touches of cell 1 one
    assert touch_coverage(truth, times, lattice, gap=10.0)['twice'] == 0.0
