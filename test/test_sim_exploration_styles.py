"""Ways of exploring the simulator offers: stroke speed, tracker rates, lifts that rise and
come back continuously (inhand_sim.exploration, .session, simulate_session)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from inhand_sim.commands.simulate_session import make_parser
from inhand_sim.exploration import SAMPLE_KINDS, ExplorationSettings, explore, speed_range_around
from inhand_sim.objects import get_object
from inhand_sim.session import SessionSettings, simulate, write_session

FAST = ExplorationSettings(pool_size=150)
STROKE = SAMPLE_KINDS.index('stroke')


@pytest.fixture(scope='module')
def cat():
    return get_object('cat')


def sliding_speeds(exploration, rate: float) -> np.ndarray:
    """Speeds (m/s) between consecutive frames of one stroke, every finger."""
    speeds = []
    for f in range(exploration.positions.shape[0]):
        sid, kind = exploration.stroke[f], exploration.kind[f]
        same = (sid[1:] == sid[:-1]) & (sid[1:] >= 0) & (kind[1:] == STROKE) & (kind[:-1] == STROKE)
        steps = np.linalg.norm(np.diff(exploration.positions[f], axis=0), axis=1)
        speeds.append(steps[same] * rate)
    return np.concatenate(speeds)


@pytest.mark.parametrize('cm_per_s', [2.0, 15.0])
def test_the_mean_contact_speed_is_the_one_asked_for(cat, cm_per_s):
    settings = replace(FAST, speed_range=speed_range_around(cm_per_s / 100.0))
    ex = explore(cat, 12.0, 240.0, np.random.default_rng(4), settings)
    speeds = sliding_speeds(ex, 240.0)
    assert len(speeds) > 2000
    assert np.mean(speeds) == pytest.approx(cm_per_s / 100.0, rel=0.2)
    # and it varies within the strokes (speed_variation), not one constant speed
    assert np.std(speeds) > 0.1 * np.mean(speeds)


def test_the_speed_option_sets_the_stroke_speed_range_and_the_default_keeps_2_to_5():
    parser = make_parser()
    base = ['--object', 'cat', '--static', '--rate', '15', '--duration', '2', '--seed', '1',
            '--output', 'x']
    assert parser.parse_args(base + ['--speed', '15']).speed == 15.0
    assert parser.parse_args(base).speed is None
    assert ExplorationSettings().speed_range == (0.02, 0.05)
    assert speed_range_around(0.15) == pytest.approx((0.12, 0.18))
    for bad in ('0.5', '31', 'fast'):
        with pytest.raises(SystemExit):
            parser.parse_args(base + ['--speed', bad])


@pytest.mark.parametrize('rate', [15.0, 30.0, 120.0, 240.0])
def test_every_rate_gives_its_frames_and_stamps_to_the_bag(tmp_path, rate):
    from rosbags.highlevel import AnyReader
    assert make_parser().parse_args(['--object', 'cat', '--static', '--rate', f'{rate:g}',
                                     '--duration', '2', '--seed', '1', '--output', 'x']).rate == rate
    session = simulate(SessionSettings(object_name='cat', static=True, rate=rate, duration=3.0,
                                       seed=2, surface_samples=100_000, exploration=FAST))
    frames = round(3.0 * rate)
    assert len(session.stamps_ns) == frames == len(session.exploration.times)
    assert np.array_equal(session.exploration.times, np.arange(frames) / rate)
    bag, _ = write_session(session, tmp_path / 'bag')
    stamps = set()
    with AnyReader([bag]) as reader:
        for _, log_time, _ in reader.messages():
            stamps.add(log_time)
    gaps = np.diff(sorted(stamps))
    assert len(stamps) == frames and np.all(np.abs(gaps - 1e9 / rate) <= 1)


def test_rates_other_than_the_four_are_refused():
    with pytest.raises(SystemExit):
        make_parser().parse_args(['--object', 'cat', '--static', '--rate', '60', '--duration',
                                  '2', '--seed', '1', '--output', 'x'])


def test_lifts_rise_from_the_surface_and_come_back_continuously(cat):
    ex = explore(cat, 20.0, 240.0, np.random.default_rng(6), FAST)
    height = np.stack([cat.sdf(p) for p in ex.positions])      # (3, T)
    off = ~ex.contact
    assert np.any(off & (height < 0.003)) and np.any(off & (height < 0.001))
    assert height[off].min() >= 0.9 * FAST.min_height
    # heights of every millimetre up to the hover height are sampled
    counts = np.histogram(height[off], bins=[0.0, 0.0005, 0.001, 0.002, 0.004, 0.006])[0]
    assert np.all(counts > 0), counts
    for f in range(3):
        c, h = ex.contact[f], height[f]
        # every stretch off the surface between two contacts starts and ends at the surface
        starts = np.flatnonzero(c[:-1] & ~c[1:]) + 1
        ends = np.flatnonzero(~c[:-1] & c[1:])
        for a in starts:
            later = ends[ends >= a]
            if later.size:
                assert h[a] < 0.0003 and h[later[0]] < 0.0003, (f, a)
        # and near it the height changes by little from one frame to the next (no jumps)
        both = off[f, 1:] & off[f, :-1] & (h[1:] < 0.006) & (h[:-1] < 0.006)
        assert np.abs(np.diff(h))[both].max() < 0.0015
    # the involuntary lifts among them: from the surface up to 1-3 cm (along the normal; the
    # distance to the surface can be less, next to a leg) and back
    lift = ex.kind == SAMPLE_KINDS.index('lift')
    assert lift.any() and height[lift].min() < 0.001
    rises = []
    for f in range(3):
        frames = np.flatnonzero(lift[f])
        for run in np.split(frames, np.flatnonzero(np.diff(frames) > 1) + 1) if frames.size else []:
            rises.append(np.linalg.norm(ex.positions[f, run] - ex.positions[f, run[0]], axis=1).max())
    assert max(rises) > 0.008


def test_lifts_between_frames_keep_the_sessions_made_before(cat):
    jumps = replace(FAST, continuous_lifts=False)
    ex = explore(cat, 10.0, 240.0, np.random.default_rng(6), jumps)
    assert cat.sdf(ex.positions[~ex.contact]).min() >= 0.006
    # both are settings of the session, recorded in the truth
    default = json.loads(SessionSettings().to_json())['exploration']
    assert default['continuous_lifts'] is True and default['min_height'] == 0.00005
    parser = make_parser()
    base = ['--object', 'cat', '--static', '--rate', '15', '--duration', '2', '--seed', '1',
            '--output', 'x']
    assert parser.parse_args(base).lifts == 'continuous'
    assert parser.parse_args(base + ['--lifts', 'between-frames']).lifts == 'between-frames'
