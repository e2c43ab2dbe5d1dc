"""The packages build with colcon as ament_python packages, as on a full ROS 2 install.

``ros2 run <pkg> <exe>`` looks for ``install/<pkg>/lib/<pkg>/<exe>``; the ament index
marker and package.xml must be installed too. The installed executable is then run.
"""

import os
import subprocess
import sys

import pytest

from conftest import WORKSPACE

EXECUTABLES = {
    'polhemus_liberty': ['liberty_driver', 'liberty_emulator'],
    'inhand_mapping': ['registration_node', 'occupancy_node'],
    'inhand_sim': ['simulate_session'],
    'inhand_stereo': ['stereo_node', 'calibrate_stereo', 'calibrate_camera_tracker'],
    'inhand_tools': ['bag_replay', 'bag_record', 'topic_echo', 'map_metrics', 'render_map',
                     'build_map', 'calibrate_vision_model', 'dds_profile'],
    'inhand_view': ['live_view'],
}


@pytest.fixture(scope='module')
def colcon_install(tmp_path_factory):
    base = tmp_path_factory.mktemp('colcon')
    colcon = os.path.join(os.path.dirname(sys.executable), 'colcon')
    result = subprocess.run(
        [colcon, '--log-base', str(base / 'log'), 'build', '--build-base', str(base / 'build'),
         '--install-base', str(base / 'install')],
        cwd=WORKSPACE, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    return base / 'install'


def test_every_package_installs_its_executables_and_manifest(colcon_install):
    packages = sorted(p.name for p in (WORKSPACE / 'src').iterdir() if (p / 'package.xml').exists())
    assert packages, 'no packages found under src/'
    for package in packages:
        prefix = colcon_install / package
        assert (prefix / 'share' / package / 'package.xml').is_file()
        assert (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / package).is_file()
        for executable in EXECUTABLES.get(package, []):
            path = prefix / 'lib' / package / executable
            assert path.is_file() and os.access(path, os.X_OK), f'{path} missing'


def test_installed_driver_runs_and_refuses_a_bad_parameter(colcon_install):
    site = [str(p) for p in colcon_install.glob('*/lib/python3*/site-packages')]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(site))
    driver = colcon_install / 'polhemus_liberty' / 'lib' / 'polhemus_liberty' / 'liberty_driver'
    result = subprocess.run([str(driver), '--ros-args', '-p', 'units:=furlong'],
                            capture_output=True, text=True, timeout=60, env=env)
    assert result.returncode == 2, result.stdout + result.stderr
    assert "parameter 'units' = 'furlong' is refused: allowed is one of 'cm', 'inch'" in \
        result.stderr


def test_installed_simulator_finds_its_shipped_meshes(colcon_install, tmp_path):
    share = colcon_install / 'inhand_sim' / 'share' / 'inhand_sim' / 'meshes'
    assert sorted(p.name for p in share.glob('*.ply')) == ['animal.ply', 'cup.ply', 'duck.ply']
    site = [str(p) for p in colcon_install.glob('*/lib/python3*/site-packages')]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(site))
    simulate = colcon_install / 'inhand_sim' / 'lib' / 'inhand_sim' / 'simulate_session'
    code = ('import sys; from inhand_sim.catalogue import mesh_folder; print(mesh_folder())')
    where = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                           timeout=60, env=env, cwd=tmp_path)
    assert where.stdout.strip() == str(share), where.stderr
    result = subprocess.run([str(simulate), '--object', 'cup', '--static', '--rate', '15',
                             '--duration', '2', '--seed', '1', '--output', str(tmp_path / 'cup'),
                             '--quiet'], capture_output=True, text=True, timeout=120, env=env)
    assert result.returncode == 0, result.stdout + result.stderr


def test_installed_mapping_reads_its_cell_judge(colcon_install, tmp_path):
    """The map's learned judge is package data (inhand_mapping/cell_judge_model.npz): an
    installed inhand_mapping reads it from the install, not from the source tree."""
    site = [str(p) for p in colcon_install.glob('*/lib/python3*/site-packages')]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(site))
    code = ('from inhand_mapping.cell_judge import MODEL_FILE, shipped_judge; '
            'print(MODEL_FILE, len(shipped_judge().roots))')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=120, env=env, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    where, trees = result.stdout.split()
    assert where.startswith(str(colcon_install)) and int(trees) > 0, result.stdout


def test_colcon_meta_gives_each_package_its_tests():
    colcon = os.path.join(os.path.dirname(sys.executable), 'colcon')
    result = subprocess.run([colcon, '--log-base', os.devnull, 'info', 'polhemus_liberty'],
                            cwd=WORKSPACE, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert "pytest-args: ['../../test/test_liberty_codec.py'" in result.stdout
    for line in result.stdout.splitlines():
        if 'pytest-args' in line:
            for path in line.split('[', 1)[1].strip(']').split(', '):
                assert (WORKSPACE / 'src' / 'polhemus_liberty' / path.strip("'")).resolve().is_file()
