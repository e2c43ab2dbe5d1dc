"""The cell judge (cell_judge.py): its trees as the map evaluates them, its features, and
the map that carries its verdicts (occupancy.py), which must not depend on when or how
often it is read, nor on a save and a resume between."""

from __future__ import annotations

import numpy as np
import pytest

from inhand_mapping import map_io
from inhand_mapping.cell_judge import (
    FEATURES,
    MODEL_FILE,
    POOL_TOUCHES,
    VETO,
    VETO_UNVISITED,
    CellJudge,
    TreeEnsemble,
    pool_features,
    shipped_judge,
)
from inhand_mapping.map_products import resume_from
from inhand_mapping.occupancy import GridSpec, OccupancyGrid, SensorModel


def stump(feature: int, threshold: float, low: float, high: float, base: int) -> dict:
    """One tree of a root and two leaves, its nodes numbered from ``base``."""
    return dict(feature=[feature, 0, 0], threshold=[threshold, 0.0, 0.0],
                left=[base + 1, base + 1, base + 2], right=[base + 2, base + 1, base + 2],
                value=[0.0, low, high])


def two_stumps() -> TreeEnsemble:
    trees = [stump(0, 1.0, -1.0, 2.0, 0), stump(1, 0.5, 0.5, -3.0, 3)]
    return TreeEnsemble(**{key: np.concatenate([t[key] for t in trees])
                           for key in trees[0]}, roots=np.array([0, 3]), baseline=0.25,
                        features=('a', 'b'))


def test_the_trees_add_their_leaves_to_the_baseline_and_give_its_logistic():
    judge = two_stumps()
    rows = np.array([[1.0, 0.5], [1.5, 0.5], [0.0, 2.0], [3.0, 9.0]])   # a split's value goes left
    raw = 0.25 + np.array([-1.0 + 0.5, 2.0 + 0.5, -1.0 - 3.0, 2.0 - 3.0])
    np.testing.assert_allclose(judge.probability(rows), 1.0 / (1.0 + np.exp(-raw)))


def test_trees_that_point_outside_their_nodes_are_refused(tmp_path):
    judge = two_stumps()
    judge.save(tmp_path / 'judge.npz')
    loaded = TreeEnsemble.load(tmp_path / 'judge.npz')
    np.testing.assert_array_equal(loaded.left, judge.left)
    assert loaded.features == ('a', 'b') and loaded.baseline == 0.25
    with pytest.raises(ValueError, match='left points outside'):
        TreeEnsemble(**{**vars(judge), 'left': judge.left + 10})
    with pytest.raises(ValueError, match='feature index outside'):
        TreeEnsemble(**{**vars(judge), 'feature': judge.feature + 2})
    looped = judge.left.copy()
    looped[1] = 0                       # a leaf that leads back to its root: a walk never ends
    with pytest.raises(ValueError, match='cycle'):
        TreeEnsemble(**{**vars(judge), 'left': looped})


def test_the_shipped_judge_reads_this_modules_features():
    judge = shipped_judge()
    assert MODEL_FILE.is_file()
    assert judge.features == FEATURES and len(judge.roots) >= 10
    p = judge.probability(np.zeros((3, len(FEATURES))))
    assert ((p >= 0) & (p <= 1)).all()


def sheet_evidence(n: int = 20, z: int = 10, touches: float = 3.0) -> np.ndarray:
    """A 12 x 12 sheet of touched cells in an (n, n, n) grid, a row of cells above it
    (a hover) and air the strokes crossed above that."""
    evidence = np.zeros((n, n, n))
    evidence[4:16, 4:16, z] = touches
    evidence[6:12, 9, z + 1] = 1.0          # a hover one cell above
    evidence[4:16, 4:16, z + 2] = 0.1       # the air of the lifts
    return evidence


