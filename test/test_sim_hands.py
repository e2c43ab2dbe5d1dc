"""Other hands than the default one (inhand_sim.exploration's hand properties) and the shapes a
touch map finds hard (inhand_sim.catalogue.SHAPES): each property does what it says, and the
default hand is the one the bundled bags were made with."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from inhand_sim.catalogue import SHAPE_NAMES, load_object
from inhand_sim.commands.simulate_session import make_parser
from inhand_sim.exploration import (
    HAND_DEFAULTS,
    SAMPLE_KINDS,
    ExplorationSettings,
    explore,
    parse_hand_setting,
    speed_range_around,
)
from inhand_sim.objects import get_object
from inhand_sim.session import SessionSettings

RATE = 240.0
FAST = replace(ExplorationSettings(pool_size=150), speed_range=speed_range_around(0.10))
KIND = {name: SAMPLE_KINDS.index(name) for name in SAMPLE_KINDS}


@pytest.fixture(scope='module')
def cat():
    return get_object('cat')


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) index pairs of the runs of True in a 1-D mask."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return list(zip(edges[::2], edges[1::2]))


def test_stroke_lengths_follow_the_length_range(cat):
    settings = replace(FAST, stroke_length_range=(0.03, 0.06))
    ex = explore(cat, 30.0, RATE, np.random.default_rng(2), settings)
    lengths = []
    for f in range(3):
        for a, b in runs(ex.kind[f] == KIND['stroke']):
            ids = ex.stroke[f, a:b]
            if b - a > 10 and len(set(ids)) == 1:
                lengths.append(np.linalg.norm(np.diff(ex.positions[f, a:b], axis=0), axis=1).sum())
    assert len(lengths) > 20
    # a stroke may end early at an obstacle, never much past its planned length
    assert max(lengths) < 0.06 * 1.15
    assert np.median(lengths) > 0.025
    default = explore(cat, 30.0, RATE, np.random.default_rng(2), FAST)
    assert np.count_nonzero(np.diff(default.stroke[0]) != 0) < np.count_nonzero(
        np.diff(ex.stroke[0]) != 0), 'short strokes: more of them in the same time'


def test_lift_offs_rise_as_high_and_as_fast_as_asked(cat):
    settings = replace(FAST, liftoff_height_range=(0.02, 0.04), liftoff_speed_range=(0.2, 0.3))
    ex = explore(cat, 30.0, RATE, np.random.default_rng(3), settings)
    heights = cat.sdf(ex.positions.reshape(-1, 3)).reshape(3, -1)
    assert heights[~ex.contact].max() > 0.02
    # from the surface to the hover height at 0.2-0.3 m/s (mean), so up to 0.6 m/s at the top
    rises = []
    for f in range(3):
        for a, b in runs((ex.kind[f] == KIND['transit']) & (heights[f] < 0.015)):
            if 3 < b - a < 40:
                steps = np.linalg.norm(np.diff(ex.positions[f, a:b], axis=0), axis=1) * RATE
                rises.append(steps.max())
    assert len(rises) > 10
    assert 0.15 < np.median(rises) < 0.7


def test_oblique_lift_offs_leave_the_normal_by_the_angle_asked(cat):
    def mean_angle(angles):
        settings = replace(FAST, liftoff_height_range=(0.02, 0.03), liftoff_angle_range=angles,
                           lift_rate=0.0)
        ex = explore(cat, 30.0, RATE, np.random.default_rng(5), settings)
        found = []
        for f in range(3):
            for _, b in runs(ex.contact[f]):
                if b + 20 < ex.positions.shape[1] and ex.kind[f, b] == KIND['transit']:
                    foot = ex.positions[f, b - 1]
                    up = ex.positions[f, b + 20] - foot
                    normal = cat.normals(foot[None])[0]
                    found.append(np.degrees(np.arccos(np.clip(
                        up @ normal / np.linalg.norm(up), -1, 1))))
        return np.median(found)
    assert mean_angle((0.0, 0.0)) < 15.0
    assert 40.0 < mean_angle((55.0, 65.0)) < 75.0


def test_hovers_stay_close_above_the_surface_without_touching(cat):
    settings = replace(FAST, hover_probability=0.5, hover_height_range=(0.003, 0.005))
    ex = explore(cat, 30.0, RATE, np.random.default_rng(6), settings)
    hover = ex.kind == KIND['hover']
    assert hover.sum() > 200
    assert not ex.contact[hover].any()
    heights = cat.sdf(ex.positions[hover])
    assert np.median(heights) == pytest.approx(0.004, abs=0.0012)
    assert heights.max() < 0.008


def test_tremor_moves_the_contacts_along_the_surface(cat):
    still = explore(cat, 10.0, RATE, np.random.default_rng(7), FAST)
    shaking = explore(cat, 10.0, RATE, np.random.default_rng(7),
                      replace(FAST, tremor_amplitude=0.001, tremor_frequency=10.0))
    both = still.contact & shaking.contact
    moved = np.linalg.norm(shaking.positions[both] - still.positions[both], axis=1)
    assert 0.0003 < np.median(moved) < 0.002
    assert np.abs(cat.sdf(shaking.positions[shaking.contact])).max() < 1e-6


def test_bell_strokes_start_and_end_at_rest(cat):
    settings = replace(FAST, speed_profile='bell', stroke_length_range=(0.04, 0.08))
    ex = explore(cat, 30.0, RATE, np.random.default_rng(8), settings)
    ends, middles = [], []
    for f in range(3):
        for a, b in runs(ex.kind[f] == KIND['stroke']):
            if b - a > 40 and len(set(ex.stroke[f, a:b])) == 1:
                speed = np.linalg.norm(np.diff(ex.positions[f, a:b], axis=0), axis=1) * RATE
                ends.append(max(speed[0], speed[-1]))
                middles.append(speed[len(speed) // 2])
    assert len(ends) > 10
    assert np.median(ends) < 0.3 * np.median(middles)


def test_the_holding_hands_region_grows_with_its_scale(cat):
    small = explore(cat, 30.0, RATE, np.random.default_rng(9), FAST)
    large = explore(cat, 30.0, RATE, np.random.default_rng(9), replace(FAST, held_scale=2.0))
    grip = cat.static_grip
    centre, radius = np.asarray(grip.centres[0]), grip.radii[0]

    def closest(ex):
        return np.linalg.norm(ex.positions[ex.contact] - centre, axis=1).min()
    assert closest(small) >= radius * 0.99
    assert closest(large) >= 2.0 * radius * 0.99


def test_the_first_strokes_start_in_the_focus_and_it_is_explored_most(cat):
    places, _ = cat.sample_surface(2000, np.random.default_rng(4))
    centre = places[np.argmax(places[:, 0])]          # the figure's far end in x
    radius = 0.03
    focused = explore(cat, 30.0, RATE, np.random.default_rng(5),
                      replace(FAST, focus_centre=tuple(centre), focus_radius=radius))
    plain = explore(cat, 30.0, RATE, np.random.default_rng(5), FAST)
    for f in range(3):
        first = np.flatnonzero(focused.kind[f] == KIND['stroke'])[0]
        assert np.linalg.norm(focused.positions[f, first] - centre) <= radius + 0.005

    def share(ex):
        """Of the strokes' starts, the share in the focus."""
        starts = [ex.positions[f, a] for f in range(3) for a, _ in runs(ex.kind[f] == KIND['stroke'])]
        return np.mean(np.linalg.norm(np.array(starts) - centre, axis=1) <= radius)
    assert share(focused) > 2 * share(plain)


