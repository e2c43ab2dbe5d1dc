#!/usr/bin/env python3
"""Real fingers: pivot calibration accuracy and maps made with sensors on the nail.

    .venv/bin/python test/benchmarks/bench_fingers.py [--quick] [--keep DIR]

Three tables, each from the commands a researcher runs (simulate_pivot, calibrate_fingertips,
simulate_session, build_map, map_metrics):

1. Pivot calibration (inhand_mapping/pivot_calibration.py) on simulated pivots, 1 mm and
   0.15 degrees of tracker noise, 10 s per finger at 30 Hz, three seeds x three fingers,
   tilted 30, 45 and 60 degrees (twisted 10 about the finger) and 10 (twisted 2): offset
   error (max, mean), residual, refusals.
   Target: within 1 mm at 30-60 degrees, refused at 10.
2. The cat on the table, 120 s at 30 Hz, seed 7, the sensor 10 mm over and 3 mm behind a
   7 mm pad, rolling 20 degrees, at 2, 5 and 15 cm/s: point fingertips (the same paths),
   no correction, the offset only, and the offset calibrated from a pivot at 30 degrees
   with the pad radius; then, at 5 cm/s, the offset's z wrong by 2, 5 and 10 mm each way.
   Target: calibrated within 0.02 of point fingertips in F@5mm and precision.
3. The mug held and turned by the other hand, 90 s at 30 Hz, 5 cm/s, seed 11, offset
   (2, 1, -10) mm, 7 mm pad, rolling 0, 15 and 30 degrees, and the duck at 30: point
   fingertips against the calibrated map (the contact along the normal of the surface the
   pad centres traced, pad_normals.py). Target: within 0.02 of F.

``--quick``: 40 s sessions, one seed and one speed (a smoke run, not the figures).
Exit status 0 whether or not the targets are met (it prints them).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from inhand_mapping.pivot_calibration import pivot_window, solve_pivot
from inhand_sim.pivot import PivotSettings, simulate_pivot

WORKSPACE = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
TRACKED = str(WORKSPACE / 'config' / 'mapping.yaml')
STATIC = str(WORKSPACE / 'config' / 'mapping_static.yaml')
PIVOT_TRUTH = ((0.004, 0.001, -0.011), (0.0, -0.003, -0.009), (0.002, 0.0, -0.012))


def run(*args: str) -> str:
    done = subprocess.run([str(BIN / args[0]), *args[1:]], capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f'{" ".join(args)} failed ({done.returncode}):\n{done.stdout}{done.stderr}')
    return done.stdout


def fingers_file(path: Path, offsets, pad_radius: float) -> str:
    flat = ', '.join(f'{v:.6f}' for v in np.ravel(offsets))
    path.write_text('/**/registration_node:\n  ros__parameters:\n'
                    f'    tip_offsets: [{flat}]\n    pad_radius: {pad_radius}\n')
    return str(path)


def pivot_table(seeds: int) -> None:
    print('\n1. pivot calibration: 1 mm / 0.15 deg noise, 10 s per finger at 30 Hz, '
          f'{seeds} seed(s) x 3 fingers')
    print(f'{"tilt":>6} {"max error":>10} {"mean error":>11} {"residual":>9} {"refused":>8}  target')
    for tilt in (10.0, 30.0, 45.0, 60.0):
        errors, residuals, refused = [], [], 0
        for seed in range(seeds):
            # 10 degrees: the twist too small to make up the 15 the calibration asks for
            session = simulate_pivot(PivotSettings(tip_offsets=PIVOT_TRUTH, tilt_deg=tilt,
                                                   twist_deg=2.0 if tilt < 15 else 10.0,
                                                   seed=seed))
            times = (session.stamps_ns - session.stamps_ns[0]) / 1e9
            for finger in range(3):
                window = pivot_window(times, session.poses[finger, :, 3:])
                result = solve_pivot(session.poses[finger, window, :3],
                                     session.poses[finger, window, 3:])
                if not result.accepted:
                    refused += 1
                    continue
                errors.append(np.linalg.norm(result.offset - PIVOT_TRUTH[finger]) * 1000)
                residuals.append(result.residual * 1000)
        total = 3 * seeds
        if tilt < 15:
            verdict = 'PASS' if refused == total else 'FAIL'
            print(f'{tilt:>5.0f}° {"-":>10} {"-":>11} {"-":>9} {refused:>4}/{total:<3}  '
                  f'refused: {verdict}')
            continue
        worst = max(errors) if errors else float('nan')
        verdict = 'PASS' if errors and refused == 0 and worst <= 1.0 else 'FAIL'
        print(f'{tilt:>5.0f}° {worst:>8.2f} mm {np.mean(errors):>8.2f} mm '
              f'{np.mean(residuals):>6.2f} mm {refused:>4}/{total:<3}  <= 1 mm: {verdict}')


def scores(npz: Path, truth: Path) -> dict:
    report = npz.with_suffix('.metrics.json')
    run('map_metrics', str(npz), '--truth', str(truth), '--json', str(report))
    return json.loads(report.read_text())['thresholds']['0.8']


def build(bag: Path, configs: list[str], out: Path, name: str) -> dict:
    run('build_map', str(bag), *[a for c in configs for a in ('--config', c)],
        '--output-dir', str(out), '--name', name, '--quiet')
    return scores(out / f'{name}.npz', bag.with_name(bag.name + '.truth.npz'))


def simulate(out: Path, name: str, common: list[str], real: list[str] | None) -> Path:
    bag = out / name
    if not bag.exists():
        run('simulate_session', *common, *(real or []), '--output', str(bag), '--quiet')
    return bag


def calibrated(out: Path, name: str, offset_mm: list[str], radius: float) -> str:
    """Calibrate like on the bench: a pivot at 30 degrees, calibrate_fingertips."""
    pivot = out / f'{name}_pivot'
    if not pivot.exists():
        run('simulate_pivot', '--output', str(pivot), '--tip-offset', *offset_mm,
            '--tilt-deg', '30', '--seed', '5')
    found = out / f'{name}_fingers.yaml'
    run('calibrate_fingertips', str(pivot), '--output', str(found))
    offsets = yaml.safe_load(found.read_text())['/**/registration_node']['ros__parameters'][
        'tip_offsets']
    return fingers_file(found, offsets, radius)


def row(label: str, results: list[dict]) -> None:
    cells = ' | '.join(f'{r["fscore_at_5mm"]:.3f} / {r["precision_at_5mm"]:.3f} / '
                       f'{r["chamfer_mm"]:.1f} mm' for r in results)
    print(f'| {label} | {cells} |')


def cat_table(out: Path, duration: str, speeds: list[str]) -> None:
    print(f'\n2. the cat, static, {duration} s at 30 Hz, seed 7; sensor 3 0 -10 mm from a 7 mm '
          'pad, rolling 20 degrees; F@5mm / precision / Chamfer')
    print('| | ' + ' | '.join(f'{s} cm/s' for s in speeds) + ' |')
    print('|---' * (len(speeds) + 1) + '|')
    real = ['--tip-offset-mm', '3', '0', '-10', '--pad-radius-mm', '7', '--finger-roll-deg', '20']
    cal = calibrated(out, 'cat', ['3', '0', '-10'], 0.007)
    offset_only = fingers_file(out / 'cat_offset_only.yaml', [0.003, 0.0, -0.010], 0.0)
    table: dict[str, list[dict]] = {k: [] for k in ('ideal', 'raw', 'offset', 'calibrated')}
    for speed in speeds:
        common = ['--object', 'cat', '--static', '--rate', '30', '--duration', duration,
                  '--seed', '7', '--speed', speed]
        ideal = simulate(out, f'cat_ideal_v{speed}', common, None)
        bag = simulate(out, f'cat_real_v{speed}', common, real)
        table['ideal'].append(build(ideal, [STATIC], out, f'cat_ideal_v{speed}_map'))
        table['raw'].append(build(bag, [STATIC], out, f'cat_raw_v{speed}_map'))
        table['offset'].append(build(bag, [STATIC, offset_only], out, f'cat_offset_v{speed}_map'))
        table['calibrated'].append(build(bag, [STATIC, cal], out, f'cat_cal_v{speed}_map'))
    row('point fingertips', table['ideal'])
    row('real fingers, no correction', table['raw'])
    row('offset only (pad centres)', table['offset'])
    row('calibrated offset (pivot at 30 degrees) + 7 mm radius', table['calibrated'])
    worst = min(min(c['fscore_at_5mm'] - i['fscore_at_5mm'], c['precision_at_5mm']
                    - i['precision_at_5mm']) for c, i in zip(table['calibrated'], table['ideal']))
    print(f'calibrated against point fingertips: worst {worst:+.3f} '
          f'(target >= -0.02: {"PASS" if worst >= -0.02 else "FAIL"})')
    middle = speeds[len(speeds) // 2]
    bag = out / f'cat_real_v{middle}'
    for sign, where in ((1, 'outside: the pad centre put nearer the nail'),
                        (-1, 'inside: the pad centre put further from the nail')):
        wrong = []
        for error in (0.002, 0.005, 0.010):
            z = -0.010 + sign * error
            configs = [STATIC, fingers_file(out / f'cat_z{z:+.3f}.yaml', [0.003, 0.0, z], 0.007)]
            wrong.append(build(bag, configs, out, f'cat_z{z * 1000:+.0f}_map'))
        print(f'offset z wrong by 2 / 5 / 10 mm ({where}), {middle} cm/s: F '
              + ' / '.join(f'{r["fscore_at_5mm"]:.3f}' for r in wrong) + '; Chamfer '
              + ' / '.join(f'{r["chamfer_mm"]:.1f}' for r in wrong) + ' mm; along the normal '
              + ' / '.join(f'{r["normal_offset_mm"]:+.1f}' for r in wrong) + ' mm')


def roll_table(out: Path, duration: str, rolls: list[str]) -> None:
    print(f'\n3. rolling the finger: held and turned, {duration} s at 30 Hz, 5 cm/s, offset 2 1 -10 '
          'mm, 7 mm pad, calibrated; F@5mm')
    cal = calibrated(out, 'roll', ['2', '1', '-10'], 0.007)
    sessions = [('mug', roll) for roll in rolls] + [('duck', rolls[-1])]
    print('| | ' + ' | '.join(f'{o} {r} deg' for o, r in sessions) + ' |')
    print('|---' * (len(sessions) + 1) + '|')
    ideal, default, gaps = [], [], []
    for obj, roll in sessions:
        common = ['--object', obj, '--moving', '--rate', '30', '--duration', duration,
                  '--seed', '11', '--speed', '5']
        ideal_bag = simulate(out, f'{obj}_ideal', common, None)
        bag = simulate(out, f'{obj}_roll{roll}', common,
                       ['--tip-offset-mm', '2', '1', '-10', '--pad-radius-mm', '7',
                        '--finger-roll-deg', roll])
        ideal.append(build(ideal_bag, [TRACKED], out, f'{obj}_ideal_map'))
        default.append(build(bag, [TRACKED, cal], out, f'{obj}_roll{roll}_map'))
        gaps.append(default[-1]['fscore_at_5mm'] - ideal[-1]['fscore_at_5mm'])
    print('| point fingertips | ' + ' | '.join(f'{r["fscore_at_5mm"]:.3f}' for r in ideal) + ' |')
    print('| calibrated, along the traced normal | '
          + ' | '.join(f'{r["fscore_at_5mm"]:.3f}' for r in default) + ' |')
    print(f'worst against point fingertips: {min(gaps):+.3f} '
          f'(target >= -0.02: {"PASS" if min(gaps) >= -0.02 else "FAIL"})')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--quick', action='store_true', help='short sessions, one speed')
    parser.add_argument('--keep', type=Path, help='keep the sessions and maps in DIR')
    args = parser.parse_args()
    started = time.monotonic()
    pivot_table(1 if args.quick else 3)
    with tempfile.TemporaryDirectory() as scratch:
        out = args.keep or Path(scratch)
        out.mkdir(parents=True, exist_ok=True)
        cat_table(out, '40' if args.quick else '120', ['5'] if args.quick else ['2', '5', '15'])
        roll_table(out, '40' if args.quick else '90', ['30'] if args.quick else ['0', '15', '30'])
    print(f'\n{time.monotonic() - started:.0f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