def test_the_features_of_a_map_do_not_depend_on_where_in_the_grid_it_lies():
    evidence = sheet_evidence()
    hits = (evidence >= 1).astype(np.uint32)
    centres = (np.indices(evidence.shape).transpose(1, 2, 3, 0) + 0.5) * 0.005
    sums = centres * hits[..., None]            # every hit at its cell's centre
    pool, rows = pool_features(evidence, hits, sums, np.zeros(3), 0.005)
    assert len(pool) == np.count_nonzero(evidence >= POOL_TOUCHES) == 144 + 6
    assert rows.shape == (len(pool), len(FEATURES)) and np.isfinite(rows).all()
    # The same cells moved by (7, 3, 5) in a larger grid: the same features, in order.
    bigger = np.zeros((32, 32, 32))
    bigger[7:27, 3:23, 5:25] = evidence
    big_hits = (bigger >= 1).astype(np.uint32)
    big_sums = np.zeros((32, 32, 32, 3))
    big_sums[7:27, 3:23, 5:25] = sums
    moved, moved_rows = pool_features(bigger, big_hits, big_sums, -np.array([7, 3, 5]) * 0.005,
                                      0.005)
    np.testing.assert_array_equal(moved, pool + [7, 3, 5])
    np.testing.assert_allclose(moved_rows, rows, atol=1e-9)
    # where in each cell its hits were, in cells from the centre: a hit at a cell's corner
    sums[tuple(pool[0])] = (pool[0] + 1.0) * 0.005 * hits[tuple(pool[0])]
    _, shifted = pool_features(evidence, hits, sums, np.zeros(3), 0.005)
    assert shifted[0, FEATURES.index('touches_off_centre')] == pytest.approx(np.sqrt(0.75))
    empty, none = pool_features(np.zeros((8, 8, 8)), np.zeros((8, 8, 8)),
                                np.zeros((8, 8, 8, 3)), np.zeros(3), 0.005)
    assert empty.shape == (0, 3) and none.shape == (0, len(FEATURES))


def test_the_judge_overrides_only_where_it_is_sure_and_only_towards_its_verdict():
    evidence = sheet_evidence()
    hits = (evidence >= 1).astype(np.uint32)
    sums = np.zeros((*evidence.shape, 3))
    pool, rows = pool_features(evidence, hits, sums, np.zeros(3), 0.005)
    # A judge of one split: sure of the surface (0.993) where over 8 of the 27 cells within
    # a cell are touched (inside the sheet), sure of the air (0.007) elsewhere.
    column = FEATURES.index('touched_1')
    split = TreeEnsemble(feature=np.array([column, 0, 0]), threshold=np.array([8.0, 0, 0]),
                         left=np.array([1, 1, 2]), right=np.array([2, 1, 2]),
                         value=np.array([0.0, -5.0, 5.0]), roots=np.array([0]), baseline=0.0,
                         features=FEATURES)
    surface = rows[:, column] > 8
    explored = rows[:, FEATURES.index('unvisited_3')] <= VETO_UNVISITED
    assert surface.any() and not surface.all()
    assert (~surface & explored).any() and (~surface & ~explored).any()
    for rules_value in (0.9, 0.5, 0.05, 0.99):
        rules = np.full(evidence.shape, 0.5)
        rules[evidence >= POOL_TOUCHES] = rules_value
        judge = CellJudge(evidence.shape, np.zeros(3), 0.005, split)
        judge.update(evidence.reshape(-1), hits, sums, np.flatnonzero(evidence))
        log_odds = np.log(rules / (1 - rules)).reshape(-1)
        probability = rules.reshape(-1).copy()
        judge.apply(log_odds, probability, (0.12, 0.97))
        flat = judge.overridden
        verdict = probability[flat]
        # towards the verdict only: a veto where the rules gave more than 0.12 and the
        # neighbourhood was explored, a rescue where they gave less than 0.97
        expected = ((~surface & explored & (rules_value > 0.12))
                    | (surface & (rules_value < 0.97)))
        np.testing.assert_array_equal(flat, np.ravel_multi_index(tuple(pool[expected].T),
                                                                 evidence.shape))
        np.testing.assert_allclose(verdict, np.where(surface[expected], 0.97, 0.12))
        judge.undo(log_odds, probability)                 # and back to the rules'
        np.testing.assert_array_equal(probability, rules.reshape(-1))


