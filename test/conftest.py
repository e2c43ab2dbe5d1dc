"""Shared test set-up: paths and a DDS domain of our own for tests that use ROS."""

import os
import pathlib

import pytest

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
