"""Stereo and camera-to-tracker calibration on synthetic data with a known answer.

The chessboard pairs are drawn, not projected as points: every square is filled as a
polygon (its edges subdivided, so lens distortion bends them) through a known pair of
cameras, 4x supersampled with anti-aliasing, averaged down, blurred and given sensor noise,
so corner detection works on pixels as it would on a camera's images.
"""

from __future__ import annotations

import math
import subprocess

import cv2
import numpy as np
import pytest
import yaml

from inhand_common.rotations import quaternion_to_matrix
from inhand_stereo.calibration import (
    CalibrationError,
    Chessboard,
    ImagePair,
    calibrate_stereo,
    detect_chessboards,
)
from inhand_stereo.camera_info_yaml import (
    CameraInfoYamlError,
    read_camera_info_yaml,
    write_camera_info_yaml,
)
from inhand_stereo.camera_model import CameraModel
from inhand_stereo.rigid_fit import (
    CorrespondenceError,
    RigidFitError,
    camera_points,
    fit_rigid,
    read_correspondences,
    write_camera_pose_yaml,
)
from inhand_tools.launching import executable

# --- the synthetic rig: known intrinsics, 70 mm baseline, the right camera turned ~2 deg ---
SIZE = (640, 480)
K_LEFT = np.array([[600.0, 0.0, 322.0], [0.0, 603.0, 238.0], [0.0, 0.0, 1.0]])
D_LEFT = np.array([-0.12, 0.09, 0.0012, -0.0007, 0.0])
K_RIGHT = np.array([[596.0, 0.0, 317.0], [0.0, 598.5, 244.0], [0.0, 0.0, 1.0]])
D_RIGHT = np.array([-0.10, 0.07, -0.0009, 0.0005, 0.0])
RIGHT_CENTRE = np.array([0.07, 0.0015, -0.002])       # the right camera's centre, left frame (m)
R_RIGHT = cv2.Rodrigues(np.array([0.006, -0.035, 0.008]))[0]  # p_right = R (p_left - centre)
T_RIGHT = -R_RIGHT @ RIGHT_CENTRE
BASELINE = float(np.linalg.norm(RIGHT_CENTRE))
BOARD = Chessboard(8, 6, 0.025)
SUPERSAMPLE = 4


def _outline(x0: float, y0: float, x1: float, y1: float, n: int = 6) -> np.ndarray:
    """A rectangle on the board (z = 0) as 4n points along its edges."""
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    xy = np.concatenate([
        np.stack([x0 + (x1 - x0) * t, np.full(n, y0)], 1),
        np.stack([np.full(n, x1), y0 + (y1 - y0) * t], 1),
        np.stack([x1 - (x1 - x0) * t, np.full(n, y1)], 1),
        np.stack([np.full(n, x0), y1 - (y1 - y0) * t], 1)])
    return np.concatenate([xy, np.zeros((len(xy), 1))], 1)


def render(k, d, rotation, translation, rng) -> np.ndarray:
    """The board (white margin, black squares) on a grey background as one camera sees it."""
    w, h = SIZE
    image = np.full((h * SUPERSAMPLE, w * SUPERSAMPLE), 90, np.uint8)
    rvec = cv2.Rodrigues(rotation)[0]

    def fill(outline, grey):
        uv, _ = cv2.projectPoints(outline, rvec, translation, k, d)
        uv = uv.reshape(-1, 2) * SUPERSAMPLE + (SUPERSAMPLE - 1) / 2
        cv2.fillPoly(image, [np.round(uv * 256).astype(np.int32)], grey, cv2.LINE_AA, shift=8)

    s, margin = BOARD.square, 1.5 * BOARD.square
    fill(_outline(-s - margin, -s - margin, BOARD.columns * s + margin,
                  BOARD.rows * s + margin, 12), 235)
    for i in range(BOARD.columns + 1):
        for j in range(BOARD.rows + 1):
            if (i + j) % 2 == 0:
                fill(_outline((i - 1) * s, (j - 1) * s, i * s, j * s), 25)
    small = cv2.GaussianBlur(cv2.resize(image, SIZE, interpolation=cv2.INTER_AREA), (0, 0), 0.7)
    return np.clip(small + rng.normal(0.0, 1.5, small.shape), 0, 255).astype(np.uint8)