def explored_session():
    """Three fingers exploring the simulator's cat for 25 s at 30 Hz, with 1 mm of tracker
    noise: (points (N, 3), times (N,), fingers (N,)) in time order."""
    from inhand_sim.exploration import explore
    from inhand_sim.objects import get_object
    rng = np.random.default_rng(5)
    exploration = explore(get_object('cat'), 25.0, 30.0, rng)
    count = exploration.positions.shape[1]
    points = exploration.positions.transpose(1, 0, 2).reshape(-1, 3)
    points = points + rng.normal(0.0, 0.001, points.shape)
    times = np.repeat(np.arange(count) / 30.0, 3)
    fingers = np.tile(np.arange(3), count)
    return points, times, fingers


SESSION = explored_session()
SESSION_SPEC = GridSpec(size=0.2, resolution=0.005)


def session_grid(model: SensorModel | None = None, chunks: int = 1,
                 read_between: bool = False, until: float = np.inf) -> OccupancyGrid:
    """The session (until ``until`` s) mapped with ``model`` (default: the defaults), in
    ``chunks`` calls, the map read after each when ``read_between``."""
    model = model or SensorModel()
    points, times, fingers = SESSION
    kept = times < until
    points, times, fingers = points[kept], times[kept], fingers[kept]
    grid = OccupancyGrid(SESSION_SPEC, model)
    for part in np.array_split(np.arange(len(times)), chunks):
        grid.integrate(points[part], times[part], fingers[part])
        if read_between:
            grid.probabilities()
    grid.flush()
    return grid


def test_the_judge_changes_the_rules_map_of_an_explored_object_where_it_is_sure():
    judged = session_grid()
    rules = session_grid(SensorModel(cell_judge=False))
    np.testing.assert_array_equal(judged.touch_evidence, rules.touch_evidence)
    p_judged, p_rules = judged.probabilities(), rules.probabilities()
    changed = p_judged != p_rules
    assert changed.any()
    # every change is to the judge's verdict: under VETO or over RESCUE (held to the clamps)
    assert ((p_judged[changed] < VETO) | (p_judged[changed] >= 0.97 - 1e-12)).all()
    assert (rules.touch_evidence[changed] >= POOL_TOUCHES).all()


def test_the_layers_probabilities_are_the_map_without_the_judge_in_its_clouds_and_file(tmp_path):
    """What the surface layer gave each cell, before the judge: the grid's, its map clouds'
    ``layer`` field and an NPZ's read back are the map made without the judge; the judge's
    rescue shows as cells occupied that the layer holds under the threshold."""
    from inhand_mapping.cloud_layouts import map_cells
    from inhand_tools.map_cells import load_map
    judged = session_grid()
    rules = session_grid(SensorModel(cell_judge=False))
    touched = judged.touched_mask()
    np.testing.assert_array_equal(touched, rules.touched_mask())
    layer = judged.layer_probabilities()
    np.testing.assert_allclose(layer, rules.probabilities()[touched], rtol=1e-12)
    p = judged.cells()[1]
    assert np.count_nonzero((p >= 0.8) & (layer < 0.8)) > 0       # rescued
    assert np.count_nonzero(p != layer) == len(judged.layer_overrides()[0])
    cloud = map_cells(judged)
    np.testing.assert_array_equal(cloud['layer'], layer.astype(np.float32))
    np.testing.assert_array_equal(cloud['intensity'], p.astype(np.float32))
    map_io.save_npz(judged, tmp_path / 'judged.npz')
    np.testing.assert_allclose(load_map(tmp_path / 'judged.npz').layer, layer, rtol=1e-12)
    # without the judge, the layer is the map
    np.testing.assert_array_equal(map_cells(rules)['layer'], map_cells(rules)['intensity'])


