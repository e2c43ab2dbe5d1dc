#!/usr/bin/env python3
"""The touch map on every way a person explores: objects x stroke speeds x tracker rates x
static / tracked, simulated sessions with exact ground truth.

    .venv/bin/python test/benchmarks/bench_quality.py [--objects cat,mug,...]
        [--speeds 2,5,10,15] [--rates 15,30,240] [--modes static,tracked]
        [--duration 120] [--seed 21] [--jobs 2] [--set NAME=VALUE ...] [--keep DIR] [--quick]
        [--hand NAME=VALUE ...] [--sweep]

Each session: ``simulate_session`` (``--speed`` cm/s, ``--rate`` Hz), ``build_map`` with the
shipped ``config/mapping*.yaml`` (and the ``--set`` overrides, to compare models), and the
map scored against the truth (``map_metrics``' code): F-score, precision and recall at
5 mm (threshold 0.8), the cells holding true off-surface fingertip positions (> 5 mm off
the surface, which the surface does not reach), and the share of the explored surface
touched at least once and at least twice (``map_quality.touch_coverage``: what any model
could know). One line per session, then a summary against the targets:

* F@5mm >= 0.9 on every session at 30 and 240 Hz and at 15 Hz up to 10 cm/s, >= 0.85 at
  15 Hz and 15 cm/s;
* precision >= 0.97 everywhere.

``--hand`` gives every session another hand (``simulate_session --hand``). ``--sweep`` varies
the hand instead, one property at a time around :data:`NOMINAL_HAND` (each over a factor of 3
around its nominal value; the other properties nominal), over the objects x speeds x rates x
modes, and ends with the sensitivity: the worst F and precision per property value. Each
session's one-touch oracle (the cells holding a true contact, scored the same way) is printed
beside it; where a session touched too little of its surface the F floor is 0.02 below it.

``--jobs`` runs that many sessions at once (each is a simulation then a map). Sessions are
seeded (``--seed`` plus the session's index), so a run is repeatable.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import re
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

WORKSPACE = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent

DEFAULT_OBJECTS = 'cat,cup,animal,duck'

# The hand the sweep varies around: short strokes, lifts of a few cm at the speed of a fast
# stroke, carried at 0.3 m/s (simulate_session --hand).
NOMINAL_HAND = (('stroke_length_range', '0.03,0.12'), ('liftoff_height_range', '0.01,0.03'),
                ('liftoff_speed_range', '0.1,0.3'), ('transit_speed', '0.3'))
# Each property's values in the sweep: a third of the nominal, the nominal, three times it.
SWEEP = {
    'stroke_length_range': ('0.01,0.04', '0.03,0.12', '0.09,0.36'),
    'liftoff_height_range': ('0.0033,0.01', '0.01,0.03', '0.03,0.09'),
    'liftoff_speed_range': ('0.033,0.1', '0.1,0.3', '0.3,0.9'),
    'liftoff_angle_range': ('0,10', '0,30', '0,85'),
    'transit_speed': ('0.1', '0.3', '0.9'),
    'hover_probability': ('0.033', '0.1', '0.3'),
    'hover_height_range': ('0.0007,0.0013', '0.002,0.004', '0.006,0.012'),
    'tremor_amplitude': ('0.0002', '0.0006', '0.0018'),
    'speed_profile': ('wave', 'bell'),
    'held_scale': ('0.58', '1', '1.73'),
}
# Properties swept with another one on (a hover's height needs hovers).
SWEEP_WITH = {'hover_height_range': (('hover_probability', '0.1'),)}


@dataclass(frozen=True)
class Session:
    index: int
    obj: str
    speed: float        # cm/s
    rate: float         # Hz
    static: bool
    hand: tuple = ()    # (name, value) pairs for simulate_session --hand
    label: str = ''     # the swept property=value, if any

    @property
    def name(self) -> str:
        kind = 'static' if self.static else 'tracked'
        swept = '_' + re.sub(r'[^A-Za-z0-9_]+', '-', self.label) if self.label else ''
        return f'{Path(self.obj).stem}_{kind}_{self.speed:g}cms_{self.rate:g}hz{swept}'

    def f_target(self, duration: float = 120.0) -> float:
        return 0.85 if duration < 120 or (self.rate < 30 and self.speed > 10) else 0.9


def run(command: list[str]) -> str:
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f'{" ".join(command)} failed:\n{done.stderr[-2000:]}')
    return done.stdout


def measure(session: Session, folder: Path, args) -> dict:
    bag = folder / session.name
    run([str(BIN / 'simulate_session'), '--object', session.obj,
         '--static' if session.static else '--moving', '--rate', f'{session.rate:g}',
         '--speed', f'{session.speed:g}', '--duration', f'{args.duration:g}',
         '--seed', str(args.seed + session.index), '--output', str(bag), '--quiet', '--force',
         *[item for name, value in session.hand for item in ('--hand', f'{name}={value}')]])
    config = WORKSPACE / 'config' / ('mapping_static.yaml' if session.static else 'mapping.yaml')
    overrides = [item for pair in args.set for item in ('--set', pair)]
    run([str(BIN / 'build_map'), str(bag), '--config', str(config), *overrides,
         '--output-dir', str(folder), '--quiet'])
    report = folder / f'{session.name}.json'
    run([str(BIN / 'map_metrics'), str(folder / f'{session.name}.npz'), '--truth',
         f'{bag}.truth.npz', '--json', str(report)])
    scores = json.loads(report.read_text())
    cells = scores['thresholds']['0.8']
    oracle = scores['oracle']
    # An empty map: no precision (NaN), no recall and so F 0.
    return {'F': cells['fscore_at_5mm'] or 0.0, 'P': nan_if_none(cells['precision_at_5mm']),
            'R': cells['recall_at_5mm'] or 0.0, 'strays': cells['stray_cells'],
            'occupied': cells['occupied_cells'], 'off': cells['off_surface_cells'],
            'touched1': scores['touch_coverage']['once'],
            'touched2': scores['touch_coverage']['twice'], 'oracle_F': oracle['fscore_at_5mm']}


def nan_if_none(value) -> float:
    return math.nan if value is None else float(value)


def f_floor(session: Session, scores: dict, duration: float) -> float:
    """The F target, or 0.02 below the oracle where the session touched too little."""
    return min(session.f_target(duration), scores['oracle_F'] - 0.02)


def sessions_of(args, objects, modes, rates, speeds) -> list[Session]:
    """The grid of sessions: with ``--sweep`` once per swept property value, else once with
    the ``--hand`` given."""
    grid = list(itertools.product(objects, modes, rates, speeds))
    if not args.sweep:
        hand = tuple(tuple(pair.split('=', 1)) for pair in args.hand)
        return [Session(k, obj, speed, rate, static, hand) for k, (obj, static, rate, speed)
                in enumerate(grid)]
    hands = []
    swept = args.sweep_only.split(',') if args.sweep_only else list(SWEEP)
    for prop in swept:
        for value in SWEEP[prop]:
            hand = dict(NOMINAL_HAND)
            hand.update(SWEEP_WITH.get(prop, ()))
            hand[prop] = value
            hands.append((f'{prop}={value}', tuple(hand.items())))
    return [Session(k, obj, speed, rate, static, hand, label)
            for k, ((label, hand), (obj, static, rate, speed))
            in enumerate(itertools.product(hands, grid))]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--objects', default=DEFAULT_OBJECTS,
                        help=f'comma-separated simulate_session objects (default {DEFAULT_OBJECTS})')
    parser.add_argument('--speeds', default='2,5,10,15', help='cm/s')
    parser.add_argument('--rates', default='15,30,240', help='Hz')
    parser.add_argument('--modes', default='static,tracked')
    parser.add_argument('--duration', type=float, default=120.0)
    parser.add_argument('--seed', type=int, default=21)
    parser.add_argument('--jobs', type=int, default=2)
    parser.add_argument('--set', action='append', default=[], metavar='NAME=VALUE',
                        help='build_map override (repeatable), to compare models')
    parser.add_argument('--keep', type=Path, help='keep the bags and maps in this folder')
    parser.add_argument('--quick', action='store_true',
                        help='30 s sessions of two objects at 15 and 240 Hz, static only')
    parser.add_argument('--hand', action='append', default=[], metavar='NAME=VALUE',
                        help='simulate_session --hand for every session (repeatable)')
    parser.add_argument('--sweep', action='store_true',
                        help='vary the hand one property at a time around the nominal hand '
                             'and print the worst F and precision per property value')
    parser.add_argument('--sweep-only', metavar='PROPERTY[,PROPERTY]',
                        help=f"with --sweep, only these properties ({', '.join(SWEEP)})")
    args = parser.parse_args()
    unknown = set(args.sweep_only.split(',')) - set(SWEEP) if args.sweep_only else set()
    if unknown:
        parser.error(f"--sweep-only: unknown {', '.join(sorted(unknown))}; "
                     f"one of {', '.join(SWEEP)}")
    if args.quick:
        args.objects, args.rates, args.modes, args.duration = 'cat,cup', '15,240', 'static', 30.0
    objects = args.objects.split(',')
    speeds = [float(v) for v in args.speeds.split(',')]
    rates = [float(v) for v in args.rates.split(',')]
    modes = [mode == 'static' for mode in args.modes.split(',')]
    sessions = sessions_of(args, objects, modes, rates, speeds)
    with tempfile.TemporaryDirectory(prefix='bench_quality_') as scratch:
        folder = args.keep or Path(scratch)        # the sessions are kept only with --keep
        folder.mkdir(parents=True, exist_ok=True)
        return report(args, sessions, folder)


def report(args: argparse.Namespace, sessions: list[Session], folder: Path) -> int:
    """Simulate and map ``sessions`` in ``folder``, ``args.jobs`` at a time, and print each
    one's scores against its targets, the summary and (``--sweep``) the sensitivity."""
    print(f'# {len(sessions)} sessions of {args.duration:g} s, {args.jobs} at a time, in '
          f'{folder}; model: shipped config{" + " + " ".join(args.set) if args.set else ""}'
          + ('' if args.duration >= 120 else '; the targets are for 120 s sessions'))
    header = (f'{"session":34s} {"F@5mm":>6s} {"P":>6s} {"R":>6s} {"strays":>6s} '
              f'{"touched":>8s} {"twice":>6s} {"oracle":>6s}  target')
    print(header)
    started = time.monotonic()
    results: dict[Session, dict] = {}
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = {session: pool.submit(measure, session, folder, args) for session in sessions}
        for session in sessions:
            scores = futures[session].result()
            results[session] = scores
            floor = f_floor(session, scores, args.duration)
            met = scores['F'] >= floor and scores['P'] >= 0.97
            print(f'{session.name:34s} {scores["F"]:6.3f} {scores["P"]:6.3f} '
                  f'{scores["R"]:6.3f} {scores["strays"]:6d} {scores["touched1"]:8.2f} '
                  f'{scores["touched2"]:6.2f} {scores["oracle_F"]:6.3f}  '
                  f'{"met" if met else "NOT met"} (F >= {floor:.2f}, P >= 0.97)', flush=True)
    f_met = sum(results[s]['F'] >= f_floor(s, results[s], args.duration) for s in sessions)
    p_met = sum(results[s]['P'] >= 0.97 for s in sessions)
    worst = min(sessions, key=lambda s: results[s]['F'] - f_floor(s, results[s], args.duration))
    print(f'\nsummary: F target met on {f_met} of {len(sessions)}, precision >= 0.97 on '
          f'{p_met} of {len(sessions)}; F min {min(r["F"] for r in results.values()):.3f}, '
          f'mean {sum(r["F"] for r in results.values()) / len(results):.3f} (worst against '
          f'its target: {worst.name}, {results[worst]["F"]:.3f}); stray cells '
          f'{sum(r["strays"] for r in results.values())} in all; '
          f'{time.monotonic() - started:.0f} s')
    if args.sweep:
        print('\nsensitivity: the worst session per hand property value')
        print(f'{"property=value":40s} {"F min":>6s} {"P min":>6s} {"met":>7s}')
        for label in dict.fromkeys(s.label for s in sessions):
            mine = [s for s in sessions if s.label == label]
            met = sum(results[s]['F'] >= f_floor(s, results[s], args.duration)
                      and results[s]['P'] >= 0.97 for s in mine)
            print(f'{label:40s} {min(results[s]["F"] for s in mine):6.3f} '
                  f'{min((results[s]["P"] for s in mine), key=lambda p: (math.isnan(p), p)):6.3f} '
                  f'{met:3d}/{len(mine):<3d}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
