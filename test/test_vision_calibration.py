"""Fitting the stereo camera's range noise (sigma_min, zeta of eq. 7) and the tool."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

from inhand_stereo.noise_fit import fit_noise, robust_sigma
from ros_helpers import WORKSPACE, executable_path


def _errors(sigma, seed=0, count=40_000, wild=0.03):
    rng = np.random.default_rng(seed)
    d = rng.uniform(0.25, 0.9, count)
    e = rng.normal(0.0, sigma(d))
    outliers = rng.random(count) < wild                   # wild matches
    e[outliers] = rng.uniform(-0.05, 0.05, outliers.sum())
    return d, e


def test_robust_sigma_ignores_wild_values():
    rng = np.random.default_rng(1)
    e = np.concatenate([rng.normal(0, 0.001, 10_000), rng.uniform(-1, 1, 300)])
    assert robust_sigma(e) == pytest.approx(0.001, rel=0.05)


@pytest.mark.parametrize('truth, sigma', [
    ('stereo', lambda d: 0.0002 + 0.004 * d ** 2),
    ('linear', lambda d: 0.0003 + 0.003 * d),
])
def test_the_fit_recovers_the_model_and_picks_it(truth, sigma):
    d, e = _errors(sigma)
    fit = fit_noise(d, e, bins=10)
    assert fit.best.noise == truth
    ranges = np.linspace(0.3, 0.85, 5)
    assert np.allclose(fit.best.sigma(ranges), sigma(ranges), rtol=0.08)


def test_too_few_errors_are_refused():
    with pytest.raises(ValueError, match='need at least'):
        fit_noise([0.4] * 10, [0.001] * 10)


def test_the_tool_fits_a_bundled_bag_against_its_truth(tmp_path):
    output = tmp_path / 'vision.yaml'
    result = subprocess.run([executable_path('calibrate_vision_model'),
                             str(WORKSPACE / 'bags' / 'cat_static'), '--config',
                             str(WORKSPACE / 'config' / 'mapping_static.yaml'), '--config',
                             str(WORKSPACE / 'config' / 'stereo.yaml'), '--truth', '--output',
                             str(output), '--bins', '4'],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert 'fits better' in result.stdout
    import yaml
    values = yaml.safe_load(output.read_text())['/**/stereo_node']['ros__parameters']
    assert values['vision_noise'] in ('linear', 'stereo')
    # about 1 mm at 0.4 m on the cat's textured surface
    growth = 0.4 if values['vision_noise'] == 'linear' else 0.16
    assert 0.0003 < values['vision_sigma_min'] + values['vision_zeta'] * growth < 0.003


def test_the_tool_refuses_a_missing_bag_in_one_line(tmp_path):
    result = subprocess.run([executable_path('calibrate_vision_model'), str(tmp_path / 'none'),
                             '--config', str(WORKSPACE / 'config' / 'mapping_static.yaml'),
                             '--truth'], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    assert 'no such bag' in result.stderr and 'Traceback' not in result.stderr
