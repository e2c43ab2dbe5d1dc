"""The launch scripts start the graph, save the map and leave no process behind."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
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


def wait_gone(pids: list[int], timeout: float) -> list[int]:
    """The pids still alive after waiting up to ``timeout`` s for them to end."""
    deadline = time.monotonic() + timeout
    while children_alive(pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    return children_alive(pids)


class LiveLauncher:
    """live_emulator.py running, its output read as it comes."""

    def __init__(self, *args: str):
        self.popen = subprocess.Popen(
            [sys.executable, str(WORKSPACE / 'launch_scripts' / 'live_emulator.py'), *args],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self.started: set[int] = set()
        self._reader = threading.Thread(target=lambda: self.lines.extend(self.popen.stdout),
                                        daemon=True)
        self._reader.start()

    def wait_mapping(self, after: float = 2.0) -> list[int]:
        """Until registered points flow (a loaded machine took over 5 s to start the graph,
        and the subscribers of registration/points matched before the driver streamed),
        then ``after`` seconds of mapping. Returns every process the launcher was seen to
        run meanwhile: with a short --duration it may already be stopping them by the end."""
        from ros_helpers import CloudCounter
        counter = CloudCounter('registration/points')
        try:
            deadline = time.monotonic() + 60
            while counter.points == 0:
                assert time.monotonic() < deadline and self.popen.poll() is None, \
                    self.output()
                self.started.update(descendants(self.popen.pid))
                time.sleep(0.1)
            end = time.monotonic() + after
            while time.monotonic() < end:
                self.started.update(descendants(self.popen.pid))
                time.sleep(0.1)
        finally:
            counter.close()
        return sorted(self.started)

    def output(self) -> str:
        return ''.join(self.lines)

    def wait(self, timeout: float) -> str:
        """Until it ends; its whole output."""
        self.popen.wait(timeout)
        self._reader.join(10)
        return self.output()


@pytest.mark.parametrize('how', ['duration', 'ctrl-c', 'ctrl-c-twice', 'sighup'])
def test_live_graph_saves_the_drained_map_and_leaves_no_orphans(tmp_path, how):
    """However the launcher is asked to stop (its --duration, Ctrl-C, a second Ctrl-C
    during the save, the terminal closing), the driver stops first, the graph drains,
    the save has everything (the occupancy node has nothing left to save at shutdown),
    and no process is left."""
    from inhand_mapping.map_io import load_npz
    live = LiveLauncher('--output', str(tmp_path),
                        *(['--duration', '10'] if how == 'duration' else []))
    started = live.wait_mapping()
    launcher = live.popen
    assert len(started) >= 4, 'emulator, driver, registration and occupancy should run'
    if how != 'duration':
        launcher.send_signal(signal.SIGHUP if how == 'sighup' else signal.SIGINT)
    if how == 'ctrl-c-twice':
        time.sleep(0.3)
        launcher.send_signal(signal.SIGINT)
    output = live.wait(60)
    assert launcher.returncode == 0, output
    assert 'Traceback' not in output, output
    if how == 'ctrl-c-twice':
        assert 'SIGINT again: still stopping' in output, output
    assert (tmp_path / 'live.npz').exists() and (tmp_path / 'live.ply').exists(), output
    assert 'points integrated' in output and 'frames published' in output
    assert 'saved at shutdown' not in output, output
    stopped = re.search(r'occupancy_node\]: stopped: .* (\d+) points integrated', output)
    grid, _ = load_npz(tmp_path / 'live.npz')
    assert stopped and grid.counts.integrated == int(stopped.group(1)) > 0, output
    assert wait_gone(started, 5.0) == [], 'orphans left'


def test_kill_9_of_the_launcher_leaves_no_orphans_and_the_map_is_saved(tmp_path):
    """kill -9 gives the launcher no chance: the kernel's parent-death signal stops its
    children, and the occupancy node saves what it has as on any SIGTERM."""
    live = LiveLauncher('--output', str(tmp_path), '--autosave', '0')
    started = live.wait_mapping()          # the shutdown save needs points in the map
    launcher = live.popen
    assert len(started) >= 4, 'emulator, driver, registration and occupancy should run'
    launcher.kill()
    launcher.wait()
    assert wait_gone(started, 30.0) == [], 'orphans left'
    assert (tmp_path / 'live.npz').exists()      # autosave off: the shutdown save


def test_ctrl_c_during_a_replay_saves_what_was_mapped(tmp_path):
    """Ctrl-C in the middle of a timed replay: the replay stops, what reached the graph is
    saved, exit code 130, no pictures, nothing left running."""
    from inhand_mapping.map_io import load_npz
    launcher = subprocess.Popen(
        [sys.executable, str(WORKSPACE / 'launch_scripts' / 'replay_bag.py'),
         str(WORKSPACE / 'bags' / 'cat_static'), '--output', str(tmp_path), '--rate', '1'],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 90
    lines = []
    for line in launcher.stdout:          # until the replay has run a few seconds
        lines.append(line)
        done = re.search(r'\]\s+([\d.]+)%', line)
        if line.startswith('[replay]') and done and float(done.group(1)) > 0:
            break
        assert time.monotonic() < deadline, ''.join(lines)
    time.sleep(3.0)
    started = descendants(launcher.pid)
    launcher.send_signal(signal.SIGINT)
    output, _ = launcher.communicate(timeout=60)
    output = ''.join(lines) + output
    assert launcher.returncode == 130, output
    assert 'Traceback' not in output and 'interrupted: saving' in output, output
    grid, _ = load_npz(tmp_path / 'cat_static.npz')
    assert 0 < grid.counts.integrated < 3 * 120 * 15, grid.counts   # a part of the bag
    assert not (tmp_path / 'figure.png').exists()
    assert wait_gone(started, 5.0) == [], 'orphans left'


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
                 'cat_static.metrics.json', 'cat_static_shape.png', 'cat_static_parts.yaml',
                 'cat_static_surface.stl', 'cat_static_uncertainty.png',
                 'cat_static_predicted.ply', 'cat_static_next_touch.yaml'):
        assert (tmp_path / name).stat().st_size > 0, name
    import yaml

    from inhand_tools.map_cells import load_map
    # the occupancy node records the graph's mode (the registration node's) in its map
    assert load_map(tmp_path / 'cat_static.npz').metadata['extra']['registration_mode'] == 'static'
    guidance = yaml.safe_load((tmp_path / 'cat_static_next_touch.yaml').read_text())
    assert guidance['support'] is not None and guidance['suggestions']   # static: on the table
    metrics = json.loads((tmp_path / 'cat_static.metrics.json').read_text())
    assert metrics['frame'] == 'tracker'  # static session: the map is in the tracker frame
    assert metrics['points']['points'] == 3 * 120 * 15  # every fingertip sample registered
    assert metrics['points']['median_to_surface_mm'] < 3.0  # the bag lines up with its truth
    assert f'done: map, pictures and metrics are in {tmp_path}' in result.stdout
