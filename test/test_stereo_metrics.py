"""The map's colours and the stereo shot against the simulator's truth (``map_metrics``,
``inhand_tools/map_quality.py``'s colour metrics, ``inhand_tools/stereo_quality.py``).

On the bundled cat sessions, mapped by ``build_map`` with config/stereo.yaml as docs/stereo.md
says, and on hand-made cases whose values are worked out in the comments. No DDS.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from inhand_common.ground_truth import TRUTH_KEYS, in_frame, load_truth, write_truth
from inhand_tools.bag_stereo_shot import read_configured_shot
from inhand_tools.commands.build_map import main as build_map_main
from inhand_tools.commands.map_metrics import main as map_metrics_main
from inhand_tools.map_cells import Lattice, load_map
from inhand_tools.map_quality import (
    SurfaceTruth,
    colour_metrics,
    seen_cells,
    surface_truth,
    true_cell_colours,
)
from inhand_tools.stereo_quality import (
    disparity_scores,
    principal_point,
    samples_in_camera,
    stereo_point_scores,
    surface_distances,
    visible_samples,
)
from ros_helpers import WORKSPACE

BAGS = WORKSPACE / 'bags'
CONFIG = WORKSPACE / 'config'
STEREO = str(CONFIG / 'stereo.yaml')
CATS = {'cat_moving': str(CONFIG / 'mapping.yaml'),
        'cat_static': str(CONFIG / 'mapping_static.yaml')}
# The colour error bound: the bundled cats' textured cells score a median of 51-56 (the
# truth is the unshaded albedo; the images are darker by the shading), the same colours
# shuffled among the cells 93-95.
COLOUR_ERROR_BOUND = 70.0


@pytest.fixture(scope='module')
def cat_maps(tmp_path_factory):
    """The bundled cats mapped with their colours (and one without, for the missing input)."""
    root = tmp_path_factory.mktemp('stereo_metrics')
    for name, config in CATS.items():
        assert build_map_main([str(BAGS / name), '--config', config, '--config', STEREO,
                               '--output-dir', str(root), '--quiet']) == 0
    assert build_map_main([str(BAGS / 'cat_static'), '--config', CATS['cat_static'],
                           '--output-dir', str(root), '--name', 'uncoloured', '--quiet']) == 0
    return root


def run_metrics(capsys, *args) -> tuple[int, str, str]:
    code = map_metrics_main([str(a) for a in args])
    printed = capsys.readouterr()
    return code, printed.out, printed.err


def shot_of(name: str, mode: str):
    configs = [CATS[name], STEREO]
    shot, why = read_configured_shot(BAGS / name, configs, {'mode': mode})
    assert shot is not None, why
    return shot


# ------------------------------------------------------------------ the bundled cats

@pytest.mark.parametrize('name', sorted(CATS))
def test_colour_and_stereo_metrics_of_a_bundled_cat(cat_maps, tmp_path, capsys, name):
    out = tmp_path / 'metrics.json'
    code, printed, err = run_metrics(capsys, cat_maps / f'{name}.npz', '--bag', BAGS / name,
                                     '--config', CATS[name], '--config', STEREO,
                                     '--json', out)
    assert code == 0, err
    assert 'map colours (occupied cells)' in printed and 'stereo shot (first usable' in printed
    assert 'n/a (' not in printed
    document = json.loads(out.read_text())
    colour = document['colour']['0.8']
    assert colour['occupied_cells'] == document['thresholds']['0.8']['occupied_cells']
    # The camera sees about half the cat; most of what it saw is textured and next to
    # nothing it did not see is painted.
    assert 0.3 < colour['seen_cells'] / colour['occupied_cells'] < 0.8
    assert colour['seen_textured_fraction'] > 0.5
    assert 0.2 < colour['textured_fraction'] < colour['seen_textured_fraction']
    assert colour['unseen_textured_cells'] <= 0.01 * colour['occupied_cells']   # back faces
    assert colour['colour_error_median'] < COLOUR_ERROR_BOUND \
        < colour['colour_error_shuffled_median']
    assert colour['colour_error_p95'] < 220
    stereo = document['stereo']
    assert stereo['principal_point'] == pytest.approx([321.7, 238.2])
    disparity = stereo['disparity']
    assert disparity['object_density'] > 0.9 and disparity['object_bad2'] < 0.05
    on_object = stereo['object_points']
    assert on_object['points'] > 10000
    assert on_object['median_mm'] < 1.0 and on_object['p95_mm'] < 3.0
    assert on_object['within_5mm'] > 0.97
    # stereo/points also holds the table and the backdrop: the object is a small share.
    every = stereo['points']
    assert every['points'] > 40000 and 0.02 < every['within_5mm'] < 0.2
    assert every['median_mm'] > 50
    assert document['colour_note'] is None and document['stereo_note'] is None
    # The registered points still come with both --config files.
    assert document['points']['points'] == 5400


def test_shuffled_or_shifted_colours_exceed_the_bound(cat_maps):
    cells = load_map(cat_maps / 'cat_moving.npz')
    truth = in_frame(load_truth(BAGS / 'cat_moving.truth.npz'), 'object')
    surface = surface_truth(truth)

    def error(colours):
        return colour_metrics(cells.centres, cells.probabilities, cells.lattice, colours,
                              cells.textured, surface, truth.surface_colours
                              )['colour_error_median']

    assert error(cells.colours) < COLOUR_ERROR_BOUND
    painted = np.flatnonzero(cells.textured)
    rng = np.random.default_rng(7)
    shuffled = cells.colours.copy()
    shuffled[painted] = cells.colours[rng.permutation(painted)]
    assert error(shuffled) > COLOUR_ERROR_BOUND
    # Each colour one textured cell further along (a misregistered index).
    rolled = cells.colours.copy()
    rolled[painted] = cells.colours[np.roll(painted, 1)]
    assert error(rolled) > COLOUR_ERROR_BOUND
    # Grey for every cell: no colour information at all.
    assert error(np.full_like(cells.colours, 128)) > COLOUR_ERROR_BOUND


def test_disparity_scores_equal_a_direct_computation(cat_maps, tmp_path, capsys):
    shot = shot_of('cat_static', 'static')
    truth = load_truth(BAGS / 'cat_static.truth.npz').stereo
    result = shot.placed.shot.disparity
    d, valid = result.disparity, result.disparity >= result.min_disparity
    error = np.abs(d - truth.focal * truth.baseline / truth.depth)
    on = truth.object_mask
    direct = {'object_pixels': int(on.sum()), 'object_density': valid[on].mean(),
              'object_bad2': (error[on & valid] > 2).mean(), 'image_density': valid.mean(),
              'image_bad2': (error[valid] > 2).mean()}
    scores = disparity_scores(d, result.valid, truth.disparity, truth.object_mask)
    for key, value in direct.items():
        assert scores[key] == pytest.approx(value, abs=1e-12), key
    out = tmp_path / 'metrics.json'
    code, _, err = run_metrics(capsys, cat_maps / 'cat_static.npz', '--bag',
                               BAGS / 'cat_static', '--config', CATS['cat_static'],
                               '--config', STEREO, '--json', out)
    assert code == 0, err
    reported = json.loads(out.read_text())['stereo']['disparity']
    for key, value in direct.items():
        assert reported[key] == pytest.approx(value, abs=1e-12), key


def test_disparity_scores_by_hand():
    # 2x3 image; the object is the left two columns. Truth 50 px everywhere.
    truth = np.full((2, 3), 50.0, np.float32)
    on = np.array([[True, True, False], [True, True, False]])
    d = np.array([[50.0, 53.0, 47], [0.0, 51.9, 50]], np.float32)
    valid = d >= 48                                 # 47 and 0 are invalid
    scores = disparity_scores(d, valid, truth, on)
    assert scores['object_pixels'] == 4
    assert scores['object_density'] == 0.75         # 3 of 4 object pixels
    assert scores['object_bad2'] == pytest.approx(1 / 3)    # 53: 3 px off; 51.9 is not
    assert scores['image_density'] == pytest.approx(4 / 6)
    assert scores['image_bad2'] == 0.25
    with pytest.raises(ValueError, match='same image size'):
        disparity_scores(d, valid, truth[:1], on)


def test_visible_samples_are_on_the_object_pixels():
    truth = load_truth(BAGS / 'cat_static.truth.npz')
    stereo = truth.stereo
    visible = visible_samples(truth, (321.7, 238.2), 0.005)
    # About 40 % of the cat's surface faces the camera unoccluded.
    assert 0.3 < visible.mean() < 0.55
    camera = samples_in_camera(truth)[visible]
    column = np.floor(stereo.focal * camera[:, 0] / camera[:, 2] + 321.7 + 0.5).astype(int)
    row = np.floor(stereo.focal * camera[:, 1] / camera[:, 2] + 238.2 + 0.5).astype(int)
    assert stereo.object_mask[row, column].mean() > 0.99
    # The same samples, the truth moved into the tracker frame (a static map's).
    assert np.array_equal(visible_samples(in_frame(truth, 'tracker'), (321.7, 238.2), 0.005),
                          visible)
    # The image centre instead of the principal point misses part of the cat's edges; 20 px
    # off, most of it.
    assert visible_samples(truth, (319.5, 239.5), 0.005).sum() < visible.sum()
    assert visible_samples(truth, (341.7, 238.2), 0.005).sum() < 0.5 * visible.sum()


def test_stereo_points_of_the_object_are_on_the_surface():
    shot = shot_of('cat_moving', 'tracked')
    truth = load_truth(BAGS / 'cat_moving.truth.npz')
    surface = surface_truth(truth)
    points, _ = shot.points()
    distances = surface_distances(surface, points)
    exact = surface.distance(points)[0]
    near = exact <= 0.02
    assert np.array_equal(distances[near], exact[near])
    # Beyond 2 cm the distance is to a subsample of the surface: never less, at most its
    # covering radius more (0.5 mm here).
    assert np.all(distances[~near] >= exact[~near])
    assert np.max(distances[~near] - exact[~near]) < 0.001
    assert principal_point(shot) == pytest.approx((321.7, 238.2))


def test_stereo_point_scores_by_hand():
    scores = stereo_point_scores([0.001, 0.002, 0.004, 0.006, 0.3])
    assert scores['points'] == 5 and scores['median_mm'] == pytest.approx(4.0)
    assert scores['within_5mm'] == 0.6
    assert scores['p95_mm'] == pytest.approx(6 + 0.8 * (300 - 6))    # numpy's linear rank
    assert np.isnan(stereo_point_scores([])['median_mm'])


# ------------------------------------------------------------------ hand-made colour cases

H = 0.01


def test_true_cell_colours_are_per_channel_medians_of_the_samples_inside():
    # Cell (0, 0, 0) holds three samples, cell (1, 0, 0) two; cell (5, 0, 0) none: the
    # nearest sample's colour (the last one, at x = 0.018).
    points = np.array([[0.002, 0.005, 0.005], [0.005, 0.005, 0.005], [0.008, 0.005, 0.005],
                       [0.012, 0.005, 0.005], [0.018, 0.005, 0.005]])
    colours = np.array([[10, 200, 0], [30, 100, 255], [20, 0, 7], [0, 0, 0], [100, 50, 3]],
                       np.uint8)
    surface = SurfaceTruth(points, np.empty((0, 3)))
    centres = np.array([[0.005, 0.005, 0.005], [0.015, 0.005, 0.005], [0.055, 0.005, 0.005]])
    true, held = true_cell_colours(centres, Lattice(H), surface, colours)
    assert held.tolist() == [True, True, False]
    assert true[0].tolist() == [20, 100, 7]         # per channel, not one sample's colour
    assert true[1].tolist() == [50, 25, 1.5]        # even count: mean of the middle two
    assert true[2].tolist() == [100, 50, 3]


def test_colour_metrics_and_seen_cells_by_hand():
    # Four occupied cells along x, one below the threshold; surface samples in the first
    # three, visible in the first two; the fourth cell holds none and its nearest sample
    # (the third cell's) is hidden.
    points = np.array([[0.005, 0.005, 0.005], [0.015, 0.005, 0.005], [0.025, 0.005, 0.005]])
    truth_colours = np.array([[100, 100, 100], [200, 0, 0], [0, 0, 200]], np.uint8)
    visible = np.array([True, True, False])
    surface = SurfaceTruth(points, np.empty((0, 3)))
    centres = np.array([[0.005, 0.005, 0.005], [0.015, 0.005, 0.005], [0.025, 0.005, 0.005],
                        [0.035, 0.005, 0.005], [0.045, 0.005, 0.005]])
    probabilities = np.array([0.9, 0.9, 0.9, 0.9, 0.5])
    assert seen_cells(centres, Lattice(H), surface, visible).tolist() == \
        [True, True, False, False, False]
    # Textured: the first (error 3 * 10 -> sqrt(300)), the third (unseen; error 0) and the
    # one below the threshold (not counted).
    colours = np.array([[110, 110, 110], [0, 0, 0], [0, 0, 200], [0, 0, 0], [9, 9, 9]],
                       np.uint8)
    textured = np.array([True, False, True, False, True])
    scores = colour_metrics(centres, probabilities, Lattice(H), colours, textured, surface,
                            truth_colours, visible)
    assert scores['occupied_cells'] == 4 and scores['textured_cells'] == 2
    assert scores['textured_fraction'] == 0.5
    assert scores['seen_cells'] == 2 and scores['seen_textured_fraction'] == 0.5
    assert scores['unseen_textured_cells'] == 1
    assert scores['colour_error_median'] == pytest.approx(np.sqrt(300) / 2)
    no_visibility = colour_metrics(centres, probabilities, Lattice(H), colours, textured,
                                   surface, truth_colours)
    assert no_visibility['seen_cells'] is None and np.isnan(
        no_visibility['seen_textured_fraction'])


# ------------------------------------------------------------------ missing inputs

def test_missing_inputs_leave_their_rows_out_with_one_line(cat_maps, tmp_path, capsys):
    cat = cat_maps / 'cat_static.npz'
    # No --bag: the colours without the seen cells; the stereo shot n/a.
    code, printed, err = run_metrics(capsys, cat, '--truth', BAGS / 'cat_static.truth.npz')
    assert code == 0, err
    assert 'colour error, median' in printed
    assert '(seen cells: n/a: no stereo shot: give --bag BAG' in printed
    assert 'stereo shot: n/a (give --bag BAG (and --config config/stereo.yaml)' in printed
    # --bag without the rig's camera_pose.
    out = tmp_path / 'no_pose.json'
    code, printed, err = run_metrics(capsys, cat, '--bag', BAGS / 'cat_static', '--config',
                                     CATS['cat_static'], '--json', out)
    assert code == 0, err
    line = next(line for line in printed.splitlines() if line.startswith('stereo shot'))
    assert 'no stereo_node camera_pose was given' in line
    document = json.loads(out.read_text())
    assert document['stereo'] is None and 'camera_pose' in document['stereo_note']
    assert document['colour']['0.8']['seen_cells'] is None
    # A map without colours.
    code, printed, err = run_metrics(capsys, cat_maps / 'uncoloured.npz', '--bag',
                                     BAGS / 'cat_static', '--config', CATS['cat_static'],
                                     '--config', STEREO)
    assert code == 0, err
    assert 'map colours: n/a (the npz map carries no colours' in printed
    assert 'disparity density on the object' in printed
    # A truth without the stereo keys: neither the colours nor the shot can be judged.
    full = load_truth(BAGS / 'cat_static.truth.npz')
    with np.load(BAGS / 'cat_static.truth.npz') as data:
        bare = write_truth(tmp_path / 'bare.truth.npz', {k: data[k] for k in TRUTH_KEYS})
    assert full.stereo is not None and load_truth(bare).stereo is None
    out = tmp_path / 'bare.json'
    code, printed, err = run_metrics(capsys, cat, '--truth', bare, '--bag',
                                     BAGS / 'cat_static', '--config', CATS['cat_static'],
                                     '--config', STEREO, '--json', out)
    assert code == 0, err
    assert 'Traceback' not in printed + err
    notes = [line for line in printed.splitlines() if 'n/a (' in line]
    assert len(notes) == 2 and all('no stereo keys' in line or 'no surface colours' in line
                                   for line in notes), notes
    document = json.loads(out.read_text())
    assert document['colour'] is None and document['stereo'] is None
    assert document['thresholds']['0.8']['occupied_cells'] > 0


def test_an_unreadable_stereo_config_is_refused(cat_maps, tmp_path, capsys):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('stereo_node:\n  ros__parameters:\n    min_disparity: many\n')
    code, _, err = run_metrics(capsys, cat_maps / 'cat_static.npz', '--bag',
                               BAGS / 'cat_static', '--config', CATS['cat_static'],
                               '--config', str(bad))
    assert code == 2 and 'min_disparity' in err and 'Traceback' not in err

