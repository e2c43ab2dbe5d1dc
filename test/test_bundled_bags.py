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
    total = sum(p.stat().st_size for p in (WORKSPACE / 'bags').rglob('*') if p.is_file())
    assert total < 22e6, f'bundled bags take {total / 1e6:.1f} MB'
