"""Stereo geometry: rectification (inhand_stereo.rectification) and 3D points
(inhand_stereo.reprojection), against a rig whose every parameter is known."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from inhand_common.rotations import euler_zyx_to_quaternion, quaternion_to_matrix
from inhand_stereo.camera_model import CameraModel, CameraModelError
from inhand_stereo.rectification import StereoRectifier, rectifier_for
from inhand_stereo.reprojection import (
    camera_points_to_map,
    camera_to_map_transform,
    depth_map,
    map_points_to_camera,
    points_from_disparity,
    transform_points,
)

WIDTH, HEIGHT = 640, 480


# -- a distorted rig -------------------------------------------------------------------------

def distorted_rig() -> tuple[CameraModel, CameraModel, np.ndarray, np.ndarray]:
    """Two plumb_bob cameras 7 cm apart, slightly rotated against each other, calibrated
    the way camera_calibration does it (cv2.stereoRectify, zero disparity at infinity).
    Returns the two CameraInfos and the right camera's pose (p_right = R p_left + T)."""
    k1 = np.array([[520.0, 0.0, 322.0], [0.0, 518.0, 236.0], [0.0, 0.0, 1.0]])
    k2 = np.array([[515.0, 0.0, 316.0], [0.0, 516.0, 244.0], [0.0, 0.0, 1.0]])
    d1 = np.array([-0.28, 0.09, 0.0012, -0.0008, 0.0])
    d2 = np.array([-0.25, 0.07, -0.0006, 0.0010, 0.0])
    rotation = cv2.Rodrigues(np.array([0.012, -0.025, 0.008]))[0]
    translation = np.array([-0.07, 0.0012, 0.0009])
    r1, r2, p1, p2, _, _, _ = cv2.stereoRectify(k1, d1, k2, d2, (WIDTH, HEIGHT), rotation,
                                                translation.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY,
                                                alpha=0.0)
    left = CameraModel.from_fields(WIDTH, HEIGHT, k1.ravel(), d1, r1.ravel(), p1.ravel(),
                                   name='left')
    right = CameraModel.from_fields(WIDTH, HEIGHT, k2.ravel(), d2, r2.ravel(), p2.ravel(),
                                    name='right')
    return left, right, rotation, translation


# Gaussian spots on a plane 0.6 m in front of the left camera (its raw frame).
PLANE_Z = 0.6
SPOT_SIGMA = 0.004      # m: about 3.5 px at this distance
SPOTS = np.array([[x, y, PLANE_Z] for x in np.linspace(-0.24, 0.24, 5)
                  for y in np.linspace(-0.17, 0.17, 4)])


