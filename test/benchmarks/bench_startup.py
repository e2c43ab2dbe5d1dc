#!/usr/bin/env python3
"""First start: how long the first build_map, occupancy_node and stereo_node take on a
machine whose numba cache is empty, and after ``compile_kernels`` (what bootstrap.sh runs).

    .venv/bin/python test/benchmarks/bench_startup.py [--fresh-clone]

Each program runs with its own ``NUMBA_CACHE_DIR``: an empty one (cold: every kernel it
calls is compiled), and one ``compile_kernels`` filled. The nodes are timed from the spawn
to their "kernels ready" line; build_map over the bundled ``cat_static`` bag with the
stereo config (touch, vision, fusion, texture), to its exit, beside a second run (warm).
After the compiled runs the cache must hold no new kernel: nothing compiled on first use.
``--fresh-clone``: also clone HEAD into a scratch folder, run the README's set-up there
(``bootstrap.sh``, which compiles) and time the three in that tree.

Target (issue: first start): each ready within 3 s after the set-up.
Exit status 0 whether or not the target is met (it prints it).
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

WORKSPACE = Path(__file__).resolve().parents[2]
TARGET = 3.0


def ready(tree: Path, args: list[str], pattern: str, env: dict) -> float:
    """Seconds from spawning ``args`` until its output matches ``pattern``."""
    started = time.monotonic()
    process = subprocess.Popen([str(tree / '.venv' / 'bin' / args[0]), *args[1:]], cwd=tree,
                               env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True, start_new_session=True)
    seconds = float('nan')
    assert process.stdout is not None
    for line in process.stdout:
        if re.search(pattern, line):
            seconds = time.monotonic() - started
            break
    os.killpg(process.pid, signal.SIGINT)
    try:
        process.wait(15)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
    return seconds


def finished(tree: Path, args: list[str], env: dict) -> float:
    started = time.monotonic()
    subprocess.run([str(tree / '.venv' / 'bin' / args[0]), *args[1:]], cwd=tree, env=env,
                   check=True, capture_output=True)
    return time.monotonic() - started


def kernels(cache: Path) -> int:
    return sum(1 for _ in cache.rglob('*.nbc'))


def three(tree: Path, env: dict, scratch: Path) -> dict[str, float]:
    build = ['build_map', 'bags/cat_static', '--config', 'config/mapping_static.yaml', '--config',
             'config/stereo.yaml', '--output-dir', str(scratch), '--quiet']
    return {
        'build_map (cat_static, stereo)': finished(tree, build, env),
        'build_map again (warm)': finished(tree, build, env),
        'occupancy_node': ready(tree, ['occupancy_node', '--ros-args', '--params-file',
                                       'config/mapping.yaml'], 'kernels ready', env),
        'stereo_node': ready(tree, ['stereo_node', '--ros-args', '--params-file',
                                    'config/stereo.yaml'], 'kernels ready', env),
    }


def table(title: str, results: dict[str, float]) -> None:
    print(f'\n{title}')
    for name, seconds in results.items():
        verdict = '' if 'warm' in name else \
            f'  ({"PASS" if seconds <= TARGET else "FAIL"}: target <= {TARGET:g} s)'
        print(f'  {name:32s} {seconds:6.2f} s{verdict}')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--fresh-clone', action='store_true',
                        help='also clone HEAD, run bootstrap.sh there and time the three')
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch_name:
        scratch = Path(scratch_name)
        for label in ('cold', 'compiled'):
            cache = scratch / f'cache_{label}'
            cache.mkdir()
            env = {**os.environ, 'NUMBA_CACHE_DIR': str(cache)}
            if label == 'compiled':
                started = time.monotonic()
                subprocess.run([str(WORKSPACE / '.venv' / 'bin' / 'compile_kernels'), '--quiet'],
                               env=env, check=True)
                print(f'compile_kernels: {time.monotonic() - started:.1f} s, '
                      f'{kernels(cache)} kernels cached')
            before = kernels(cache)
            results = three(WORKSPACE, env, scratch)
            table(f'{label}: NUMBA_CACHE_DIR {"empty" if label == "cold" else "from compile_kernels"}',
                  results)
            if label == 'compiled':
                new = kernels(cache) - before
                print(f'  kernels compiled on first use: {new} '
                      f'({"PASS" if new == 0 else "FAIL"}: target 0)')
        if args.fresh_clone:
            tree = scratch / 'clone'
            subprocess.run(['git', 'clone', '-q', str(WORKSPACE), str(tree)], check=True)
            started = time.monotonic()
            subprocess.run(['bash', str(tree / 'launch_scripts' / 'bootstrap.sh')], check=True,
                           capture_output=True)
            print(f'\nfresh clone: bootstrap.sh {time.monotonic() - started:.0f} s')
            env = {k: v for k, v in os.environ.items() if k != 'NUMBA_CACHE_DIR'}
            table('fresh clone, after bootstrap.sh (the cache in its tree)',
                  three(tree, env, scratch))
    return 0


if __name__ == '__main__':
    sys.exit(main())
