"""Shared test set-up: paths and a DDS domain of our own for tests that use ROS."""

import os
import pathlib

import pytest

# Tests that use DDS stay on this machine and in a domain of their own, so parallel runs
# (or a developer's live graph) never hear each other. Set before rclpy is imported.
os.environ.setdefault('ROS_DOMAIN_ID', str(100 + os.getpid() % 100))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

WORKSPACE = pathlib.Path(__file__).resolve().parents[1]
SHARED = WORKSPACE.parent / 'shared'


@pytest.fixture(scope='session')
def workspace() -> pathlib.Path:
    return WORKSPACE


@pytest.fixture(scope='session')
def liberty_recordings() -> pathlib.Path:
    """The real Liberty recordings kept beside the workspace (not copied into it)."""
    folder = SHARED / 'data' / 'liberty_recordings'
    if not (folder / 'plhm_mocap1.txt').exists():
        pytest.skip(f'real Liberty recordings not found at {folder} (they live in ../shared)')
    return folder


@pytest.fixture
def panel_labels(monkeypatch):
    """The (title, subtitle) of every panel the map pictures annotate, in order (records
    ``inhand_tools.drawing.annotate``'s arguments and still draws)."""
    from inhand_tools import drawing
    labels = []
    annotate = drawing.annotate

    def recording(image, camera, title=None, subtitle=None, frame_label=None):
        labels.append((title, subtitle or ''))
        return annotate(image, camera, title, subtitle, frame_label)

    monkeypatch.setattr(drawing, 'annotate', recording)
    return labels
