"""The predicted surface with its uncertainty, the next touches, predict_surface, and the
simulator's guided and greedy explorers."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from inhand_shape.implicit_surface import (
    SEEN_POINTS,
    PredictionSettings,
    predict_map_surface,
    predict_surface,
    seen_cells,
)
from inhand_shape.known_shapes import KNOWN_SHAPES, signed_distance
from inhand_shape.next_touch import SEPARATION, next_touches
from inhand_shape.superquadric import Superquadric
from inhand_shape.surface_mesh import oriented_normals
from inhand_shape.touch_guidance import GUIDANCE_PARAMETERS, MODE_ORIENTATION, guide, std_colours
from pose_sessions import fibonacci_sphere, sphere_session, write_pose_bag

WORKSPACE = Path(__file__).resolve().parents[1]
RESOLUTION = 0.005
RADIUS = 0.04


def _lattice(low: float = -0.07, high: float = 0.07) -> np.ndarray:
    axis = np.arange(low, high, RESOLUTION) + RESOLUTION / 2
    return np.stack(np.meshgrid(axis, axis, axis, indexing='ij'), axis=-1).reshape(-1, 3)


def _sphere_cap(z_above: float = -0.01) -> tuple[np.ndarray, np.ndarray]:
    """Cells of a 4 cm sphere's shell above ``z_above`` (what fingers touched) and the free
    cells around its top (where they passed through air)."""
    points = _lattice()
    r = np.linalg.norm(points, axis=1)
    shell = (np.abs(r - RADIUS) < 0.6 * RESOLUTION) & (points[:, 2] > z_above)
    free = (r > RADIUS + 2 * RESOLUTION) & (r < RADIUS + 4 * RESOLUTION) & (points[:, 2] > 0.0)
    return points[shell], points[free]


def test_the_predicted_surface_follows_the_touched_cap_and_closes_the_sphere_unsure_where_untouched():
    cells, free = _sphere_cap()
    # the cap's superquadric is its sphere, and the whole sphere is within 5 cm of the cap:
    # let the prior reach that far
    surface = predict_surface(cells, RESOLUTION, free,
                              PredictionSettings(prior='superquadric', prior_reach=0.05))
    assert not surface.empty
    error = np.abs(np.linalg.norm(surface.vertices, axis=1) - RADIUS)
    top, bottom = surface.vertices[:, 2] > 0.0, surface.vertices[:, 2] < -0.025
    # where touched: on the sphere to about a millimetre, and surer of it ...
    assert error[top].mean() < 0.0015
    # ... than where not: closed by the superquadric the cap belongs to, but unsure there,
    # as unsure as the prior
    assert bottom.any() and error[bottom].mean() < 0.006
    assert np.median(surface.vertex_std[bottom]) > 2 * np.median(surface.vertex_std[top])
    assert np.isclose(np.median(surface.process_std[bottom]), surface.settings.signal_std, rtol=0.2)
    # ... and the farther from every touched cell, the less sure: beyond what the process
    # alone says (at most signal_std), by `extrapolation` per metre
    far = np.linalg.norm(surface.vertices[:, None, :] - cells[None, ::7, :], axis=2).min(axis=1)
    beyond = np.maximum(far - surface.settings.length_scale, 0.0)
    assert np.all(surface.vertex_std >= surface.process_std - 1e-12)
    assert np.median(surface.vertex_std[beyond > 0.03]) > 2 * surface.settings.signal_std
    assert (beyond == 0).any()
    assert np.allclose(surface.vertex_std[beyond == 0], surface.process_std[beyond == 0], atol=1e-9)
    # calibrated: the true error within two standard deviations over most of the surface
    areas = surface.vertex_areas()
    assert areas[error <= 2 * surface.vertex_std].sum() / areas.sum() > 0.9
    # outward faces, and normals to match
    normals = surface.vertex_normals()
    assert np.mean(np.einsum('ij,ij->i', normals, surface.vertices) > 0) > 0.95
    # the grid points next to the surface carry a standard deviation too
    band = surface.band_std()
    assert len(band) == len(surface.band_points) > 0 and np.all(band >= 0)
    assert surface.process.std(surface.band_points).max() <= 0.011   # the process's own
    assert band.min() < surface.settings.signal_std < band.max()


def test_the_completed_surface_is_the_prediction_near_the_touched_cells_with_its_std():
    # a cap touched in two bands with an untouched gap between them, on the sphere's top
    cells, free = _sphere_cap(z_above=0.0)
    band = (cells[:, 2] < 0.015) | (cells[:, 2] > 0.025)
    # the prior the cap's sphere, reaching round it (as in the test above)
    surface = predict_surface(cells[band], RESOLUTION, free,
                              PredictionSettings(prior='superquadric', prior_reach=0.05))
    completed = surface.completed()
    reach = surface.settings.completed_reach
    assert not completed.empty and 0 < len(completed.faces) < len(surface.faces)
    # each of its triangles has its centroid within reach of a touched cell ...
    from scipy.spatial import cKDTree
    centroids = completed.vertices[completed.faces].mean(axis=1)
    assert cKDTree(cells[band]).query(centroids)[0].max() <= reach + 1e-12
    # ... the gap between the bands is bridged, the prediction far below them is not kept
    r = np.linalg.norm(completed.vertices, axis=1)
    gap = (completed.vertices[:, 2] > 0.016) & (completed.vertices[:, 2] < 0.024)
    assert gap.any() and np.all(np.abs(r[gap] - RADIUS) < 0.004)
    assert completed.vertices[:, 2].min() > -reach - RESOLUTION
    assert surface.vertices[:, 2].min() < -0.02
    # the same vertices and standard deviations as the prediction's, and a valid mesh
    kept = cKDTree(surface.vertices).query(completed.vertices)
    assert np.all(kept[0] == 0)
    assert np.array_equal(completed.vertex_std, surface.vertex_std[kept[1]])
    assert np.array_equal(completed.process_std, surface.process_std[kept[1]])
    assert completed.faces.max() < len(completed.vertices) and completed.faces.min() >= 0
    # a reach past everything keeps the whole prediction
    whole = replace(surface, settings=replace(surface.settings, completed_reach=1.0)).completed()
    assert len(whole.faces) == len(surface.faces)


def test_what_a_camera_saw_is_surface_and_the_space_in_front_of_it_free():
    touched, free = _sphere_cap(z_above=0.02)        # a small cap touched at the top
    camera = np.array([0.3, 0.0, 0.0])               # the camera looks at the sphere's +x side
    points = fibonacci_sphere(40_000, RADIUS)
    seen = points[(points[:, 0] > 0.01) & (points @ (camera / 0.3) > 0)]
    map_cells = np.concatenate([touched, free])
    known = map_cells
    surface, empty = seen_cells(seen, camera, map_cells, RESOLUTION, known, touched)
    # on the sphere, in the map's lattice, none a touched or free cell
    assert len(surface) > 50
    assert np.abs(np.linalg.norm(surface, axis=1) - RADIUS).max() < 0.0045
    phase = ((surface - map_cells[0]) / RESOLUTION) % 1.0
    assert np.abs((phase + 0.5) % 1.0 - 0.5).max() < 1e-6
    gap = np.abs(surface[:, None, :] - map_cells[None, :, :]).max(axis=2).min(axis=1)
    assert gap.min() > RESOLUTION / 2
    # the free cells lie in front of the seen side, outside the sphere, towards the camera
    radius = np.linalg.norm(empty, axis=1)
    assert len(empty) > 50 and radius.min() > RADIUS - RESOLUTION / 2
    assert np.median(radius) > RADIUS + RESOLUTION and np.all(empty[:, 0] > 0)
    # a cell with fewer than SEEN_POINTS points is a mismatch, not a surface
    lone = np.array([[0.0, 0.0, -0.1]])
    assert len(seen_cells(np.repeat(lone, SEEN_POINTS - 1, axis=0), None, map_cells, RESOLUTION,
                          known)[0]) == 0
    assert len(seen_cells(np.repeat(lone, SEEN_POINTS, axis=0), None, map_cells, RESOLUTION,
                          known)[0]) == 1
    # a camera point behind a touched surface along its ray (dark glass reads behind it) is
    # not surface: the touch map wins
    behind = np.repeat([[0.0, 0.0, RADIUS - 0.012]], 10, axis=0)
    assert len(seen_cells(behind, np.array([0.0, 0.0, 0.3]), map_cells, RESOLUTION, known,
                          touched)[0]) == 0
    assert len(seen_cells(behind, np.array([0.0, 0.0, 0.3]), map_cells, RESOLUTION, known)[0]) == 1


def test_the_completed_surface_follows_what_the_camera_saw_where_no_finger_went():
    touched, free = _sphere_cap(z_above=0.02)
    centres = np.concatenate([touched, free])
    probabilities = np.concatenate([np.full(len(touched), 0.9), np.full(len(free), 0.3)])
    camera = np.array([0.3, 0.0, -0.1])
    points = fibonacci_sphere(40_000, RADIUS)
    seen = points[np.einsum('ij,ij->i', points, camera - points) > 0]     # the side it faces
    alone = predict_map_surface(centres, probabilities, RESOLUTION)
    both = predict_map_surface(centres, probabilities, RESOLUTION, seen=seen, seen_from=camera)

    def seen_side(surface) -> np.ndarray:
        return (surface.vertices[:, 0] > 0.02) & (surface.vertices[:, 2] < 0.0)

    # where only the camera saw the sphere, the completed surface is on it to about a
    # millimetre and surer than the prior; from the cap alone there is no surface there (the
    # prior reaches only prior_reach past the touched cells)
    side = seen_side(both)
    assert side.sum() > 20 and not seen_side(alone).any()
    assert np.abs(np.linalg.norm(both.vertices[side], axis=1) - RADIUS).mean() < 0.002
    assert np.median(both.vertex_std[side]) < both.settings.signal_std


def test_the_prior_is_pulled_back_where_it_reaches_past_the_touched_cells_but_not_inside():
    from inhand_shape.implicit_surface import SurfacePrior, _PriorMean
    sphere = SurfacePrior(Superquadric(np.full(3, RADIUS), (1.0, 1.0), np.eye(3), np.zeros(3)))
    patch = np.array([[x, y, RADIUS] for x in (-0.005, 0.0, 0.005) for y in (-0.005, 0.0, 0.005)])
    mean = _PriorMean(sphere, patch, reach=0.02)
    points = np.array([[0.0, 0.0, -RADIUS],      # the far side of the sphere: 8 cm from the patch
                       [0.0, 0.0, 0.002],        # its middle: as deep as it is far from the patch
                       [0.0, 0.0, RADIUS - 0.005]])
    values = mean(points)
    assert np.isclose(values[0], 0.08 - 0.02)           # outside, by the excess over the reach
    assert np.isclose(values[1], -(RADIUS - 0.002), atol=1e-3)    # inside, as the prior says
    assert np.isclose(values[2], -0.005, atol=1e-3)


def test_an_ellipsoid_prior_cannot_close_a_cap_as_the_superquadric_does():
    cells, free = _sphere_cap()
    fitted = predict_surface(cells, RESOLUTION, free, PredictionSettings(prior='superquadric',
                                                                         prior_reach=0.05))
    ellipsoid = predict_surface(cells, RESOLUTION, free, PredictionSettings(prior_reach=0.05))

    def bottom_error(surface):
        low = surface.vertices[:, 2] < -0.025
        return np.abs(np.linalg.norm(surface.vertices[low], axis=1) - RADIUS).mean() if low.any() \
            else np.inf
    assert bottom_error(fitted) < bottom_error(ellipsoid)


def test_too_few_cells_give_an_empty_surface_and_bad_settings_are_refused_by_name():
    assert predict_surface(np.zeros((3, 3)), RESOLUTION).empty
    assert next_touches(predict_surface(np.zeros((3, 3)), RESOLUTION), RESOLUTION) == []
    with pytest.raises(ValueError, match=r"'length_scale' = 0.5 is refused: allowed is a number in "
                                         r"\[0.005, 0.2\]"):
        PredictionSettings(length_scale=0.5)
    with pytest.raises(ValueError, match=r"'prior' = 'sphere' is refused: allowed is one of 'ellipsoid'"):
        PredictionSettings(prior='sphere')
    with pytest.raises(ValueError, match='resolution'):
        predict_surface(np.zeros((20, 3)), 0.0)


def test_next_touches_go_where_the_surface_is_unknown_into_it_and_never_below_the_support():
    cells, free = _sphere_cap(z_above=0.0)
    # the sphere predicted whole (its superquadric) from its upper half
    surface = predict_surface(cells, RESOLUTION, free,
                              PredictionSettings(prior='superquadric', prior_reach=0.05))
    support = -0.03
    touches = next_touches(surface, RESOLUTION, 5, support=support)
    assert len(touches) == 5
    gains = [t.gain for t in touches]
    assert gains == sorted(gains, reverse=True) and gains[0] > 0
    # the best ones are on the untouched lower half, none within 1 cm of the support
    assert touches[0].position[2] < 0.0
    assert all(t.position[2] > support + 0.01 for t in touches)
    for t in touches:
        assert np.isclose(np.linalg.norm(t.approach), 1.0)
        assert t.approach @ t.position < 0          # moving into the sphere
    # a ranked handful of different places, not neighbours of one
    positions = np.array([t.position for t in touches])
    gaps = np.linalg.norm(positions[:, None] - positions[None], axis=2) + np.eye(5)
    assert gaps.min() >= max(SEPARATION, surface.settings.length_scale) - 1e-9
    # a held region rules out what it covers
    held = [(touches[0].position, 0.02)]
    again = next_touches(surface, RESOLUTION, 5, support=support, held=held)
    assert all(np.linalg.norm(t.position - touches[0].position) > 0.02 for t in again)


def test_normals_point_outward_even_where_the_farthest_cell_is_a_thin_handle():
    """A hammer: the cell farthest from the centre is at the end of the shaft, whose normal
    is sideways; every component still ends up facing outward."""
    shape = KNOWN_SHAPES['hammer']
    parts = tuple(Superquadric(np.asarray(p.size), p.shape, np.asarray(p.rotation),
                               np.asarray(p.centre)) for p in shape.parts)
    points = _lattice(-0.15, 0.15)
    distance = signed_distance(parts, points)
    cells = points[np.abs(distance) < 0.6 * RESOLUTION]
    normals = oriented_normals(cells, RESOLUTION)
    step = 1e-4
    gradient = np.stack([(signed_distance(parts, cells + step * e) - signed_distance(parts, cells - step * e))
                         for e in np.eye(3)], axis=1)
    agree = np.einsum('ij,ij->i', normals, gradient) > 0
    assert agree.mean() > 0.9


def test_normals_stay_consistent_along_a_long_bent_strip_hundreds_of_cells_from_its_root():
    """A half ring 1 m round, one cell thick: each cell's sign is carried from the root along
    a spanning tree hundreds of levels deep; every normal must end up facing away from the
    ring's centre, none flipped part way."""
    angle = np.arange(0.0, np.pi, RESOLUTION / 0.3)
    ring = np.stack([0.3 * np.cos(angle), 0.3 * np.sin(angle)], axis=1)
    cells = np.concatenate([np.column_stack([ring, np.full(len(ring), z)])
                            for z in RESOLUTION * np.arange(4)])
    normals = oriented_normals(cells, RESOLUTION)
    radial = cells[:, :2] / np.linalg.norm(cells[:, :2], axis=1, keepdims=True)
    assert len(cells) > 700
    assert np.all(np.einsum('ij,ij->i', normals[:, :2], radial) > 0.9)


