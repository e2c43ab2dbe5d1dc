#!/usr/bin/env python3
"""Fuzz every reader of outside input with a million inputs or more.

Runs the hypothesis properties of ``test/test_fuzz.py`` (the Liberty parser, the
PoseStamped and PointCloud2 decoders, the NPZ and PLY map readers, the parameter checks)
with random seeds, in rounds, until each has had its share of ``--inputs``; the test
command runs the same properties on 150 fixed inputs each. Prints the inputs and the rate
per target as it goes and a table at the end.

    .venv/bin/python test/benchmarks/fuzz.py [--inputs 1000000] [--jobs 2] [--round 20000]
                                             [--targets SUBSTRING ...]

Exit status 0 when no property failed; otherwise 1, after the falsifying input of each
failure (hypothesis prints it with the seed to reproduce it).
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import sys
import time
import traceback
from pathlib import Path

TEST_DIR = Path(__file__).resolve().parents[1]


def _targets(module) -> dict[str, object]:
    return {name: fn for name, fn in vars(module).items()
            if name.startswith('test_') and getattr(fn, 'is_hypothesis_test', False)}


def _round(job: tuple[str, int]) -> tuple[str, int, float, str | None]:
    """One round of one property in a worker: (name, inputs, seconds, failure or None)."""
    name, examples = job
    os.environ['INHAND_FUZZ_EXAMPLES'] = str(examples)
    sys.path.insert(0, str(TEST_DIR))
    import test_fuzz
    target = _targets(test_fuzz)[name]
    test_fuzz.INPUTS.clear()
    start = time.perf_counter()
    failure = None
    try:
        target()
    except BaseException:
        failure = traceback.format_exc()
    return name, sum(test_fuzz.INPUTS.values()), time.perf_counter() - start, failure


def _quiet_worker() -> None:
    # rclpy's deserializer prints "sequence size exceeds remaining buffer" for every bad
    # PointCloud2 it is given; failures come back as text, so the worker's stderr can go.
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--inputs', type=int, default=1_000_000,
                        help='inputs in all (default 1,000,000), shared evenly by the targets')
    parser.add_argument('--jobs', type=int, default=os.cpu_count() or 1,
                        help='worker processes (default: one per core)')
    parser.add_argument('--round', type=int, default=20_000,
                        help='inputs per hypothesis run (a fresh random seed each)')
    parser.add_argument('--targets', nargs='*', default=[],
                        help='only the properties whose name holds one of these')
    args = parser.parse_args()
    for name in ('inputs', 'jobs', 'round'):
        if getattr(args, name) < 1:
            parser.error(f'--{name} must be at least 1')

    sys.path.insert(0, str(TEST_DIR))
    os.environ['INHAND_FUZZ_EXAMPLES'] = '1'
    import test_fuzz
    names = [n for n in _targets(test_fuzz) if not args.targets or any(t in n for t in args.targets)]
    if not names:
        parser.error('no property matches --targets')
    share = math.ceil(args.inputs / len(names))
    rounds = math.ceil(share / args.round)
    jobs = [(name, math.ceil(share / rounds)) for _ in range(rounds) for name in names]
    print(f'fuzzing {len(names)} properties, {share:,} inputs each in {rounds} round(s), '
          f'{args.jobs} worker(s)', flush=True)

    done = {name: [0, 0.0] for name in names}
    failures: dict[str, str] = {}
    start = time.perf_counter()
    context = multiprocessing.get_context('spawn')
    with context.Pool(args.jobs, initializer=_quiet_worker, maxtasksperchild=1) as pool:
        for finished, (name, inputs, seconds, failure) in enumerate(
                pool.imap_unordered(_round, jobs), 1):
            done[name][0] += inputs
            done[name][1] += seconds
            if failure:
                failures.setdefault(name, failure)
            total = sum(d[0] for d in done.values())
            print(f'[{finished}/{len(jobs)}] {name}: +{inputs:,} in {seconds:.0f} s '
                  f'({inputs / max(seconds, 1e-9):,.0f}/s){"  FAILED" if failure else ""}; '
                  f'{total:,} inputs so far, {time.perf_counter() - start:.0f} s', flush=True)

    print(f'\n{"property":<86} {"inputs":>10} {"per s":>8}  result')
    for name in names:
        inputs, seconds = done[name]
        print(f'{name:<86} {inputs:>10,} {inputs / max(seconds, 1e-9):>8,.0f}  '
              f'{"FAILED" if name in failures else "ok"}')
    total = sum(d[0] for d in done.values())
    print(f'{"all":<86} {total:>10,}           {len(failures)} failed; '
          f'{time.perf_counter() - start:.0f} s on {args.jobs} worker(s)')
    for name, failure in failures.items():
        print(f'\n### {name}\n{failure}')
    return 1 if failures else 0


if __name__ == '__main__':
    sys.exit(main())
