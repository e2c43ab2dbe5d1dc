#!/usr/bin/env python3
"""First start: how long the first build_map, occupancy_node and stereo_node take on a
machine whose numba cache is empty, and after ``compile_kernels`` (what bootstrap.sh runs).

    .venv/bin/python test/benchmarks/bench_startup.py [--fresh-clone]

Each program runs with its own ``NUMBA_CACHE_DIR``: an empty one (cold: every kernel it
calls is compiled), and one ``compile_kernels`` filled. The nodes are timed from the spawn
to their "kernels ready" line; build_map over the bundled ``cat_static`` bag with the
stereo config (touch, vision, fusion, texture) to its first progress line (the first
4,096 messages in the map), and its whole run for reference.
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


def three(tree: Path, env_for, scratch: Path) -> dict[str, float]:
    """The three first starts; ``env_for(name)`` gives each program's environment (its own
    empty cache when cold, so that one does not warm the next)."""
    build = ['build_map', 'bags/cat_static', '--config', 'config/mapping_static.yaml', '--config',
             'config/stereo.yaml', '--output-dir', str(scratch)]
    env = env_for('build_map')
    return {
        # its first progress line comes after the first 4,096 messages are in the map
        'build_map, first progress line': ready(tree, build, r'build_map:\s+[\d.]+ /', env),
        'build_map, the whole bag (info)': finished(tree, [*build, '--quiet'], env),
        'occupancy_node': ready(tree, ['occupancy_node', '--ros-args', '--params-file',
                                       'config/mapping.yaml'], 'kernels ready',
                                env_for('occupancy_node')),
        'stereo_node': ready(tree, ['stereo_node', '--ros-args', '--params-file',
                                    'config/stereo.yaml'], 'kernels ready', env_for('stereo_node')),
    }


def table(title: str, results: dict[str, float]) -> None:
    print(f'\n{title}')
    for name, seconds in results.items():
        verdict = '' if '(info)' in name else \
            f'  ({"PASS" if seconds <= TARGET else "FAIL"}: target <= {TARGET:g} s)'
        print(f'  {name:32s} {seconds:6.2f} s{verdict}')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--fresh-clone', action='store_true',
                        help='also clone HEAD, run bootstrap.sh there and time the three')
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch_name:
        scratch = Path(scratch_name)
        cold = {'build_map': scratch / 'cold_build_map', 'occupancy_node': scratch / 'cold_occ',
                'stereo_node': scratch / 'cold_stereo'}
        for folder in cold.values():
            folder.mkdir()
        table('cold: each program with its own empty NUMBA_CACHE_DIR',
              three(WORKSPACE, lambda name: {**os.environ, 'NUMBA_CACHE_DIR': str(cold[name])},
                    scratch))
        cache = scratch / 'compiled'
        cache.mkdir()
        env = {**os.environ, 'NUMBA_CACHE_DIR': str(cache)}
        started = time.monotonic()
        subprocess.run([str(WORKSPACE / '.venv' / 'bin' / 'compile_kernels'), '--quiet'], env=env,
                       check=True)
        print(f'\ncompile_kernels: {time.monotonic() - started:.1f} s, {kernels(cache)} kernels cached')
        before = kernels(cache)
        table('compiled: NUMBA_CACHE_DIR from compile_kernels', three(WORKSPACE, lambda name: env,
                                                                      scratch))
        new = kernels(cache) - before
        print(f'  kernels compiled on first use: {new} ({"PASS" if new == 0 else "FAIL"}: target 0)')
        if args.fresh_clone:
            tree = scratch / 'clone'
            subprocess.run(['git', 'clone', '-q', str(WORKSPACE), str(tree)], check=True)
            started = time.monotonic()
            subprocess.run(['bash', str(tree / 'launch_scripts' / 'bootstrap.sh')], check=True,
                           capture_output=True)
            print(f'\nfresh clone: bootstrap.sh {time.monotonic() - started:.0f} s')
            plain = {k: v for k, v in os.environ.items() if k != 'NUMBA_CACHE_DIR'}
            table('fresh clone, after bootstrap.sh (the cache in its tree)',
                  three(tree, lambda name: plain, scratch))
    return 0


if __name__ == '__main__':
    sys.exit(main())