def board_poses(count: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board poses in the left camera frame, tilted up to 35 degrees, 0.45-0.75 m away,
    the whole board (with its margin) inside both images."""
    rng = np.random.default_rng(seed)
    s = BOARD.square
    centre = np.array([(BOARD.columns - 1) * s / 2, (BOARD.rows - 1) * s / 2, 0.0])
    extent = np.array([[x, y, 0.0] for x in (-2.5 * s, (BOARD.columns + 1.5) * s)
                       for y in (-2.5 * s, (BOARD.rows + 1.5) * s)])
    poses = []
    while len(poses) < count:
        rotation = cv2.Rodrigues(np.radians([rng.uniform(-35, 35), rng.uniform(-35, 35),
                                             rng.uniform(-25, 25)]))[0]
        position = np.array([rng.uniform(-0.12, 0.16), rng.uniform(-0.08, 0.08),
                             rng.uniform(0.45, 0.75)])
        translation = position - rotation @ centre
        inside = True
        for k, d, r_cam, t_cam in ((K_LEFT, D_LEFT, np.eye(3), np.zeros(3)),
                                   (K_RIGHT, D_RIGHT, R_RIGHT, T_RIGHT)):
            uv, _ = cv2.projectPoints(extent, cv2.Rodrigues(r_cam @ rotation)[0],
                                      r_cam @ translation + t_cam, k, d)
            uv = uv.reshape(-1, 2)
            inside &= bool(uv.min() > 15 and (uv[:, 0] < SIZE[0] - 15).all()
                           and (uv[:, 1] < SIZE[1] - 15).all())
        if inside:
            poses.append((rotation, translation))
    return poses


def render_pairs(count: int = 15, seed: int = 3) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed + 100)
    return [(render(K_LEFT, D_LEFT, rotation, translation, rng),
             render(K_RIGHT, D_RIGHT, R_RIGHT @ rotation, R_RIGHT @ translation + T_RIGHT, rng))
            for rotation, translation in board_poses(count, seed)]


@pytest.fixture(scope='module')
def pairs():
    return render_pairs()


def image_pairs(pairs):
    return [ImagePair(f'{i:04d}', left, right) for i, (left, right) in enumerate(pairs)]


def write_folder(folder, pairs):
    folder.mkdir(parents=True, exist_ok=True)
    for i, (left, right) in enumerate(pairs):
        cv2.imwrite(str(folder / f'left-{i:04d}.png'), left)
        cv2.imwrite(str(folder / f'right-{i:04d}.png'), right)
    return folder


def run(command: str, *args) -> subprocess.CompletedProcess:
    return subprocess.run([executable(command), *map(str, args)], capture_output=True,
                          text=True, timeout=120)


def assert_refused(result: subprocess.CompletedProcess, *words: str) -> None:
    """Exit 2 with one line on stderr naming the problem, no traceback."""
    assert result.returncode == 2, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert 'Traceback' not in result.stderr
    for word in words:
        assert word in lines[0], lines[0]


def assert_recovers_the_rig(left: CameraModel, right: CameraModel) -> None:
    for model, k in ((left, K_LEFT), (right, K_RIGHT)):
        assert model.K[0, 0] == pytest.approx(k[0, 0], rel=0.01)
        assert model.K[1, 1] == pytest.approx(k[1, 1], rel=0.01)
        assert model.K[0, 2] == pytest.approx(k[0, 2], abs=5.0)
        assert model.K[1, 2] == pytest.approx(k[1, 2], abs=5.0)
    # CameraInfo's convention: the left P has no translation, the right one -fx' * baseline.
    assert left.P[0, 3] == 0.0
    assert -right.P[0, 3] / right.P[0, 0] == pytest.approx(BASELINE, rel=0.01)
    assert np.allclose(left.P[:, :3], right.P[:, :3])  # zero disparity at infinity: same f, c
    for model in (left, right):
        assert np.allclose(model.R @ model.R.T, np.eye(3), atol=1e-9)


# --- stereo calibration --------------------------------------------------------------------

def test_calibration_recovers_intrinsics_and_baseline(pairs):
    detections = detect_chessboards(image_pairs(pairs), BOARD)
    assert len(detections.pairs) == len(pairs) and not detections.rejected
    result = calibrate_stereo(detections)
    assert_recovers_the_rig(result.left, result.right)
    assert result.baseline == pytest.approx(BASELINE, rel=0.01)
    assert result.translation[0] < 0  # the right camera sits along +x of the left one
    true_angle = math.degrees(np.linalg.norm(cv2.Rodrigues(R_RIGHT)[0]))
    assert result.rotation_angle == pytest.approx(true_angle, abs=0.3)
    assert result.epipolar_error < 0.5
    assert result.rms < 0.5
    # Joint refinement lands on the same rig.
    joint = calibrate_stereo(detections, joint=True)
    assert_recovers_the_rig(joint.left, joint.right)
    assert joint.epipolar_error < 0.5


def test_a_repeated_view_is_skipped_and_swapped_cameras_are_refused(pairs):
    repeated = image_pairs(pairs[:8]) + [ImagePair('again', *pairs[0])]
    detections = detect_chessboards(repeated, BOARD)
    assert len(detections.pairs) == 8
    assert detections.rejected == [('again', 'nearly the same view as an earlier pair')]
    swapped = detect_chessboards([ImagePair(p.name, p.right, p.left)
                                  for p in image_pairs(pairs[:8])], BOARD)
    with pytest.raises(CalibrationError, match='swapped'):
        calibrate_stereo(swapped)


def test_right_corners_are_put_in_the_order_of_the_left_ones(pairs):
    """The detector may start at either end of the board; a pair ordered differently would
    pull the extrinsics half a turn apart."""
    from inhand_stereo.calibration import _match_order, find_chessboard
    left, right = (find_chessboard(image, BOARD) for image in pairs[0])
    assert np.array_equal(_match_order(left, right[::-1].copy(), BOARD), right)
    square = Chessboard(4, 4, 0.025)
    grid = left.reshape(6, 8, 2)[:4, :4].reshape(-1, 1, 2)
    turned = np.rot90(grid.reshape(4, 4, 2)).reshape(-1, 1, 2)
    assert np.array_equal(_match_order(grid, turned + [30.0, 1.0], square), grid + [30.0, 1.0])


def test_too_few_pairs_are_refused_with_the_count(pairs):
    blank = np.full((SIZE[1], SIZE[0]), 128, np.uint8)
    views = image_pairs(pairs[:3]) + [ImagePair('empty', blank, blank),
                                      ImagePair('half', pairs[3][0], blank)]
    detections = detect_chessboards(views, BOARD)
    with pytest.raises(CalibrationError) as refused:
        calibrate_stereo(detections)
    message = str(refused.value)
    assert '3 of 5 pairs show the whole 8x6 chessboard' in message
    assert 'at least 6' in message
    assert 'no whole chessboard in the right image (half)' in message
    assert len(detections.left_only) == 1  # the half pair still serves the left intrinsics


def test_calibrate_stereo_command_on_a_folder(pairs, tmp_path):
    folder = write_folder(tmp_path / 'pairs', pairs)
    cv2.imwrite(str(folder / 'left-0099.png'), pairs[0][0])  # no right partner
    result = run('calibrate_stereo', folder, '--size', '8x6', '--square', '0.025',
                 '--output-dir', tmp_path / 'out', '--camera-name', 'rig')
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert f'{len(pairs)} pairs used, 1 not used (of {len(pairs) + 1})' in out
    assert 'not used: 1 left image without a right one of the same name (0099)' in out
    assert 'RMS reprojection error' in out and 'epipolar error after rectification' in out
    left = read_camera_info_yaml(tmp_path / 'out' / 'left.yaml')
    right = read_camera_info_yaml(tmp_path / 'out' / 'right.yaml')
    assert (left.name, right.name) == ('rig/left', 'rig/right')
    assert (left.width, left.height) == SIZE
    assert_recovers_the_rig(left, right)
    text = (tmp_path / 'out' / 'right.yaml').read_text()
    assert text.startswith('image_width: 640\nimage_height: 480\ncamera_name: rig/right\n')


def write_image_bag(path, pairs):
    """stereo/left and stereo/right image_raw: left mono8, right bgr8 with a padded step,
    plus one left image whose right partner never comes."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    Image = store.types['sensor_msgs/msg/Image']
    Header = store.types['std_msgs/msg/Header']
    Time = store.types['builtin_interfaces/msg/Time']

    def image(stamp_ns, pixels, encoding):
        height, width = pixels.shape[:2]
        rows = pixels.reshape(height, -1)
        step = rows.shape[1] + 8
        data = np.zeros((height, step), np.uint8)
        data[:, :rows.shape[1]] = rows
        header = Header(Time(stamp_ns // 10**9, stamp_ns % 10**9), 'stereo_left_optical')
        return Image(header, height, width, encoding, 0, step, data.ravel())

    msgtype = 'sensor_msgs/msg/Image'
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        left = writer.add_connection('/stereo/left/image_raw', msgtype, typestore=store)
        right = writer.add_connection('/stereo/right/image_raw', msgtype, typestore=store)
        for i, (grey_left, grey_right) in enumerate(pairs):
            stamp = 10**9 + i * 100_000_000
            colour = cv2.cvtColor(grey_right, cv2.COLOR_GRAY2BGR)
            writer.write(left, stamp, store.serialize_cdr(image(stamp, grey_left, 'mono8'),
                                                          msgtype))
            writer.write(right, stamp + 1000, store.serialize_cdr(image(stamp, colour, 'bgr8'),
                                                                  msgtype))
        lone = 10**9 + len(pairs) * 100_000_000
        writer.write(left, lone, store.serialize_cdr(image(lone, pairs[0][0], 'mono8'), msgtype))
    return path


def test_calibrate_stereo_command_on_a_bag(pairs, tmp_path, capsys):
    from inhand_stereo.commands import calibrate_stereo as command
    bag = write_image_bag(tmp_path / 'bag', pairs[:10])
    code = command.main([str(bag), '--size', '8x6', '--square', '0.025',
                         '--output-dir', str(tmp_path / 'out')])
    out = capsys.readouterr().out
    assert code == 0, out
    assert '10 pairs used, 1 not used (of 11)' in out
    assert 'left image with no right image of the same stamp' in out
    assert_recovers_the_rig(read_camera_info_yaml(tmp_path / 'out' / 'left.yaml'),
                            read_camera_info_yaml(tmp_path / 'out' / 'right.yaml'))


def test_calibrate_stereo_refuses_bad_input(pairs, tmp_path):
    arguments = ('--size', '8x6', '--square', '0.025', '--output-dir', tmp_path / 'out')
    assert_refused(run('calibrate_stereo', tmp_path / 'missing', *arguments),
                   'missing: no such folder or bag')
    blank = np.full((SIZE[1], SIZE[0]), 128, np.uint8)
    empty = write_folder(tmp_path / 'blank', [(blank, blank)] * 6)
    assert_refused(run('calibrate_stereo', empty, *arguments),
                   '0 of 6 pairs show the whole 8x6 chessboard', 'inner corners')
    no_images = tmp_path / 'nothing'
    no_images.mkdir()
    assert_refused(run('calibrate_stereo', no_images, *arguments), 'no left*.png')
    folder = write_folder(tmp_path / 'good', pairs[:6])
    assert_refused(run('calibrate_stereo', folder, '--size', '8by6', '--square', '0.025'),
                   '--size')
    assert not (tmp_path / 'out').exists()


# --- camera_info YAML ----------------------------------------------------------------------

def example_model(name='stereo/right') -> CameraModel:
    return CameraModel.from_fields(
        640, 480, [601.234567891234, 0, 321.5, 0, 603.1, 239.75, 0, 0, 1],
        [-0.1234567, 0.0876, 1e-05, -0.00071, 0.0],
        [0.9998, 0.0123, -0.0156, -0.0122, 0.99991, 0.0047, 0.0157, -0.0045, 0.99987],
        [598.7, 0, 318.2, -41.909, 0, 598.7, 241.3, 0, 0, 0, 1, 0], name=name)


def test_camera_info_yaml_round_trip_is_exact(tmp_path):
    model = example_model()
    path = write_camera_info_yaml(tmp_path / 'right.yaml', model)
    back = read_camera_info_yaml(path)
    assert (back.width, back.height, back.name, back.distortion_model) == \
        (640, 480, 'stereo/right', 'plumb_bob')
    for field in 'KDRP':
        assert np.array_equal(getattr(back, field), getattr(model, field)), field
    document = yaml.safe_load(path.read_text())
    assert list(document) == ['image_width', 'image_height', 'camera_name', 'camera_matrix',
                              'distortion_model', 'distortion_coefficients',
                              'rectification_matrix', 'projection_matrix']
    assert document['distortion_coefficients'] == {
        'rows': 1, 'cols': 5, 'data': [-0.1234567, 0.0876, 1e-05, -0.00071, 0.0]}
    # A name YAML would read as something else is quoted.
    odd = write_camera_info_yaml(tmp_path / 'odd.yaml', example_model('true: yes'))
    assert read_camera_info_yaml(odd).name == 'true: yes'


# As ROS's camera_calibration (cameracalibrator) writes right.yaml: numpy's array2string
# layout, '0.' for zeros.
CAMERA_CALIBRATION_RIGHT = """\
image_width: 640
image_height: 480
camera_name: narrow_stereo/right
camera_matrix:
  rows: 3
  cols: 3
  data: [ 596.83324,    0.     ,  316.89648,
            0.     ,  599.16311,  244.78812,
            0.     ,    0.     ,    1.     ]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.099395, 0.072133, -0.000487, 0.000612, 0.000000]
rectification_matrix:
  rows: 3
  cols: 3
  data: [ 0.99947694, -0.00422331,  0.03209398,
          0.00434468,  0.99998435, -0.00371476,
         -0.03207772,  0.00385229,  0.9994779 ]
projection_matrix:
  rows: 3
  cols: 4
  data: [ 622.29157,    0.     ,  327.64285,  -43.60997,
            0.     ,  622.29157,  239.94524,    0.     ,
            0.     ,    0.     ,    1.     ,    0.     ]
"""

# As camera_calibration_parsers (yaml-cpp) writes it: integers where the value is whole.
CAMERA_CALIBRATION_PARSERS_LEFT = """\
image_width: 640
image_height: 480
camera_name: narrow_stereo/left
camera_matrix:
  rows: 3
  cols: 3
  data: [600.5, 0, 321.8, 0, 603.4, 237.6, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.116, 0.0739, 0.00093, -0.00071, 0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [622.29157, 0, 327.64285, 0, 0, 622.29157, 239.94524, 0, 0, 0, 1, 0]
"""


def test_files_written_by_ros_read(tmp_path):
    path = tmp_path / 'right.yaml'
    path.write_text(CAMERA_CALIBRATION_RIGHT)
    model = read_camera_info_yaml(path)
    assert model.name == 'narrow_stereo/right'
    assert model.K[0, 0] == 596.83324 and model.K[1, 2] == 244.78812
    assert model.P[0, 3] == -43.60997 and model.D.shape == (5,)
    path.write_text(CAMERA_CALIBRATION_PARSERS_LEFT)
    left = read_camera_info_yaml(path)
    assert left.baseline_term == 0.0 and np.array_equal(left.R, np.eye(3))
    # camera_name and distortion_model may be left out (camera_calibration_parsers allows it).
    path.write_text(CAMERA_CALIBRATION_PARSERS_LEFT.replace('camera_name: narrow_stereo/left\n', '')
                    .replace('distortion_model: plumb_bob\n', ''))
    assert read_camera_info_yaml(path).distortion_model == 'plumb_bob'


@pytest.mark.parametrize('change, problem', [
    (('image_height: 480\n', ''), 'image_height is missing'),
    (('  cols: 4\n', '  cols: 3\n'), 'projection_matrix: cols is 3, a 3x4 matrix was expected'),
    (('[-0.116, 0.0739, 0.00093, -0.00071, 0]', '[-0.116, 0.0739]'),
     'distortion_coefficients: data holds 2 numbers but rows x cols is 1x5 = 5'),
    (('[600.5, 0,', '[0, 0,'), 'zero or negative focal length'),
    (('[1, 0, 0, 0, 1, 0, 0, 0, 1]', '[1, 0, 0, 0, one, 0, 0, 0, 1]'),
     "rectification_matrix: data[4] is 'one', not a number"),
    (('image_width: 640\n', 'image_width: [640\n'), 'not valid YAML at line'),
    (('image_width: 640\n', 'image_width: 640.5\n'), 'image_width must be a whole number'),
])
def test_malformed_camera_info_is_refused_with_file_and_problem(tmp_path, change, problem):
    path = tmp_path / 'left.yaml'
    path.write_text(CAMERA_CALIBRATION_PARSERS_LEFT.replace(*change))
    with pytest.raises(CameraInfoYamlError) as refused:
        read_camera_info_yaml(path)
    assert str(refused.value).startswith(f'{path}: ')
    assert problem in str(refused.value)


def test_missing_and_non_mapping_camera_info(tmp_path):
    with pytest.raises(CameraInfoYamlError, match='no such file'):
        read_camera_info_yaml(tmp_path / 'absent.yaml')
    (tmp_path / 'list.yaml').write_text('- 1\n- 2\n')
    with pytest.raises(CameraInfoYamlError, match='top level is not a mapping'):
        read_camera_info_yaml(tmp_path / 'list.yaml')


# --- camera to tracker ---------------------------------------------------------------------

TRUE_ROTATION = quaternion_to_matrix(np.array([0.62, -0.18, 0.71, 0.27]))  # normalised inside
TRUE_TRANSLATION = np.array([0.42, -0.11, -0.35])


def scene(count: int = 10, noise: float = 0.001, seed: int = 5):
    """Camera-frame points 0.35-0.6 m in front of the camera and their tracker positions
    with ``noise`` (m, per axis)."""
    rng = np.random.default_rng(seed)
    camera = np.stack([rng.uniform(-0.12, 0.12, count), rng.uniform(-0.09, 0.09, count),
                       rng.uniform(0.35, 0.6, count)], axis=1)
    tracker = camera @ TRUE_ROTATION.T + TRUE_TRANSLATION + rng.normal(0, noise, (count, 3))
    return camera, tracker


def rotation_error_deg(rotation) -> float:
    cos = (np.trace(rotation @ TRUE_ROTATION.T) - 1) / 2
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def test_rigid_fit_recovers_the_transform_from_noisy_points():
    noise = 0.001
    camera, tracker = scene(12, noise)
    fit = fit_rigid(camera, tracker)
    assert np.linalg.det(fit.rotation) == pytest.approx(1.0)
    assert rotation_error_deg(fit.rotation) < 0.5
    assert np.linalg.norm(fit.translation - TRUE_TRANSLATION) < 0.003
    # 3D noise of 1 mm per axis is 1.73 mm; the fit absorbs 6 of the 36 degrees of freedom.
    expected = noise * math.sqrt(3 * (1 - 6 / 36))
    assert 0.6 * expected < fit.rms < 1.4 * expected
    exact = fit_rigid(*scene(4, 0.0))
    assert np.allclose(exact.rotation, TRUE_ROTATION, atol=1e-12) and exact.rms < 1e-9
    assert np.allclose(exact.apply(camera), camera @ TRUE_ROTATION.T + TRUE_TRANSLATION)


def test_rigid_fit_refuses_what_does_not_fix_a_pose():
    camera, tracker = scene(6, 0.0)
    with pytest.raises(RigidFitError, match='2 point pairs given: a pose needs at least 3'):
        fit_rigid(camera[:2], tracker[:2])
    line = np.outer(np.linspace(0, 0.2, 5), [0.3, 0.5, 0.8]) + [0.0, 0.0, 0.4]
    line[2] += [0.0005, 0, 0]  # half a millimetre off the line: still a line
    with pytest.raises(RigidFitError, match=r'5 camera points are \(nearly\) on one line'):
        fit_rigid(line, line @ TRUE_ROTATION.T + TRUE_TRANSLATION)
    with pytest.raises(RigidFitError, match='unit mix-up'):
        fit_rigid(camera, tracker * 100)  # centimetres typed as metres
    # A mirror image fits no proper rotation: still det +1, with large residuals.
    mirrored = fit_rigid(camera, tracker * [1, 1, -1])
    assert np.linalg.det(mirrored.rotation) == pytest.approx(1.0) and mirrored.rms > 0.01


# The left camera's rectification turns it by 3 degrees: triangulated points must be turned
# back into stereo_left_optical, or the fitted pose would be off by that much.
R_RECTIFY_LEFT = cv2.Rodrigues(np.radians([1.0, -2.5, 1.2]))[0]


def rectified_pair(tmp_path):
    f, cx_left, cx_right, cy, baseline = 610.0, 320.5, 312.0, 241.0, 0.07
    k = [f, 0, 320, 0, f, 240, 0, 0, 1]
    left = CameraModel.from_fields(640, 480, k, [0.0] * 5, R_RECTIFY_LEFT.ravel(),
                                   [f, 0, cx_left, 0, 0, f, cy, 0, 0, 0, 1, 0], name='s/left')
    right = CameraModel.from_fields(640, 480, k, [0.0] * 5, np.eye(3).ravel(),
                                    [f, 0, cx_right, -f * baseline, 0, f, cy, 0, 0, 0, 1, 0],
                                    name='s/right')
    paths = (write_camera_info_yaml(tmp_path / 'left.yaml', left),
             write_camera_info_yaml(tmp_path / 'right.yaml', right))
    return left, right, paths


def pixels_of(points, left, right):
    """Rectified pixels of left-camera points (the rectified frame is ``R_left p``)."""
    x, y, z = (points @ left.R.T).T
    return np.stack([left.P[0, 0] * x / z + left.P[0, 2], left.P[1, 1] * y / z + left.P[1, 2],
                     (right.P[0, 0] * x + right.P[0, 3]) / z + right.P[0, 2]], axis=1)


def pose_from_file(path):
    document = yaml.safe_load(path.read_text())
    pose = document['/**/stereo_node']['ros__parameters']['camera_pose']
    assert len(pose) == 7 and all(isinstance(v, float) for v in pose)
    return quaternion_to_matrix(np.array(pose[3:])), np.array(pose[:3])


def test_calibrate_camera_tracker_command_from_camera_points(tmp_path):
    camera, tracker = scene(8, 0.0005)
    lines = ['# touched corners of the calibration block', 'name,x,y,z,x_cam,y_cam,z_cam']
    lines += [f'p{i},' + ','.join(f'{v:.6f}' for v in (*t, *c))
              for i, (t, c) in enumerate(zip(tracker, camera))]
    (tmp_path / 'points.csv').write_text('\n'.join(lines) + '\n')
    output = tmp_path / 'config' / 'camera_pose.yaml'
    result = run('calibrate_camera_tracker', tmp_path / 'points.csv', '--output', output)
    assert result.returncode == 0, result.stderr
    assert 'p7' in result.stdout and 'RMS' in result.stdout and 'max' in result.stdout
    rotation, translation = pose_from_file(output)
    assert rotation_error_deg(rotation) < 0.5
    assert np.abs(camera @ rotation.T + translation - tracker).max() < 0.003


def test_the_stereo_node_reads_the_parameter_file_in_any_namespace(tmp_path):
    """rcl's own parser: the wildcard key matches a namespaced stereo_node, and the pose is
    a double array."""
    import rclpy
    from rclpy.node import Node

    camera, tracker = scene(5, 0.0)
    fit = fit_rigid(camera, tracker)
    path = write_camera_pose_yaml(tmp_path / 'camera_pose.yaml', fit, ['a test'])
    context = rclpy.Context()
    rclpy.init(args=['--ros-args', '--params-file', str(path)], context=context)
    try:
        node = Node('stereo_node', namespace='rig', context=context,
                    automatically_declare_parameters_from_overrides=True)
        try:
            value = list(node.get_parameter('camera_pose').value)
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    assert value == fit.pose


def test_calibrate_camera_tracker_triangulates_pixels(tmp_path):
    left, right, (left_path, right_path) = rectified_pair(tmp_path)
    camera, tracker = scene(7, 0.0)
    pixels = pixels_of(camera, left, right)
    entries = []
    for i, (t, c, p) in enumerate(zip(tracker, camera, pixels)):
        entry = {'name': f'corner{i}', 'x': float(t[0]), 'y': float(t[1]), 'z': float(t[2])}
        if i % 2:  # half as pixels, half as camera points
            entry.update(u_left=round(float(p[0]), 3), v_left=round(float(p[1]), 3),
                         u_right=round(float(p[2]), 3))
        else:
            entry.update(x_cam=float(c[0]), y_cam=float(c[1]), z_cam=float(c[2]))
        entries.append(entry)
    points = tmp_path / 'points.yaml'
    points.write_text(yaml.safe_dump({'points': entries}))
    # The library: pixels come back as the camera points they were made from.
    correspondences = read_correspondences(points)
    assert np.allclose(camera_points(correspondences, left, right), camera, atol=2e-4)
    with pytest.raises(CorrespondenceError, match='pass --left and --right'):
        camera_points(correspondences)
    output = tmp_path / 'pose.yaml'
    result = run('calibrate_camera_tracker', points, '--left', left_path, '--right', right_path,
                 '--output', output)
    assert result.returncode == 0, result.stderr
    rotation, translation = pose_from_file(output)
    assert rotation_error_deg(rotation) < 0.1
    assert np.linalg.norm(translation - TRUE_TRANSLATION) < 0.001
    # Left and right swapped: the disparity is negative, the pair check says so.
    swapped = run('calibrate_camera_tracker', points, '--left', right_path, '--right',
                  left_path, '--output', output)
    assert_refused(swapped, 'not the rectified pair')


def test_calibrate_camera_tracker_refuses_bad_input(tmp_path):
    good = 'name,x,y,z,x_cam,y_cam,z_cam\n' + '\n'.join(
        f'p{i},' + ','.join(f'{v:.6f}' for v in (*t, *c))
        for i, (c, t) in enumerate(zip(*scene(5, 0.0))))
    out = tmp_path / 'pose.yaml'
    (tmp_path / 'missing_column.csv').write_text(good.replace(',z_cam\n', '\n', 1))
    assert_refused(run('calibrate_camera_tracker', tmp_path / 'missing_column.csv',
                       '--output', out), 'missing column z_cam')
    (tmp_path / 'two.csv').write_text('\n'.join(good.splitlines()[:3]))
    assert_refused(run('calibrate_camera_tracker', tmp_path / 'two.csv', '--output', out),
                   '2 point pairs given')
    (tmp_path / 'blank.csv').write_text(good.replace('p2,', 'p2,,', 1))
    assert_refused(run('calibrate_camera_tracker', tmp_path / 'blank.csv', '--output', out),
                   'line 4')
    (tmp_path / 'pixels.csv').write_text('x,y,z,u_left,v_left,u_right\n0.1,0.2,0.3,300,200,250\n')
    assert_refused(run('calibrate_camera_tracker', tmp_path / 'pixels.csv', '--output', out),
                   'pass --left and --right')
    (tmp_path / 'bad.yaml').write_text('image_width: [640\n')
    assert_refused(run('calibrate_camera_tracker', tmp_path / 'two.csv', '--left',
                       tmp_path / 'bad.yaml', '--right', tmp_path / 'bad.yaml', '--output', out),
                   'bad.yaml: not valid YAML')
    assert_refused(run('calibrate_camera_tracker', tmp_path / 'absent.csv', '--output', out),
                   'absent.csv: no such file')
    assert not out.exists()
