"""Real fingers: the sensor on the nail (tip offsets), the round pad (pad radius), pivot
calibration, and sessions simulated with both.

The maths is checked against hand-built poses; calibration against simulated pivots with a
known offset and 1 mm tracker noise; the whole chain (simulate_session with real fingers,
build_map with the offsets and the radius, map_metrics) against the same session with
point fingertips.
"""

from __future__ import annotations

import math
import os
import re
import subprocess

import cv2
import numpy as np
import pytest
import yaml

from inhand_common.parameters import ParameterError
from inhand_common.rotations import euler_zyx_to_quaternion
from inhand_mapping.mapping_config import load_parameters
from inhand_mapping.pad_normals import PadNormals
from inhand_mapping.pivot_calibration import pivot_window, solve_pivot
from inhand_mapping.registration import Registrar
from inhand_mapping.tip_offsets import TipOffsets
from inhand_sim.pivot import PivotSettings, simulate_pivot
from inhand_sim.session import write_bag
from inhand_tools.launching import driver_command
from polhemus_liberty.emulator import LibertyEmulator
from polhemus_liberty.motion import load_pose_bag
from ros_helpers import WORKSPACE, executable_path, running

QUARTER_TURN_Z = euler_zyx_to_quaternion(math.pi / 2, 0.0, 0.0)   # x -> y


def test_the_pad_centre_is_the_offset_turned_with_the_sensor():
    offsets = TipOffsets([[0.01, 0.0, 0.0], [0.0, 0.0, -0.02]])
    sensors = np.array([[0.1, 0.2, 0.3], [0.0, 0.0, 0.0]])
    centres, _, valid = offsets.pads(sensors, np.stack([QUARTER_TURN_Z] * 2), np.array([0, 1]))
    assert valid.all()
    np.testing.assert_allclose(centres, [[0.1, 0.21, 0.3], [0.0, 0.0, -0.02]], atol=1e-12)


def test_the_contact_is_one_pad_radius_further_the_way_the_pad_faces():
    # facing = the offset's direction; with no offset, the sensor's -z (no surface traced
    # yet, so the registrar goes the way the finger's frame says)
    offsets = TipOffsets([[0.01, 0.0, 0.0], [0.0, 0.0, 0.0]], pad_radius=0.005)
    registrar = Registrar('static', tip_offsets=offsets)
    registrar.add_fingertips([0.0, 0.0], np.zeros((2, 3)), [0, 1],
                             quaternions=np.stack([QUARTER_TURN_Z] * 2))
    contacts, _, fingers = registrar.finish()
    assert fingers.tolist() == [0, 1]
    np.testing.assert_allclose(contacts, [[0.0, 0.015, 0.0], [0.0, 0.0, -0.005]], atol=1e-12)