def test_the_std_colour_scale_runs_dark_to_yellow_and_the_live_page_uses_the_same_stops():
    top = 0.01
    colours = std_colours(np.array([0.0, 0.25, 0.5, 1.0, 3.0]) * top, top)
    assert np.allclose(colours[0], np.array([68, 1, 84]) / 255)       # dark blue: known
    assert np.allclose(colours[3], np.array([253, 231, 37]) / 255)    # yellow: a guess
    assert np.allclose(colours[4], colours[3])                         # clipped beyond the top
    assert np.all(np.diff(colours.sum(axis=1)[:4]) > 0)               # brighter as it grows
    page = (Path(__file__).resolve().parents[1] / 'src' / 'inhand_view' / 'inhand_view' / 'web'
            / 'view.js').read_text()
    stops = json.loads(page.split('const VIRIDIS = ')[1].split(';')[0])
    assert np.allclose(std_colours(np.linspace(0.0, top, 5), top) * 255, stops)


def test_a_static_object_gets_no_touch_near_its_support_with_the_tracker_frames_z_down():
    cells, _ = _sphere_cap(z_above=-0.03)
    parameters = {spec.name: spec.default for spec in GUIDANCE_PARAMETERS}
    # an object standing on a support, tracker frame (z down): its lowest cell is the largest z
    turned = cells * np.array([1.0, 1.0, -1.0])
    up, on_support = MODE_ORIENTATION['static']
    guidance = guide(turned, np.full(len(turned), 0.9), RESOLUTION, parameters, up=up,
                     on_support=on_support, frame_id='object')
    assert np.isclose(guidance.support, -turned[:, 2].max())
    clearance = parameters['support_clearance']
    assert all(-t.position[2] > guidance.support + clearance for t in guidance.suggestions)
    best = guidance.suggestions[0]
    assert guidance.as_dict()['suggestions'][0]['position'] == [round(float(v), 5) for v in best.position]


