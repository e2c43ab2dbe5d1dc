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
    # Three 120 s sessions at 15 Hz: about 12 MB, most of it the three 3 MB truth sidecars.
    total = sum(p.stat().st_size for p in (WORKSPACE / 'bags').rglob('*') if p.is_file())
    assert total < 14e6, f'bundled bags take {total / 1e6:.1f} MB'


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
