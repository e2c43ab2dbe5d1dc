"""The touch, vision and global maps side by side (map_metrics on a map saved with fusion)."""

from __future__ import annotations

import json
import re
import subprocess

import pytest

from ros_helpers import WORKSPACE, executable_path

CONFIGS = ['--config', str(WORKSPACE / 'config' / 'mapping_static.yaml'), '--config',
           str(WORKSPACE / 'config' / 'stereo.yaml')]
BAG = str(WORKSPACE / 'bags' / 'cat_static')


@pytest.fixture(scope='module')
def fused_metrics(tmp_path_factory):
    folder = tmp_path_factory.mktemp('fused')
    # the shipped configs fuse by product
    built = subprocess.run([executable_path('build_map'), BAG, *CONFIGS, '--output-dir',
                            str(folder), '--quiet'],
                           capture_output=True, text=True, timeout=300)
    assert built.returncode == 0, built.stderr
    assert 'product fusion with touch' in built.stdout
    out = folder / 'metrics.json'
    scored = subprocess.run([executable_path('map_metrics'), str(folder / 'cat_static.npz'),
                             '--bag', BAG, *CONFIGS, '--json', str(out)],
                            capture_output=True, text=True, timeout=300)
    assert scored.returncode == 0, scored.stderr
    return scored.stdout, json.loads(out.read_text())['fusion']


def test_the_three_maps_are_scored_side_by_side(fused_metrics):
    text, fusion = fused_metrics
    assert 'local and global maps' in text and set(fusion) == {'touch', 'vision', 'global'}
    assert 'recall lost' not in text     # the global map is not the touch map alone
    touch, vision, fused = fusion['touch'], fusion['vision'], fusion['global']
    # vision sees one side: precise, a third of the surface
    assert vision['precision_at_5mm'] > 0.95 and 0.15 < vision['recall_whole_at_5mm'] < 0.5
    # the global map is better than either local map, on the whole and the observed surface
    for key in ('fscore_whole_at_5mm', 'fscore_observed_at_5mm'):
        assert fused[key] > max(touch[key], vision[key]), key
    # the observed surface is a part of the whole: recall against it is not lower
    assert touch['recall_observed_at_5mm'] >= touch['recall_whole_at_5mm']
    # vision carved free space: the global map is less uncertain than the touch map
    assert fused['entropy_bits'] < touch['entropy_bits']
    assert fused['only_this_sensor'] > 0 and vision['only_this_sensor'] > 0


def test_a_map_without_fusion_has_no_side_by_side_table(tmp_path):
    built = subprocess.run([executable_path('build_map'), BAG, *CONFIGS, '--set', 'fusion=none',
                            '--output-dir', str(tmp_path), '--quiet'], capture_output=True,
                           text=True, timeout=300)
    assert built.returncode == 0, built.stderr
    scored = subprocess.run([executable_path('map_metrics'), str(tmp_path / 'cat_static.npz'),
                             '--truth', f'{BAG}.truth.npz'], capture_output=True, text=True,
                            timeout=300)
    assert scored.returncode == 0, scored.stderr
    assert 'local and global maps' not in scored.stdout
    # a touch map's lost recall, split by the touches of the contact cells nearby
    lost = re.search(r'^recall lost at p > 0.8: ([\d.]+)% of the explored surface: ([\d.]+)% '
                     r'with no .* ([\d.]+)% whose contact cells hold under one touch and '
                     r'([\d.]+)% under 1.74 before the surface rules, ([\d.]+)% whose', scored.stdout,
                     re.M)
    assert lost, scored.stdout
    missed, *parts = (float(v) for v in lost.groups())
    assert 0 < missed < 20 and sum(parts) == pytest.approx(missed, abs=0.25)


def test_render_map_draws_the_local_maps_of_a_fused_map(fused_metrics, tmp_path_factory):
    folder = next(tmp_path_factory.getbasetemp().glob('fused*'))
    output = tmp_path_factory.mktemp('pictures')
    result = subprocess.run([executable_path('render_map'), str(folder / 'cat_static.npz'),
                             '--truth', f'{BAG}.truth.npz', '--output', str(output),
                             '--size', '200'], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    import cv2
    picture = cv2.imread(str(output / 'local_maps.png'))
    assert picture is not None and picture.shape[1] >= 400     # two panels a row
    assert str(output / 'local_maps.png') in result.stdout
