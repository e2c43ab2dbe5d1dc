#!/usr/bin/env python3
"""Touch, vision and their fusion on sessions where each sensor fails somewhere.

    .venv/bin/python test/benchmarks/bench_fusion.py [--quick] [--keep DIR]

Simulates a grid of sessions with a stereo pair (objects x viewpoints x session lengths:
the camera does not see the back or the underside, the bottle's glass is weakly textured,
a short session leaves parts of the object untouched), plus the bundled bags, and builds
each map with ``build_map`` (the nodes' code) under every fusion: none (touch), product,
entropy as eq. 12 (linear pooling, whole map and local) and entropy with log pooling. For
each: F-score at 5 mm, precision and recall (against the whole true surface) of the touch
map, the vision map and the global map, side by side (``map_metrics``' fusion table:
against the whole true surface and against the surface either sensor observed). Prints
one table (markdown) and the commands that made it. Each session's rig gets its own
``camera_pose`` (the truth's: what its calibration would give).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

WORKSPACE = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent

from inhand_common.ground_truth import load_truth  # noqa: E402

# (name, simulate_session arguments)
SESSIONS = [
    ('cat, 120 s, default view', ['--object', 'cat', '--static', '--duration', '120']),
    ('cat, 30 s, default view', ['--object', 'cat', '--static', '--duration', '30']),
    ('cat, 120 s, from the front above', ['--object', 'cat', '--static', '--duration', '120',
                                          '--camera-azimuth', '0', '--camera-elevation', '55']),
    ('cat moving, 60 s, default view', ['--object', 'cat', '--moving', '--duration', '60']),
    ('mug, 120 s, default view', ['--object', 'mug', '--static', '--duration', '120']),
    ('mug, 30 s, from the other side', ['--object', 'mug', '--static', '--duration', '30',
                                        '--camera-azimuth', '100', '--camera-elevation', '25']),
    ('bottle, 120 s, default view', ['--object', 'bottle', '--static', '--duration', '120']),
    ('bottle moving, 30 s, low view', ['--object', 'bottle', '--moving', '--duration', '30',
                                       '--camera-elevation', '10']),
]
BUNDLED = [('bundled cat_static', 'cat_static', 'mapping_static.yaml'),
           ('bundled cat_moving', 'cat_moving', 'mapping.yaml'),
           ('bundled bottle_static', 'bottle_static', 'mapping_static.yaml')]
FUSIONS = {
    'product': ['fusion=product'],
    # every setting spelled out: the shipped files set the best entropy form
    'entropy eq. 12': ['fusion=entropy', 'entropy_radius=0', 'entropy_pooling=linear'],
    'entropy eq. 12, local r=1': ['fusion=entropy', 'entropy_radius=1',
                                  'entropy_pooling=linear'],
    'entropy log, whole map': ['fusion=entropy', 'entropy_radius=0', 'entropy_pooling=log'],
    'entropy log, local r=1': ['fusion=entropy', 'entropy_radius=1', 'entropy_pooling=log'],
    'entropy log, local r=2': ['fusion=entropy', 'entropy_radius=2', 'entropy_pooling=log'],
}


def camera_file(bag: Path, out: Path) -> Path:
    """The rig's camera_pose as its calibration would give it: the truth's (a session from
    another viewpoint than config/stereo.yaml's rig has its own)."""
    pose = load_truth(Path(f'{bag}.truth.npz')).stereo.camera_pose
    path = out / f'{bag.name}_camera.yaml'
    out.mkdir(parents=True, exist_ok=True)
    path.write_text('/**/stereo_node:\n  ros__parameters:\n    camera_pose: ['
                    + ', '.join(f'{float(v):.9f}' for v in pose) + ']\n')
    return path


def build(bag: Path, config: str, out: Path, name: str, overrides: list[str]) -> Path:
    command = [str(BIN / 'build_map'), str(bag), '--config', config, '--config',
               str(WORKSPACE / 'config' / 'stereo.yaml'), '--config',
               str(camera_file(bag, out)), '--output-dir', str(out), '--name', name,
               '--quiet']
    for value in overrides:
        command += ['--set', value]
    subprocess.run(command, check=True, capture_output=True, text=True)
    return out / f'{name}.npz'


def fused_scores(npz: Path, bag: Path, configs: list[str]) -> dict:
    """map_metrics' side-by-side scores of the touch, vision and global maps."""
    out = npz.with_suffix('.metrics.json')
    command = [str(BIN / 'map_metrics'), str(npz), '--bag', str(bag), '--json', str(out)]
    for config in configs:
        command += ['--config', config]
    subprocess.run(command, check=True, capture_output=True, text=True)
    return json.loads(out.read_text())['fusion']


def cell(scores: dict) -> str:
    return (f"{scores['fscore_whole_at_5mm']:.3f} / {scores['fscore_observed_at_5mm']:.3f} "
            f"({scores['precision_at_5mm']:.2f})")


def row(label: str, bag: Path, config: str, out: Path) -> list[str]:
    lines = []
    configs = [config, str(WORKSPACE / 'config' / 'stereo.yaml'), str(camera_file(bag, out))]
    for index, (fusion, overrides) in enumerate(FUSIONS.items()):
        path = build(bag, config, out, f'{bag.name}_{index}', overrides)
        scores = fused_scores(path, bag, configs)
        touch, vision, fused = scores['touch'], scores['vision'], scores['global']
        cells = [label if index == 0 else '', fusion]
        cells += [cell(touch), cell(vision)] if index == 0 else ['', '']
        better = all(fused[key] > max(touch[key], vision[key])
                     for key in ('fscore_whole_at_5mm', 'fscore_observed_at_5mm'))
        cells.append(cell(fused) + (' **>**' if better else ''))
        lines.append('| ' + ' | '.join(cells) + ' |')
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--quick', action='store_true', help='the bundled bags and two sessions')
    parser.add_argument('--keep', type=Path, help='keep the simulated sessions here')
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix='bench_fusion_') as scratch:
        folder = args.keep or Path(scratch)         # the sessions are kept only with --keep
        folder.mkdir(parents=True, exist_ok=True)
        return run(args, folder)