def render_raw(camera: CameraModel, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """What ``camera`` (at p_cam = rotation p_left + translation) sees of the spots: each
    raw pixel undistorted to its ray (iteratively, to 1e-10), the ray met with the plane."""
    u, v = np.meshgrid(np.arange(WIDTH, dtype=np.float64), np.arange(HEIGHT, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], -1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-10)
    normalised = cv2.undistortPoints(pixels, camera.K, camera.D,
                                     criteria=criteria).reshape(-1, 2)
    rays = rotation.T @ np.column_stack([normalised, np.ones(len(normalised))]).T
    centre = -rotation.T @ translation
    t = (PLANE_Z - centre[2]) / rays[2]
    hit = centre[:, None] + rays * t                                # (3, N) in the left frame
    intensity = np.zeros(hit.shape[1])
    for spot in SPOTS:
        intensity += np.exp(-((hit[0] - spot[0]) ** 2 + (hit[1] - spot[1]) ** 2)
                            / (2 * SPOT_SIGMA ** 2))
    return np.clip(20 + 220 * intensity, 0, 255).reshape(HEIGHT, WIDTH)


def centroid(image: np.ndarray, near: np.ndarray, radius: int = 12) -> np.ndarray:
    """Intensity-weighted centre of the spot near ``near`` (background subtracted)."""
    x0, y0 = np.round(near).astype(int)
    patch = image[y0 - radius:y0 + radius + 1, x0 - radius:x0 + radius + 1].astype(np.float64)
    weight = np.clip(patch - 20.0, 0.0, None)
    ys, xs = np.mgrid[y0 - radius:y0 + radius + 1, x0 - radius:x0 + radius + 1]
    return np.array([np.sum(weight * xs), np.sum(weight * ys)]) / np.sum(weight)


def project(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    homogeneous = matrix @ np.column_stack([points, np.ones(len(points))]).T
    return (homogeneous[:2] / homogeneous[2]).T


def project_raw(camera: CameraModel, points: np.ndarray) -> np.ndarray:
    """Where the raw (distorted) image of ``camera`` at the left camera's pose shows points."""
    pixels, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera.K, camera.D)
    return pixels.reshape(-1, 2)


@pytest.fixture(scope='module')
def rig():
    left, right, rotation, translation = distorted_rig()
    raw_left = render_raw(left, np.eye(3), np.zeros(3))
    raw_right = render_raw(right, rotation, translation)
    return left, right, raw_left, raw_right, rotation, translation


# Tolerance for a spot's centre after rectification. The rendering samples each spot at the
# pixel centres exactly, so the raw centroids are exact to ~1e-3 px; the error budget is
# bilinear interpolation with OpenCV's 1/32 px map tables (<= 1/64 px bias per coordinate),
# 8-bit rounding, and the distortion bending a spot (3.5 px sigma) unevenly, which moves its
# centroid by a few hundredths of a pixel in the corners. 0.1 px is well above those and
# two orders of magnitude below what distortion does to these spots (checked below).
TOLERANCE_PX = 0.1


@pytest.mark.parametrize('colour', [False, True], ids=['mono8', 'rgb8'])
def test_rectified_spots_land_where_the_rectified_cameras_project_them(rig, colour):
    left, right, raw_left, raw_right, rotation, translation = rig
    rectifier = StereoRectifier(left, right)
    images = [np.rint(raw).astype(np.uint8) for raw in (raw_left, raw_right)]
    if colour:
        images = [np.repeat(image[:, :, None], 3, axis=2) for image in images]
    rect_left, rect_right = rectifier.rectify(*images)
    assert rect_left.shape == images[0].shape and rect_left.dtype == np.uint8
    if colour:
        rect_left, rect_right = rect_left[:, :, 1], rect_right[:, :, 1]
    in_rectified = SPOTS @ left.R.T                              # p_rect = R_left p_raw
    expected_left = project(left.P, in_rectified)
    expected_right = project(right.P, in_rectified)
    found_left = np.array([centroid(rect_left, p) for p in expected_left])
    found_right = np.array([centroid(rect_right, p) for p in expected_right])
    assert np.abs(found_left - expected_left).max() < TOLERANCE_PX
    assert np.abs(found_right - expected_right).max() < TOLERANCE_PX
    # Rectified: each spot on one row in both images.
    assert np.abs(found_left[:, 1] - found_right[:, 1]).max() < TOLERANCE_PX
    # The raw image has the spots where the distorted model puts them, far from there.
    raw_found_left = np.array([centroid(raw_left, p) for p in project_raw(left, SPOTS)])
    assert np.abs(raw_found_left - project_raw(left, SPOTS)).max() < TOLERANCE_PX
    assert np.abs(raw_found_left - expected_left).max() > 50 * TOLERANCE_PX


def test_straight_lines_come_out_straight(rig):
    """A row of spots on a straight 3D line is bent by the lens in the raw image and
    straight after rectification."""
    left, right, raw_left, _, _, _ = rig
    rect_left = StereoRectifier(left, right).rectify_left(np.rint(raw_left).astype(np.uint8))
    top_row = SPOTS[np.isclose(SPOTS[:, 1], SPOTS[:, 1].min())]
    expected = project(left.P, top_row @ left.R.T)
    found = np.array([centroid(rect_left, p) for p in expected])
    line = np.polyfit(found[:, 0], found[:, 1], 1)
    assert np.abs(np.polyval(line, found[:, 0]) - found[:, 1]).max() < TOLERANCE_PX
    raw = np.array([centroid(raw_left, p) for p in project_raw(left, top_row)])
    raw_line = np.polyfit(raw[:, 0], raw[:, 1], 1)
    assert np.abs(np.polyval(raw_line, raw[:, 0]) - raw[:, 1]).max() > 2.0


def test_rectified_geometry_of_the_rig(rig):
    left, right, _, _, _, translation = rig
    rectifier = StereoRectifier(left, right)
    assert rectifier.baseline == pytest.approx(np.linalg.norm(translation), rel=1e-9)
    assert rectifier.focal == left.P[0, 0]
    assert rectifier.cx_offset == 0.0            # CALIB_ZERO_DISPARITY
    np.testing.assert_array_equal(rectifier.R_left, left.R)
    np.testing.assert_array_equal(rectifier.P_left, left.P)
    assert not rectifier.passthrough


# -- pre-rectified input ----------------------------------------------------------------------

def rectified_pair(fx=500.0, fy=500.0, cx_left=320.0, cx_right=320.0, cy=240.0,
                   baseline=0.07) -> tuple[CameraModel, CameraModel]:
    """Cameras that deliver rectified images (identity R, zero D, P = [K | t])."""
    def camera(cx: float, tx: float, name: str) -> CameraModel:
        k = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]
        p = [fx, 0.0, cx, tx, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        return CameraModel.from_fields(WIDTH, HEIGHT, k, [0.0] * 5, np.eye(3).ravel(), p,
                                       name=name)
    return camera(cx_left, 0.0, 'left'), camera(cx_right, -fx * baseline, 'right')


def test_pre_rectified_input_passes_through_unchanged():
    left, right = rectified_pair()
    rectifier = StereoRectifier(left, right)
    assert rectifier.passthrough
    rng = np.random.default_rng(3)
    for shape in ((HEIGHT, WIDTH), (HEIGHT, WIDTH, 3)):
        image_left, image_right = rng.integers(0, 256, (2,) + shape, dtype=np.uint8)
        out_left, out_right = rectifier.rectify(image_left, image_right)
        assert out_left is image_left and out_right is image_right


def test_images_of_the_wrong_size_are_refused():
    rectifier = StereoRectifier(*distorted_rig()[:2])
    with pytest.raises(ValueError, match=r'left image: shape \(480, 600\)'):
        rectifier.rectify(np.zeros((480, 600), np.uint8), np.zeros((480, 640), np.uint8))
    with pytest.raises(ValueError, match='right image'):
        rectifier.rectify_right(np.zeros((480, 640, 4), np.uint8))


# -- Q ----------------------------------------------------------------------------------------

def test_q_is_image_geometrys():
    """Hand-computed from image_geometry's updateQ with Tx = P_r[0,3] / P_r[0,0] = -0.07:
    fx 500, fy 505, cx_l 320, cx_r 330, cy 240."""
    left, right = rectified_pair(fx=500.0, fy=505.0, cx_left=320.0, cx_right=330.0)
    q = StereoRectifier(left, right).Q
    expected = np.array([
        [-35.35, 0.0, 0.0, 11312.0],          # fy Tx, -fy cx Tx = 505*320*0.07
        [0.0, -35.0, 0.0, 8400.0],            # fx Tx, -fx cy Tx = 500*240*0.07
        [0.0, 0.0, 0.0, -17675.0],            # fx fy Tx = -500*505*0.07
        [0.0, 0.0, -505.0, -5050.0],          # -fy, fy (cx_l - cx_r) = 505*(-10)
    ])
    np.testing.assert_allclose(q, expected, rtol=1e-12)
    assert StereoRectifier(left, right).baseline == pytest.approx(0.07)


# -- reprojection -----------------------------------------------------------------------------

@pytest.mark.parametrize('cx_right', [320.0, 331.5], ids=['parallel', 'verged'])
def test_a_known_point_comes_back(cx_right):
    """A point projected into both rectified cameras -> its disparity -> the same point."""
    left, right = rectified_pair(fx=500.0, fy=505.0, cx_right=cx_right)
    rectifier = StereoRectifier(left, right)
    u, v, z = 401, 187, 0.43                                   # left pixel and depth
    point = np.array([(u - 320.0) * z / 500.0, (v - 240.0) * z / 505.0, z])
    x_left, y_left = project(left.P, point[None])[0]
    x_right, y_right = project(right.P, point[None])[0]
    assert (x_left, y_left) == pytest.approx((u, v)) and y_right == pytest.approx(v)
    raw_disparity = x_left - x_right                           # what OpenCV measures
    adjusted = raw_disparity - rectifier.cx_offset             # what DisparityImage holds
    disparity = np.full((HEIGHT, WIDTH), -1.0, np.float32)
    disparity[v, u] = adjusted
    points, colours = points_from_disparity(disparity, rectifier.Q, 0.0)
    assert colours is None and points.dtype == np.float32 and points.shape == (1, 3)
    np.testing.assert_allclose(points[0], point, rtol=2e-6)
    # The same point from the raw disparity with image_geometry's Q as it is.
    disparity[v, u] = raw_disparity
    again, _ = points_from_disparity(disparity, rectifier.Q, 0.0, pre_adjusted=False)
    np.testing.assert_allclose(again[0], point, rtol=2e-6)
    # And OpenCV agrees on the raw one.
    cv_point = cv2.reprojectImageTo3D(disparity, rectifier.Q)[v, u]
    np.testing.assert_allclose(cv_point, point, rtol=1e-5)
    depth = depth_map(np.where(disparity >= 0, np.float32(adjusted), disparity), rectifier.Q, 0.0)
    assert depth[v, u] == pytest.approx(z, rel=1e-6)
    assert np.isnan(depth[0, 0])


def test_points_go_back_to_the_raw_camera_frame(rig):
    """With R_left the points are in stereo_left_optical: p_raw = R_left^T p_rect."""
    left, right, _, _, _, _ = rig
    rectifier = StereoRectifier(left, right)
    u, v, z = 250, 300, 0.5                                    # rectified pixel, depth
    fx, fy, cx, cy = left.P[0, 0], left.P[1, 1], left.P[0, 2], left.P[1, 2]
    rectified = np.array([(u - cx) * z / fx, (v - cy) * z / fy, z])
    disparity = np.full((HEIGHT, WIDTH), -1.0, np.float32)
    disparity[v, u] = fx * rectifier.baseline / z             # cx_offset is 0 here
    points, _ = points_from_disparity(disparity, rectifier.Q, 0.0, R_left=rectifier.R_left)
    np.testing.assert_allclose(points[0], left.R.T @ rectified, atol=2e-6)
    assert not np.allclose(points[0], rectified, atol=1e-3)   # R_left is not the identity


def test_invalid_and_impossible_disparities_give_no_points():
    left, right = rectified_pair()
    q = StereoRectifier(left, right).Q
    disparity = np.full((4, 6), 10.0, np.float32)
    disparity[0, 0] = np.nan
    disparity[0, 1] = np.inf
    disparity[0, 2] = 0.0           # at infinity
    disparity[0, 3] = -3.0          # behind
    disparity[0, 4] = 4.0           # below the range
    points, _ = points_from_disparity(disparity, q, invalid_below=-5.0)
    assert len(points) == 24 - 4    # nan, inf, zero, negative dropped; 4.0 kept
    points, _ = points_from_disparity(disparity, q, invalid_below=5.0)
    assert len(points) == 24 - 5
    assert np.all(np.isfinite(points)) and np.all(points[:, 2] > 0)
    assert points[:, 2] == pytest.approx(500 * 0.07 / 10.0)


def test_colours_come_from_the_left_image_in_rgb_order():
    left, right = rectified_pair()
    q = StereoRectifier(left, right).Q
    disparity = np.full((HEIGHT, WIDTH), -1.0, np.float32)
    disparity[10, 20] = disparity[11, 21] = disparity[12, 22] = 30.0
    rgb = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    rgb[10, 20] = (200, 100, 50)
    rgb[12, 22] = (1, 2, 3)
    points, colours = points_from_disparity(disparity, q, 0.0, image=rgb)
    assert colours is not None and colours.dtype == np.uint8
    np.testing.assert_array_equal(colours, [[200, 100, 50], [0, 0, 0], [1, 2, 3]])
    _, from_bgr = points_from_disparity(disparity, q, 0.0, image=rgb[:, :, ::-1],
                                        encoding='bgr8')
    np.testing.assert_array_equal(from_bgr, colours)
    mono = rgb[:, :, 0].copy()
    _, grey = points_from_disparity(disparity, q, 0.0, image=mono)
    np.testing.assert_array_equal(grey, [[200] * 3, [0] * 3, [1] * 3])
    # step 2 keeps every other row and column: (10, 20) and (12, 22).
    stepped, stepped_colours = points_from_disparity(disparity, q, 0.0, image=rgb, step=2)
    np.testing.assert_array_equal(stepped_colours, [[200, 100, 50], [1, 2, 3]])
    np.testing.assert_allclose(stepped, points[[0, 2]])


def test_a_non_stereo_q_is_refused():
    with pytest.raises(ValueError, match='reprojection matrix'):
        points_from_disparity(np.zeros((4, 4), np.float32), np.eye(4), 0.0)


# -- frames -----------------------------------------------------------------------------------

def quaternion(azimuth, elevation, roll):
    return euler_zyx_to_quaternion(np.radians(azimuth), np.radians(elevation), np.radians(roll))


def test_transform_points_rotates_then_translates():
    points = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]], np.float32)
    moved = transform_points(points, [0.1, 0.2, 0.3], quaternion(90, 0, 0))
    assert moved.dtype == np.float32
    np.testing.assert_allclose(moved, [[0.1, 1.2, 0.3], [-1.9, 0.2, 0.3]], atol=1e-6)


