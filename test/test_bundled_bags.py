"""The bundled bags are what the one command makes, bit for bit, and they replay."""

import hashlib
import subprocess

from conftest import WORKSPACE

BAGS = ('cat_static', 'cat_moving', 'bottle_static')


def digest(folder):
    files = sorted(p for p in folder.rglob('*') if p.is_file())
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


def test_make_bags_regenerates_the_bundled_bags_bit_for_bit(tmp_path):
    result = subprocess.run(['bash', str(WORKSPACE / 'launch_scripts' / 'make_bags.sh'),
                             str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    for name in BAGS:
        bundled = WORKSPACE / 'bags'
        assert digest(tmp_path / name) == digest(bundled / name), f'{name} differs'
        assert (tmp_path / f'{name}.truth.npz').read_bytes() == \
            (bundled / f'{name}.truth.npz').read_bytes(), f'{name}.truth.npz differs'


def test_bundled_bags_stay_small():
    # Three 120 s sessions at 15 Hz with one stereo pair each: about 24 MB, most of it the
    # truth sidecars (surface samples and colours, the true depth of the left image: 5 MB
    # each) and the image pairs (1.8 MB each).
    total = sum(p.stat().st_size for p in (WORKSPACE / 'bags').rglob('*') if p.is_file())
    assert total < 30e6, f'bundled bags take {total / 1e6:.1f} MB'


def test_bundled_sessions_are_120_s_at_15_hz():
    """All three at the paper's rate and of one length, so their maps compare on equal terms
    (the static and the non-static cat in particular)."""
    from inhand_common.ground_truth import load_truth
    expected = {'cat_static': ('cat', True), 'cat_moving': ('cat', False),
                'bottle_static': ('bottle', True)}
    for name, (object_name, static) in expected.items():
        truth = load_truth(WORKSPACE / 'bags' / f'{name}.truth.npz')
        assert (truth.object_name, truth.static) == (object_name, static), name
        assert truth.rate == 15.0 and truth.settings['duration'] == 120.0, name
        assert len(truth.object_times) == 120 * 15, name
    assert load_truth(WORKSPACE / 'bags' / 'cat_moving.truth.npz').settings['regrasp']


def test_bundled_sessions_carry_a_stereo_pair_with_its_truth():
    from inhand_common.bag_source import BagSource
    from inhand_common.ground_truth import load_truth
    for name in BAGS:
        with BagSource(WORKSPACE / 'bags' / name) as source:
            counts = {topic: source.topics[topic].count for topic in source.topics
                      if topic.startswith('stereo/')}
        assert counts == {'stereo/left/image_raw': 1, 'stereo/right/image_raw': 1,
                          'stereo/left/camera_info': 1, 'stereo/right/camera_info': 1}, name
        truth = load_truth(WORKSPACE / 'bags' / f'{name}.truth.npz')
        assert truth.stereo is not None and truth.surface_colours is not None, name
        assert truth.stereo.depth.shape == (480, 640), name
        assert truth.stereo.object_mask.mean() > 0.01, name    # the object is in the picture
        assert truth.stereo.time == truth.object_times[0], name