@pytest.mark.parametrize('form', ['product', 'entropy'])
def test_a_fused_map_carries_the_fusion_of_the_touch_layer_in_its_clouds_and_file(form, tmp_path):
    """Fused with a vision map, the published map is the fusion of the judged touch map;
    where the touch map's judge overrode, its layer is the fusion of the touch layer
    instead, in the fused grid, its map clouds and its file read back; reading the layer
    leaves the fused map as it was."""
    from inhand_common.log_odds import probability
    from inhand_mapping.cloud_layouts import map_cells
    from inhand_mapping.fusion import fuse
    from inhand_mapping.global_map import GlobalMap
    from inhand_tools.map_cells import load_map
    touch = session_grid()
    vision = np.zeros(touch.spec.shape)
    vision[:, :, :20], vision[:, :, 30:] = 0.7, -0.5
    fused_map = GlobalMap(touch, form, 1, (-2.0, 3.5), 'log')
    fused_map.set_vision(vision)
    fused = fused_map.grid()
    expected = fuse(form, touch.log_odds, vision, (-2.0, 3.5), 1, 'log').log_odds
    np.testing.assert_allclose(fused.probabilities(), probability(expected), rtol=1e-12)
    cells, rules = touch.judged
    layer = touch.log_odds.copy()
    layer.reshape(-1)[cells] = rules
    without = probability(fuse(form, layer, vision, (-2.0, 3.5), 1, 'log').log_odds).reshape(-1)
    held, held_layer = fused.layer_overrides()
    np.testing.assert_array_equal(held, np.sort(cells))
    np.testing.assert_allclose(held_layer, without[held], rtol=1e-12)
    np.testing.assert_allclose(fused.probabilities(), probability(expected), rtol=1e-12)
    p, fused_layer = fused.cells()[1], fused.layer_probabilities()
    assert np.count_nonzero((p >= 0.8) & (fused_layer < 0.8)) > 0          # rescued
    np.testing.assert_array_equal(map_cells(fused)['layer'], fused_layer.astype(np.float32))
    map_io.save_npz(fused, tmp_path / 'fused.npz', local_maps=fused_map.local_maps())
    read = load_map(tmp_path / 'fused.npz')
    np.testing.assert_allclose(read.probabilities, p, rtol=1e-12)
    np.testing.assert_allclose(read.layer, fused_layer, rtol=1e-12)


def test_the_judged_map_is_the_same_however_often_and_in_what_pieces_it_is_read():
    once = session_grid().log_odds.copy()
    often = session_grid(chunks=23, read_between=True)
    np.testing.assert_array_equal(often.log_odds, once)
    np.testing.assert_allclose(often.probabilities(), 1.0 / (1.0 + np.exp(-once)), rtol=1e-12)


def resumed(model: SensorModel, folder) -> OccupancyGrid:
    """The session's first 12 s saved, resumed, and the rest after a pause."""
    points, times, fingers = SESSION
    first = times < 12.0
    map_io.save_npz(session_grid(model, until=12.0), folder / 'half.npz')
    grid = OccupancyGrid(SESSION_SPEC, model)
    resume_from(grid, folder / 'half.npz')
    grid.integrate(points[~first], times[~first] + 10.0, fingers[~first])
    grid.flush()
    return grid


def test_a_judged_map_resumed_is_the_judge_over_the_layers_map_resumed(tmp_path):
    # Cells the judge overrode in the file may be the layer's again by the end: a resumed
    # grid must put back what the file says the layer had there, not keep the verdicts.
    (tmp_path / 'on').mkdir()
    (tmp_path / 'off').mkdir()
    judged = resumed(SensorModel(), tmp_path / 'on')
    rules = resumed(SensorModel(cell_judge=False), tmp_path / 'off')
    np.testing.assert_array_equal(judged.touch_evidence, rules.touch_evidence)
    judge = CellJudge(SESSION_SPEC.shape, SESSION_SPEC.origin, SESSION_SPEC.resolution)
    judge.update(rules.touch_evidence.reshape(-1), rules.hits, rules.contact_sum,
                 np.empty(0, dtype=np.int64))
    expected, probability = rules.log_odds.reshape(-1).copy(), rules.probabilities().reshape(-1).copy()
    judge.apply(expected, probability, (0.12, 0.97))
    np.testing.assert_array_equal(judged.log_odds.reshape(-1), expected)
    # and the file said where: loaded, the first half reads as it was saved
    loaded, _ = map_io.load_npz(tmp_path / 'on' / 'half.npz')
    np.testing.assert_array_equal(loaded.log_odds, session_grid(until=12.0).log_odds)
    cells, replaced = loaded.judged
    assert len(cells) > 0 and (loaded.log_odds.reshape(-1)[cells] != replaced).all()


def test_a_settled_copy_carries_the_verdicts_and_what_they_replaced():
    points, times, fingers = SESSION
    grid = OccupancyGrid(SESSION_SPEC, SensorModel())
    grid.integrate(points, times, fingers)
    settled = grid.settled_copy()
    grid.flush()
    np.testing.assert_array_equal(settled.log_odds, grid.log_odds)