def run(args: argparse.Namespace, scratch: Path) -> int:
    """Simulate the sessions into ``scratch`` (unless there already) and print the table."""
    sessions = SESSIONS[:2] if args.quick else SESSIONS
    print('| session | fusion | touch F whole / observed (P) | vision | global |')
    print('|---|---|---|---|---|')
    started = time.monotonic()
    for label, name, config in BUNDLED:
        for line in row(label, WORKSPACE / 'bags' / name, str(WORKSPACE / 'config' / config),
                        scratch / 'maps'):
            print(line, flush=True)
    for index, (label, simulate) in enumerate(sessions):
        bag = scratch / f'session{index}'
        if not bag.exists():
            subprocess.run([str(BIN / 'simulate_session'), *simulate, '--rate', '15',
                            '--seed', str(100 + index), '--stereo', '--output', str(bag),
                            '--quiet'], check=True)
        config = 'mapping_static.yaml' if '--static' in simulate else 'mapping.yaml'
        for line in row(label, bag, str(WORKSPACE / 'config' / config), scratch / 'maps'):
            print(line, flush=True)
    print(f'\n{len(BUNDLED) + len(sessions)} sessions in {time.monotonic() - started:.0f} s; '
          'F@5mm against the whole true surface / against the surface either sensor observed '
          '(precision at 5 mm), threshold 0.8; **>**: the global map beats both local maps '
          'on both', file=sys.stderr)
    print('sessions: simulate_session ' + ' ; '.join(
        f'{" ".join(s)} --rate 15 --seed {100 + i} --stereo' for i, (_, s) in
        enumerate(sessions)), file=sys.stderr)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
