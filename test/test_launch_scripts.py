"""The launch scripts start the graph, save the map and leave no process behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from conftest import WORKSPACE

pytestmark = pytest.mark.dds


def children_alive(pids: list[int]) -> list[int]:
    alive = []
    for pid in pids:
        try:
            os.kill(pid, 0)
            alive.append(pid)
        except ProcessLookupError:
            pass
    return alive


def descendants(pid: int) -> list[int]:
    out = subprocess.run(['ps', '-e', '-o', 'pid=,ppid='], capture_output=True, text=True).stdout
    children: dict[int, list[int]] = {}
    for line in out.splitlines():
        child, parent = map(int, line.split())
        children.setdefault(parent, []).append(child)
    found, stack = [], [pid]
    while stack:
        for child in children.get(stack.pop(), []):
            found.append(child)
            stack.append(child)
    return found


@pytest.mark.parametrize('how', ['duration', 'ctrl-c'])
def test_live_graph_saves_the_map_and_leaves_no_orphans(tmp_path, how):
    args = [sys.executable, str(WORKSPACE / 'launch_scripts' / 'live_emulator.py'),
            '--output', str(tmp_path)]
    if how == 'duration':
        args += ['--duration', '6']
    launcher = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True)
    time.sleep(5.0)
    started = descendants(launcher.pid)
    assert len(started) >= 4, 'emulator, driver, registration and occupancy should run'
    if how == 'ctrl-c':
        launcher.send_signal(signal.SIGINT)
    output, _ = launcher.communicate(timeout=60)
    assert launcher.returncode == 0, output
    assert (tmp_path / 'live.npz').exists() and (tmp_path / 'live.ply').exists(), output
    assert 'points integrated' in output and 'frames published' in output
    time.sleep(0.5)
    assert children_alive(started) == [], f'orphans left: {children_alive(started)}'


def test_replaying_a_bag_of_a_live_run_replays_only_the_graphs_inputs(tmp_path):
    """A bag recorded from a live run also holds the graph's outputs (here diagnostics):
    the launcher replays only the driver's poses, so nothing waits for a subscriber that
    never comes, and every pose reaches the map."""
    from inhand_mapping.map_io import load_npz
    from pose_sessions import sphere_session, write_pose_bag
    frames, _ = sphere_session(seconds=2.0, surface_points=12, moving=False)
    bag = write_pose_bag(tmp_path / 'live_run', frames, diagnostics=True)
    result = subprocess.run(
        [sys.executable, str(WORKSPACE / 'launch_scripts' / 'replay_bag.py'), str(bag),
         '--output', str(tmp_path / 'out'), '--no-render'],
        capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    assert 'diagnostics' not in result.stderr          # not replayed, not waited for
    grid, _ = load_npz(tmp_path / 'out' / 'live_run.npz')
    assert grid.counts.integrated == 3 * len(frames)


def test_replaying_a_bundled_bag_makes_the_map_pictures_and_metrics(tmp_path):
    """What the demo does, on the small static bag: graph over DDS, save, render, metrics."""
    import json
    result = subprocess.run(
        [sys.executable, str(WORKSPACE / 'launch_scripts' / 'replay_bag.py'),
         str(WORKSPACE / 'bags' / 'cat_static'), '--output', str(tmp_path)],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert 'mapping_static.yaml' in result.stdout  # no object sensor in the bag
    for name in ('cat_static.npz', 'cat_static.ply', 'figure.png', 'map_above_0.8.png',
                 'cat_static.metrics.json'):
        assert (tmp_path / name).stat().st_size > 0, name
    metrics = json.loads((tmp_path / 'cat_static.metrics.json').read_text())
    assert metrics['frame'] == 'tracker'  # static session: the map is in the tracker frame
    assert metrics['points']['points'] == 3 * 120 * 15  # every fingertip sample registered
    assert metrics['points']['median_to_surface_mm'] < 3.0  # the bag lines up with its truth
    assert f'done: map, pictures and metrics are in {tmp_path}' in result.stdout