def test_hand_settings_are_parsed_with_their_ranges_and_refused_by_name():
    assert parse_hand_setting('liftoff_height_range=0.01,0.04') == ('liftoff_height_range',
                                                                    (0.01, 0.04))
    assert parse_hand_setting('speed_profile=bell') == ('speed_profile', 'bell')
    assert parse_hand_setting('tremor_amplitude=0.0005') == ('tremor_amplitude', 0.0005)
    assert parse_hand_setting('liftoff_speed_range=none') == ('liftoff_speed_range', None)
    assert parse_hand_setting('focus_centre=0.03,0,-0.01') == ('focus_centre', (0.03, 0.0, -0.01))
    for bad, says in (('lift_height=0.01', 'NAME one of'), ('speed_profile=jerky', 'wave, bell'),
                      ('liftoff_height_range=0.04,0.01', 'a <= b'),
                      ('tremor_amplitude=1', '[0, 0.01] m'), ('hover_probability=x', 'a number'),
                      ('focus_centre=0.1,0', 'three numbers')):
        with pytest.raises(ValueError, match=says.replace('[', r'\[').replace(']', r'\]')):
            parse_hand_setting(bad)
    parser = make_parser()
    base = ['--object', 'cat', '--static', '--rate', '30', '--duration', '2', '--seed', '1',
            '--output', 'x']
    args = parser.parse_args(base + ['--hand', 'held_scale=1.5', '--hand', 'speed_profile=bell'])
    assert dict(args.hand) == {'held_scale': 1.5, 'speed_profile': 'bell'}
    with pytest.raises(SystemExit):
        parser.parse_args(base + ['--hand', 'held_scale=-1'])


def test_a_default_hand_writes_no_hand_keys_and_another_writes_its_own():
    plain = json.loads(SessionSettings().to_json())['exploration']
    assert not set(HAND_DEFAULTS) & set(plain)
    other = SessionSettings(exploration=replace(ExplorationSettings(), hover_probability=0.2))
    assert json.loads(other.to_json())['exploration']['hover_probability'] == 0.2


@pytest.mark.parametrize('name', SHAPE_NAMES)
def test_the_shapes_are_closed_objects_of_their_size(name):
    obj = load_object(name)
    expected = {'plate': (0.14, 0.09, 0.02), 'rod': (0.20, 0.025, 0.025),
                'box': (0.08, 0.06, 0.05), 'large': (0.20, 0.14, 0.12)}[name]
    assert obj.size == pytest.approx(expected, abs=0.002)
    points, normals = obj.sample_surface(2000, np.random.default_rng(1))
    assert np.abs(obj.sdf(points)).max() < 0.0006
    assert (obj.sdf(points + 0.003 * normals) > 0.002).mean() > 0.97
    ex = explore(obj, 6.0, 30.0, np.random.default_rng(1), FAST)
    assert ex.contact.sum() > 100
