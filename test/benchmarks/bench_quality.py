#!/usr/bin/env python3
"""The touch map on every way a person explores: objects x stroke speeds x tracker rates x
static / tracked, simulated sessions with exact ground truth.

    .venv/bin/python test/benchmarks/bench_quality.py [--objects cat,mug,...]
        [--speeds 2,5,10,15] [--rates 15,30,240] [--modes static,tracked]
        [--duration 120] [--seed 21] [--jobs 2] [--set NAME=VALUE ...] [--keep DIR] [--quick]

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

``--jobs`` runs that many sessions at once (each is a simulation then a map). Sessions are
seeded (``--seed`` plus the session's index), so a run is repeatable.
"""

from __future__ import annotations

import argparse
import itertools
import json
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


@dataclass(frozen=True)
class Session:
    index: int
    obj: str
    speed: float        # cm/s
    rate: float         # Hz
    static: bool

    @property
    def name(self) -> str:
        kind = 'static' if self.static else 'tracked'
        return f'{Path(self.obj).stem}_{kind}_{self.speed:g}cms_{self.rate:g}hz'

    def f_target(self) -> float:
        return 0.85 if self.rate < 30 and self.speed > 10 else 0.9


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
         '--seed', str(args.seed + session.index), '--output', str(bag), '--quiet', '--force'])
    config = WORKSPACE / 'config' / ('mapping_static.yaml' if session.static else 'mapping.yaml')
    overrides = [item for pair in args.set for item in ('--set', pair)]
    run([str(BIN / 'build_map'), str(bag), '--config', str(config), *overrides,
         '--output-dir', str(folder), '--quiet'])
    report = folder / f'{session.name}.json'
    run([str(BIN / 'map_metrics'), str(folder / f'{session.name}.npz'), '--truth',
         f'{bag}.truth.npz', '--json', str(report)])
    scores = json.loads(report.read_text())
    cells = scores['thresholds']['0.8']
    return {'F': cells['fscore_at_5mm'], 'P': cells['precision_at_5mm'],
            'R': cells['recall_at_5mm'], 'strays': cells['stray_cells'],
            'touched1': scores['touch_coverage']['once'],
            'touched2': scores['touch_coverage']['twice']}


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
    args = parser.parse_args()
    if args.quick:
        args.objects, args.rates, args.modes, args.duration = 'cat,cup', '15,240', 'static', 30.0
    objects = args.objects.split(',')
    speeds = [float(v) for v in args.speeds.split(',')]
    rates = [float(v) for v in args.rates.split(',')]
    modes = [mode == 'static' for mode in args.modes.split(',')]
    sessions = [Session(k, obj, speed, rate, static) for k, (obj, static, rate, speed) in
                enumerate(itertools.product(objects, modes, rates, speeds))]
    folder = args.keep or Path(tempfile.mkdtemp(prefix='bench_quality_'))
    folder.mkdir(parents=True, exist_ok=True)
    print(f'# {len(sessions)} sessions of {args.duration:g} s, {args.jobs} at a time, in '
          f'{folder}; model: shipped config{" + " + " ".join(args.set) if args.set else ""}'
          + ('' if args.duration >= 120 else '; the targets are for 120 s sessions'))
    header = (f'{"session":34s} {"F@5mm":>6s} {"P":>6s} {"R":>6s} {"strays":>6s} '
              f'{"touched":>8s} {"twice":>6s}  target')
    print(header)
    started = time.monotonic()
    results: dict[Session, dict] = {}
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = {session: pool.submit(measure, session, folder, args) for session in sessions}
        for session in sessions:
            scores = futures[session].result()
            results[session] = scores
            met = scores['F'] >= session.f_target() and scores['P'] >= 0.97
            print(f'{session.name:34s} {scores["F"]:6.3f} {scores["P"]:6.3f} '
                  f'{scores["R"]:6.3f} {scores["strays"]:6d} {scores["touched1"]:8.2f} '
                  f'{scores["touched2"]:6.2f}  {"met" if met else "NOT met"} '
                  f'(F >= {session.f_target():.2f}, P >= 0.97)', flush=True)
    f_met = sum(results[s]['F'] >= s.f_target() for s in sessions)
    p_met = sum(results[s]['P'] >= 0.97 for s in sessions)
    worst = min(sessions, key=lambda s: results[s]['F'] - s.f_target())
    print(f'\nsummary: F target met on {f_met} of {len(sessions)}, precision >= 0.97 on '
          f'{p_met} of {len(sessions)}; F min {min(r["F"] for r in results.values()):.3f}, '
          f'mean {sum(r["F"] for r in results.values()) / len(results):.3f} (worst against '
          f'its target: {worst.name}, {results[worst]["F"]:.3f}); stray cells '
          f'{sum(r["strays"] for r in results.values())} in all; '
          f'{time.monotonic() - started:.0f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