def test_the_registrar_places_contacts_and_counts_rows_it_cannot_place():
    registrar = Registrar('static', tip_offsets=TipOffsets([[0.0, 0.0, -0.01]] * 2))
    with pytest.raises(ValueError, match='quaternions'):
        registrar.add_fingertips([0.0], [[0.0, 0.0, 0.0]], [0])
    q = np.array([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    registrar.add_fingertips([0.0, 0.0, 0.0], np.zeros((3, 3)), [0, 1, 5], quaternions=q)
    points, _, fingers = registrar.finish()
    np.testing.assert_allclose(points, [[0.0, 0.0, -0.01]])
    assert fingers.tolist() == [0]
    # the zero quaternion and the finger beyond the table: dropped, counted
    assert registrar.stats.dropped_invalid == 2
    assert registrar.stats.received == registrar.stats.registered + 2


def _pad_centres_over_a_plane(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Pad centres 7 mm over the plane z = 0 (1 mm noise), a patch 8 cm wide, 240 Hz."""
    rng = np.random.default_rng(seed)
    centres = np.c_[rng.uniform(-0.04, 0.04, (n, 2)), 0.007 + rng.normal(0.0, 0.001, n)]
    return centres, np.arange(n) / 240.0


def test_a_rolled_pad_touches_along_the_surface_the_pads_have_traced():
    # the finger rolled 40 degrees: its frame says the pad faces 40 degrees off the normal
    centres, times = _pad_centres_over_a_plane(6000)
    roll = math.radians(40.0)
    facing = np.tile([0.0, math.sin(roll), -math.cos(roll)], (len(centres), 1))
    normals = PadNormals()
    contacts = normals.contacts(centres, facing, times, 0.007)
    assert normals.fitted > 0.9 * len(centres)
    late = contacts[len(centres) // 2:]
    # on the surface (7 mm down), not 7 (1 - cos 40) = 1.6 mm over it
    assert abs(float(np.mean(late[:, 2]))) < 0.0003
    directions = (contacts - centres)[len(centres) // 2:] / 0.007
    assert float(np.median(directions[:, 2])) < -0.99


def test_pad_normals_do_not_depend_on_how_the_points_were_batched():
    centres, times = _pad_centres_over_a_plane(3000, seed=1)
    times = np.repeat(times[::3], 3)      # three fingers share each stamp
    facing = np.tile([0.0, 0.0, -1.0], (len(centres), 1))
    whole = PadNormals().contacts(centres, facing, times, 0.007)
    split = PadNormals()
    # the registrar releases whole stamps (all stations of a tracker frame at once)
    stamps = np.array_split(np.arange(len(centres) // 3), 41)
    parts = [split.contacts(centres[rows], facing[rows], times[rows], 0.007)
             for rows in (np.arange(3 * k[0], 3 * k[-1] + 3) for k in stamps)]
    assert np.array_equal(whole, np.concatenate(parts))


def test_a_lone_stroke_keeps_the_fingers_own_facing():
    # one straight stroke: its centres are a line, which has no normal
    n = 400
    centres = np.c_[np.linspace(0.0, 0.08, n), np.zeros(n), np.full(n, 0.007)]
    facing = np.tile([0.0, math.sin(0.3), -math.cos(0.3)], (n, 1))
    normals = PadNormals()
    contacts = normals.contacts(centres, facing, np.arange(n) / 240.0, 0.007)
    assert normals.fitted == 0
    np.testing.assert_allclose(contacts, centres + 0.007 * facing)


def test_zero_offsets_and_radius_leave_the_raw_positions():
    registrar = load_parameters(None, {'mode': 'static'})[0].make_registrar()
    assert registrar.tip_offsets is None
    registrar.add_fingertips([0.0], [[0.1, 0.2, 0.3]], [0])   # no quaternions needed
    np.testing.assert_allclose(registrar.finish()[0], [[0.1, 0.2, 0.3]])


def test_tip_offsets_parameter_takes_one_triple_or_one_per_finger():
    registration, _ = load_parameters(None, {'tip_offsets': [0.0, 0.001, -0.01]})
    assert registration.tip_offsets == (0.0, 0.001, -0.01) * 3
    with pytest.raises(ParameterError, match=r"'tip_offsets' has 6 numbers: allowed is 3 .* or 9"):
        load_parameters(None, {'tip_offsets': [0.0] * 6})
    with pytest.raises(ParameterError, match=r"'tip_offsets' = .* allowed is a list of at least 3"):
        load_parameters(None, {'tip_offsets': [0.0, 0.0, 0.5]})
    with pytest.raises(ParameterError,
                       match=r"'pad_radius' = 0.05 is refused: allowed is a number in \[0, 0.02\]"):
        load_parameters(None, {'pad_radius': 0.05})


@pytest.mark.parametrize('tilt', [30.0, 45.0, 60.0])
def test_pivot_calibration_finds_the_offset_within_a_millimetre(tilt):
    truth = ((0.004, 0.001, -0.011), (0.0, -0.003, -0.009), (0.002, 0.0, -0.012))
    for seed in range(3):
        session = simulate_pivot(PivotSettings(tip_offsets=truth, tilt_deg=tilt, seed=seed))
        times = (session.stamps_ns - session.stamps_ns[0]) / 1e9
        for finger in range(3):
            window = pivot_window(times, session.poses[finger, :, 3:])
            # the pivot is found: the resting poses (two thirds of the stream) are left out
            assert window.sum() < 0.45 * len(times)
            result = solve_pivot(session.poses[finger, window, :3],
                                 session.poses[finger, window, 3:])
            assert result.accepted, result.summary('finger')
            assert np.linalg.norm(result.offset - truth[finger]) < 0.001
            np.testing.assert_allclose(result.pivot, session.pivots[finger], atol=0.0015)
            # 1 mm per axis of noise: about sqrt(3) mm RMS
            assert 0.0012 < result.residual < 0.0025
            assert abs(result.rotation_deg - tilt) < 0.25 * tilt + 5


@pytest.mark.parametrize('tilt, twist, reason', [
    (10.0, 2.0, 'turned 1[0-4] deg, at least 15 needed'),
    (0.0, 30.0, 'uncertain .* tilt the finger about more than one axis'),
])
def test_a_poor_pivot_is_refused_with_what_to_do(tilt, twist, reason):
    session = simulate_pivot(PivotSettings(tilt_deg=tilt, twist_deg=twist, seed=1))
    times = (session.stamps_ns - session.stamps_ns[0]) / 1e9
    window = pivot_window(times, session.poses[0, :, 3:])
    result = solve_pivot(session.poses[0, window, :3], session.poses[0, window, 3:])
    assert not result.accepted
    assert result.problem and re.search(reason, result.problem), result.problem


def test_a_finger_that_never_pivots_is_refused():
    still = np.tile([0.0, 0.0, 0.0, 1.0], (300, 1))
    window = pivot_window(np.arange(300) / 30.0, still)
    assert not window.any()
    result = solve_pivot(np.zeros((0, 3)), still[window])
    assert 'at least 30 needed' in result.problem


def test_calibrate_fingertips_writes_what_build_map_reads(tmp_path):
    bag = tmp_path / 'pivot'
    simulate = [executable_path('simulate_pivot'), '--output', str(bag), '--tip-offset', '3', '0',
                '-10', '--seconds', '6']
    subprocess.run(simulate, check=True, capture_output=True, timeout=120)
    output = tmp_path / 'fingers.yaml'
    figure = tmp_path / 'pivot.png'
    done = subprocess.run([executable_path('calibrate_fingertips'), str(bag), '--output',
                           str(output), '--figure', str(figure)], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.count('residual') == 3
    # the geometry and one panel per finger, side by side
    picture = cv2.imread(str(figure))
    assert picture is not None and picture.shape[1] == 4 * 420
    panels = picture[60:440].reshape(380, 4, 420, 3)
    assert all((panel < 200).any(axis=2).mean() > 0.005 for panel in panels.transpose(1, 0, 2, 3))
    registration, _ = load_parameters([str(WORKSPACE / 'config' / 'mapping_static.yaml'),
                                       str(output)], {})
    offsets = np.array(registration.tip_offsets).reshape(3, 3)
    np.testing.assert_allclose(offsets, [[0.003, 0.0, -0.010]] * 3, atol=0.0012)
    assert yaml.safe_load(output.read_text())['/**/registration_node']['ros__parameters']

    # too little rotation: refused in one line per finger, nothing written
    poor = tmp_path / 'poor'
    subprocess.run([*simulate[:2], str(poor), '--tilt-deg', '8', '--twist-deg', '2'],
                   check=True, capture_output=True, timeout=120)
    refused = tmp_path / 'refused.yaml'
    done = subprocess.run([executable_path('calibrate_fingertips'), str(poor), '--output',
                           str(refused)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert done.stderr.count('REFUSED, the finger turned') == 3
    assert 'nothing written' in done.stderr and not refused.exists()


def test_a_session_with_real_fingers_maps_like_point_fingertips_once_calibrated(tmp_path):
    """The sensor 10 mm over a 7 mm pad, the finger rolling: raw, the map is the object
    inflated by the finger; with the offset and the radius, it is the point-finger map."""
    common = ['--object', 'cat', '--static', '--rate', '30', '--duration', '40', '--seed', '4',
              '--speed', '5', '--quiet']
    config = str(WORKSPACE / 'config' / 'mapping_static.yaml')
    fingers = tmp_path / 'fingers.yaml'
    fingers.write_text('/**/registration_node:\n  ros__parameters:\n'
                       '    tip_offsets: [0.003, 0.0, -0.010]\n    pad_radius: 0.007\n')
    scores = {}
    for name, extra, configs in (
            ('ideal', [], [config]),
            ('raw', ['--tip-offset-mm', '3', '0', '-10', '--pad-radius-mm', '7',
                     '--finger-roll-deg', '20'], [config]),
            ('calibrated', None, [config, str(fingers)])):
        bag = tmp_path / ('real' if extra is None else name)
        if extra is not None:
            subprocess.run([executable_path('simulate_session'), *common, *extra, '--output',
                            str(bag)], check=True, capture_output=True, timeout=300)
        config_args = [a for c in configs for a in ('--config', c)]
        if name == 'raw':
            bag = bag.rename(tmp_path / 'real')
            bag.with_name('raw.truth.npz').rename(tmp_path / 'real.truth.npz')
        subprocess.run([executable_path('build_map'), str(bag), *config_args, '--output-dir',
                        str(tmp_path), '--name', name, '--quiet'], check=True,
                       capture_output=True, timeout=300)
        report = tmp_path / f'{name}.json'
        subprocess.run([executable_path('map_metrics'), str(tmp_path / f'{name}.npz'), '--truth',
                        str(bag.with_name(bag.name + '.truth.npz')), '--json', str(report)],
                       check=True, capture_output=True, timeout=300)
        scores[name] = yaml.safe_load(report.read_text())['thresholds']['0.8']
    assert scores['raw']['fscore_at_5mm'] < 0.3
    assert scores['raw']['normal_offset_mm'] > 10
    for key in ('fscore_at_5mm', 'precision_at_5mm'):
        assert scores['calibrated'][key] >= scores['ideal'][key] - 0.02, (key, scores)
    assert abs(scores['calibrated']['normal_offset_mm']) < 1.5


@pytest.mark.dds
def test_live_calibration_of_a_pivot_played_by_the_emulator(tmp_path):
    """A pivot session through the whole live chain: the emulated Liberty plays it on a
    pty, the driver publishes it, calibrate_fingertips --live reads the topics."""
    truth = ((0.003, 0.0, -0.010), (0.002, 0.001, -0.011), (0.0, -0.002, -0.009))
    settings = PivotSettings(tip_offsets=truth, tilt_deg=40.0, seconds=3.0, seed=2)
    session = simulate_pivot(settings)
    bag = tmp_path / 'pivot'
    write_bag(session, bag)
    motion = load_pose_bag(bag, {'thumb': 1, 'index': 2, 'middle': 3})
    # one whole loop of the session and one finger's turn more: every finger's pivot is
    # heard whole at least once, wherever the loop was when listening began
    listen = motion.duration + settings.seconds + 2 * settings.approach + 1.0
    output = tmp_path / 'fingers.yaml'
    port = f'/tmp/liberty-pivot-{os.getpid()}'
    with LibertyEmulator(motion, port, stations=(1, 2, 3)) as emulator, \
            running(driver_command(str(WORKSPACE / 'config' / 'liberty_emulator.yaml'),
                                   emulator.port, 'stations:=[1, 2, 3]',
                                   "station_names:=['thumb', 'index', 'middle']")) as driver:
        done = subprocess.run([executable_path('calibrate_fingertips'), '--live', f'{listen:.1f}',
                               '--output', str(output)], capture_output=True, text=True,
                              timeout=listen + 60)
        assert driver.interrupt() == 0, driver.output()
    assert done.returncode == 0, done.stdout + done.stderr
    offsets = np.array(yaml.safe_load(output.read_text())
                       ['/**/registration_node']['ros__parameters']['tip_offsets']).reshape(3, 3)
    assert np.abs(offsets - np.array(truth)).max() < 0.0015, offsets
