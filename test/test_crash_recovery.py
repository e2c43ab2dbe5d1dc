"""A session cannot be repeated: the occupancy node autosaves, saves at shutdown, and
starts again from a saved map after a crash (kill -9), over real DDS."""

from __future__ import annotations

import signal
import time

import numpy as np
import pytest

from inhand_mapping.map_io import load_npz
from polling import wait_until
from pose_sessions import sphere_session
from ros_helpers import WORKSPACE, PosePublisher, running

pytestmark = pytest.mark.dds

CONFIG = str(WORKSPACE / 'config' / 'mapping_static.yaml')


def wait_for_file(path, timeout: float = 20.0) -> None:
    wait_until(path.exists, timeout, str(path), period=0.1)


def test_autosave_kill_9_and_resume_from_the_autosave(tmp_path):
    frames, _ = sphere_session(seconds=1.0, surface_points=12, moving=False)
    fingers = [(t, {k: v for k, v in frame.items() if k != 'object'}) for t, frame in frames]
    ros = ['--ros-args', '--params-file', CONFIG]
    occupancy = ['occupancy_node', *ros, '-p', f'output_dir:={tmp_path}']
    with running(['registration_node', *ros]) as registration:
        with running([*occupancy, '-p', 'autosave_period:=0.5']) as first:
            # registration -> occupancy matched first
            registration.wait_for_matches(['registration/points'], 'subscriber')
            publisher = PosePublisher(['thumb', 'index', 'middle'])
            try:
                publisher.wait_for_subscribers(reader=registration)
                publisher.publish(fingers, rate_factor=4.0)
            finally:
                publisher.close()
            autosaved = tmp_path / 'map.npz'
            deadline = time.monotonic() + 20
            while True:    # the autosave of the whole session, nobody asked for a save
                if autosaved.exists() and load_npz(autosaved)[0].hits.sum() == 3 * len(frames):
                    break
                assert time.monotonic() < deadline, first.output()
                time.sleep(0.2)
            first.popen.send_signal(signal.SIGKILL)           # a crash: nothing more is said
            first.popen.wait(10)
        assert 'autosaved' in first.output()
        before, _ = load_npz(autosaved)
        with running([*occupancy, '-p', f'initial_map:={autosaved}', '-p',
                      'map_name:=resumed']) as second:
            deadline = time.monotonic() + 20
            while 'resumed:' not in second.output():
                assert time.monotonic() < deadline, second.output()
                time.sleep(0.1)
            assert second.interrupt() == 0                    # Ctrl-C: saved at shutdown
    assert f'resumed: {3 * len(frames)} hits' in second.output()
    assert 'saved at shutdown' in second.output()
    after, _ = load_npz(tmp_path / 'resumed.npz')
    assert np.array_equal(after.hits, before.hits)
    assert np.array_equal(after.log_odds, before.log_odds)


def test_an_initial_map_of_another_grid_is_refused(tmp_path):
    from inhand_mapping.map_products import save_map
    from inhand_mapping.occupancy import GridSpec, OccupancyGrid
    save_map(OccupancyGrid(GridSpec(0.2, 0.005)), tmp_path, 'small', 0.8)
    with running(['occupancy_node', '--ros-args', '-p',
                  f'initial_map:={tmp_path / "small.npz"}']) as node:
        assert node.popen.wait(30) == 2
    assert "parameter 'initial_map'" in node.output()
    assert '40^3 cells of 5 mm' in node.output() and 'must match' in node.output()
    with running(['occupancy_node', '--ros-args', '-p',
                  f'initial_map:={tmp_path / "none.npz"}']) as node:
        assert node.popen.wait(30) == 2
    assert "parameter 'initial_map'" in node.output()