def test_camera_points_reach_the_map_frame():
    camera_pose = np.concatenate([[0.3, -0.1, 0.2], quaternion(30, -20, 100)])
    object_pose = np.concatenate([[0.25, 0.05, 0.1], quaternion(-60, 10, 5)])
    rng = np.random.default_rng(5)
    points = rng.normal(0.0, 0.1, (50, 3)) + [0.0, 0.0, 0.4]
    in_tracker = points @ quaternion_to_matrix(camera_pose[3:]).T + camera_pose[:3]
    # Static mode: the map frame is the tracker frame.
    np.testing.assert_allclose(camera_points_to_map(points, camera_pose), in_tracker,
                               atol=1e-12)
    # Tracked mode: registration's p_obj = R_o^T (p - t_o).
    r_obj = quaternion_to_matrix(object_pose[3:])
    expected = (in_tracker - object_pose[:3]) @ r_obj
    in_map = camera_points_to_map(points, camera_pose, object_pose)
    np.testing.assert_allclose(in_map, expected, atol=1e-12)
    np.testing.assert_allclose(map_points_to_camera(in_map, camera_pose, object_pose), points,
                               atol=1e-12)
    rotation, offset = camera_to_map_transform(camera_pose, object_pose)
    np.testing.assert_allclose(points @ rotation.T + offset, expected, atol=1e-12)
    with pytest.raises(ValueError, match='camera_pose must be 7 finite numbers'):
        camera_points_to_map(points, camera_pose[:6])