@pytest.fixture(scope='module')
def cat_map(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp('explore')
    subprocess.run([sys.executable, '-m', 'inhand_tools.commands.build_map',
                    str(WORKSPACE / 'bags' / 'cat_static'), '--config',
                    str(WORKSPACE / 'config' / 'mapping_static.yaml'), '--output-dir', str(folder),
                    '--name', 'cat', '--quiet'], check=True, capture_output=True)
    return folder / 'cat.npz'


def test_predict_surface_writes_the_surface_with_its_std_the_ranked_touches_and_a_picture(cat_map, tmp_path):
    run = subprocess.run([sys.executable, '-m', 'inhand_tools.commands.predict_surface', str(cat_map),
                          '--output-dir', str(tmp_path), '--name', 'c', '--set', 'suggestions=4'],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert 'best next touch' in run.stdout
    for suffix in ('_predicted.ply', '_completed.ply', '_next_touch.yaml', '_uncertainty.png'):
        assert (tmp_path / f'c{suffix}').stat().st_size > 0
    import trimesh
    mesh = trimesh.load(tmp_path / 'c_predicted.ply', process=False)
    std = np.asarray(mesh.metadata['_ply_raw']['vertex']['data']['std'])
    assert len(std) == len(mesh.vertices) > 100 and np.all(std >= 0) and std.max() < 0.05
    # the completed surface: the part of the prediction near the touched cells, with its std
    completed = trimesh.load(tmp_path / 'c_completed.ply', process=False)
    assert 0 < len(completed.faces) < len(mesh.faces)
    assert len(np.asarray(completed.metadata['_ply_raw']['vertex']['data']['std'])) == len(completed.vertices)
    answer = yaml.safe_load((tmp_path / 'c_next_touch.yaml').read_text())
    suggestions = answer['suggestions']
    assert len(suggestions) == 4 and answer['up'] == [0.0, 0.0, -1.0]
    assert [s['gain'] for s in suggestions] == sorted((s['gain'] for s in suggestions), reverse=True)
    for s in suggestions:
        assert len(s['position']) == 3 and np.isclose(np.linalg.norm(s['approach']), 1.0, atol=1e-3)
        # the cat stands on the table: nothing suggested within 1 cm of its lowest cell
        assert -s['position'][2] > answer['support'] + 0.01 - 1e-6
    # a bad parameter: its name and range, and nothing written
    bad = subprocess.run([sys.executable, '-m', 'inhand_tools.commands.predict_surface', str(cat_map),
                          '--output-dir', str(tmp_path / 'bad'), '--set', 'length_scale=2'],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "'length_scale'" in bad.stderr and '0.2' in bad.stderr
    assert not (tmp_path / 'bad').exists()


def test_predict_surface_takes_what_the_bags_camera_saw(cat_map, tmp_path):
    base = [sys.executable, '-m', 'inhand_tools.commands.predict_surface', str(cat_map),
            '--output-dir', str(tmp_path), '--config', str(WORKSPACE / 'config' / 'mapping_static.yaml'),
            '--config', str(WORKSPACE / 'config' / 'stereo.yaml')]
    run = subprocess.run([*base, '--name', 'seen', '--bag', str(WORKSPACE / 'bags' / 'cat_static')],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert re.search(r'1 stereo pair\(s\), [\d,]+ points of the object', run.stdout)
    alone = subprocess.run([*base, '--name', 'alone'], capture_output=True, text=True)
    assert alone.returncode == 0, alone.stderr
    import trimesh
    seen = trimesh.load(tmp_path / 'seen_predicted.ply', process=False)
    touch = trimesh.load(tmp_path / 'alone_predicted.ply', process=False)
    assert len(seen.vertices) > 100 and not np.array_equal(seen.vertices, touch.vertices)
    # a bag without images: one line, the touch map alone; a file that is no bag: refused
    frames, _ = sphere_session(seconds=0.5, surface_points=10, moving=False)
    plain_bag = write_pose_bag(tmp_path / 'no_images', frames)
    plain = subprocess.run([*base, '--name', 'plain', '--bag', str(plain_bag)], capture_output=True,
                           text=True)
    assert plain.returncode == 0, plain.stderr
    assert 'no stereo pair in the bag; the touch map alone' in plain.stdout
    assert (tmp_path / 'plain_predicted.ply').exists()
    wrong = subprocess.run([*base, '--name', 'wrong', '--bag', str(cat_map)], capture_output=True,
                           text=True)
    assert wrong.returncode == 2 and str(cat_map) in wrong.stderr
    assert not (tmp_path / 'wrong_predicted.ply').exists()


def test_guided_and_greedy_explorers_choose_other_strokes_and_random_sessions_stay_as_they_were():
    from inhand_sim.exploration import ExplorationSettings, parse_hand_setting
    from inhand_sim.session import SessionSettings, simulate
    base = SessionSettings(object_name='box', static=True, rate=15.0, duration=40.0, seed=3)
    assert 'explorer' not in json.loads(base.to_json())['exploration']
    assert parse_hand_setting('explorer=guided') == ('explorer', 'guided')
    with pytest.raises(ValueError, match='random, guided, greedy'):
        parse_hand_setting('explorer=smart')
    sessions = {kind: simulate(replace(base, exploration=replace(ExplorationSettings(), explorer=kind)))
                for kind in ('random', 'guided', 'greedy')}
    strokes = {kind: [e for e in s.exploration.events if e[1] == 'stroke'] for kind, s in sessions.items()}
    assert all(len(v) >= 6 for v in strokes.values())
    first = {kind: s.exploration.positions[:, s.exploration.contact.any(axis=0)]
             for kind, s in sessions.items()}
    assert not np.array_equal(first['random'], first['guided'])
    assert not np.array_equal(first['random'], first['greedy'])
    # the same settings give the same session
    again = simulate(replace(base, exploration=replace(ExplorationSettings(), explorer='guided')))
    assert np.array_equal(again.poses, sessions['guided'].poses)


def test_the_guide_sends_fingers_to_its_suggestions():
    from inhand_sim.guidance import START_REACH, StrokeGuide
    cells, _ = _sphere_cap(z_above=0.0)
    guide_ = StrokeGuide('guided', support=None)
    guide_.touched(cells, stroke=True)
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(400, 3))
    starts = RADIUS * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    chosen = guide_.choose(starts, np.ones(len(starts), dtype=bool))
    assert chosen is not None and guide_.plans == 1
    # the start is within reach of the best suggestion, on the untouched half
    assert starts[chosen][2] < 0.01
    assert guide_.surface is not None
    greedy = StrokeGuide('greedy', support=None)
    greedy.touched(cells, stroke=True)
    far = greedy.choose(starts, np.ones(len(starts), dtype=bool))
    assert starts[far][2] < -0.03          # the farthest from everything touched: the bottom
    assert greedy.steering() is None       # the baseline is not steered
    with pytest.raises(ValueError):
        StrokeGuide('random', support=None)
    assert START_REACH > 0


def test_the_guide_steers_a_stroke_away_from_the_touched_surface_and_its_own_trail():
    from inhand_sim.guidance import REPEL_REACH, TRAIL_SKIP, StrokeGuide
    cells, _ = _sphere_cap(z_above=0.0)
    guide_ = StrokeGuide('guided', support=None)
    assert guide_.steering() is None       # nothing touched yet: the person strokes
    guide_.touched(cells, stroke=True)
    away = guide_.steering()
    assert away is not None
    # just below the touched cap's edge: pushed down, away from it, hard (one-sided)
    edge = RADIUS * np.array([[np.cos(-0.15), 0.0, np.sin(-0.15)]])
    push = away(edge)[0]
    assert push[2] < 0 and np.linalg.norm(push) > 0.5
    # far below it, in untouched surface: no push, the stroke keeps its heading
    bottom = np.array([[0.0, 0.0, -RADIUS]])
    assert np.allclose(away(bottom), 0.0)
    # the stroke's own trail pushes it on once it is TRAIL_SKIP steps behind
    steering = guide_.steering()
    assert steering is not None
    step = np.array([0.002, 0.0, 0.0])
    for k in range(TRAIL_SKIP + 1):
        ahead = steering(bottom + k * step)
    assert ahead[0, 0] > 0 and np.isclose(np.linalg.norm(ahead[0, 1:]), 0.0)
    assert TRAIL_SKIP * np.linalg.norm(step) < REPEL_REACH


def test_a_steered_stroke_goes_where_its_guide_sends_it_on_the_surface():
    """The guided explorer's strokes (exploration._integrate_strokes with a steering): from
    the same place on a box's side, sent up a stroke climbs, sent down it descends, and it
    stays on the surface either way."""
    from inhand_sim.catalogue import load_object
    from inhand_sim.exploration import _STEERED, ExplorationSettings, _integrate_strokes, _Surroundings
    from inhand_sim.objects import HeldRegion
    box = load_object('box')
    settings = ExplorationSettings()
    start = box.project_to_surface((box.centre + np.array([0.0, box.size[1], 0.0]))[None])
    normal = box.normals(start)
    nobody = HeldRegion('nobody', (), ())
    ends = {}
    for name, direction in (('up', (0.0, 0.0, 1.0)), ('down', (0.0, 0.0, -1.0))):
        path, _, steps = _integrate_strokes(
            box, _Surroundings(box, False), nobody, False, settings, start, normal,
            np.array([[1.0, 0.0, 0.0]]), np.array([_STEERED]), np.random.default_rng(0),
            lambda points, d=direction: np.tile(np.asarray(d), (len(points), 1)), length=0.04)
        assert steps[0] > 10 and np.abs(box.sdf(path[0])).max() < 1e-6
        ends[name] = path[0, steps[0], 2] - start[0, 2]
    assert ends['up'] > 0.01 and ends['down'] < -0.01