# -- refusals ---------------------------------------------------------------------------------

def with_p(model: CameraModel, **entries: float) -> CameraModel:
    """A copy of ``model`` with P entries replaced (p03=..., p11=...), unchecked."""
    p = model.P.copy()
    for key, value in entries.items():
        p[int(key[1]), int(key[2])] = value
    return CameraModel(model.width, model.height, model.K, model.D, model.R, p,
                       model.distortion_model, model.name)


def test_pairs_that_cannot_be_rectified_are_refused():
    left, right = rectified_pair()
    smaller = CameraModel(320, 240, right.K, right.D, right.R, right.P, name='right')
    cases = [
        ((left, smaller), 'left image is 640x480, right is 320x240'),
        ((left, with_p(right, p03=0.0)), 'right P without a baseline'),
        ((left, with_p(right, p03=35.0)), 'left and right swapped'),
        ((with_p(left, p03=-35.0), right), 'left P[0, 3] = -35, expected 0'),
        ((left, with_p(right, p13=5.0)), 'only a horizontal baseline'),
        ((left, with_p(right, p00=510.0)), 'rectified focal lengths differ'),
        ((left, with_p(right, p12=241.0)), "rectified cy' differs"),
        ((left, with_p(right, p00=0.0)), 'zero or negative focal length'),
        ((with_p(left, p11=0.0), right), 'zero or negative focal length'),
    ]
    for (first, second), message in cases:
        with pytest.raises(CameraModelError, match=message.replace('[', r'\[')
                           .replace(']', r'\]')):
            StereoRectifier(first, second)
        with pytest.raises(ValueError):
            rectifier_for(first, second)


def test_unsupported_distortion_length_is_refused():
    left, right = rectified_pair()
    odd = CameraModel(WIDTH, HEIGHT, left.K, np.array([0.1, 0.0, 0.0]), left.R, left.P)
    with pytest.raises(CameraModelError, match='D has 3 coefficients'):
        StereoRectifier(odd, right)


def test_one_rectifier_per_calibration():
    left, right, _, _ = distorted_rig()
    first = rectifier_for(left, right)
    again = CameraModel.from_fields(WIDTH, HEIGHT, left.K.ravel(), left.D, left.R.ravel(),
                                    left.P.ravel(), name='left')
    assert rectifier_for(again, right) is first
    changed = CameraModel.from_fields(WIDTH, HEIGHT, (left.K * [[1.001], [1], [1]]).ravel(),
                                      left.D, left.R.ravel(), left.P.ravel(), name='left')
    assert rectifier_for(changed, right) is not first
