"""StereoPipeline.process (inhand_stereo.stereo_pipeline) against the plain steps it stands for.

The node's per-frame path is optimised (one remap per image, the left one kept as RGBA; the
depth and the points from one pass: ``StereoRectifier.rectify_frame``,
``reprojection.depth_and_points``); these tests pin it to the obvious composition of the
public steps, value for value: rectify both images, match their grey, the left image's
RGB, ``depth_map`` and ``points_from_disparity`` with its colours. Synthetic scenes of
``test_stereo_disparity`` at 320x240, seen by a distorted, slightly rotated rig (raw images
that rectify to the scene) and by cameras that deliver rectified, verged images.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from inhand_stereo.camera_model import CameraModel
from inhand_stereo.disparity import DisparityConfig
from inhand_stereo.image_encoding import to_grey, to_rgb
from inhand_stereo.rectification import StereoRectifier, rectifier_for
from inhand_stereo.reprojection import depth_and_points, depth_map, points_from_disparity
from inhand_stereo.stereo_pipeline import StereoPipeline, StereoShot
from test_stereo_disparity import render_scene

WIDTH, HEIGHT = 320, 240


def small_distorted_rig() -> tuple[CameraModel, CameraModel]:
    """Two plumb_bob cameras 7 cm apart, slightly rotated against each other, at 320x240,
    rectified as camera_calibration does (test_stereo_geometry's rig at half the size)."""
    k1 = np.array([[300.0, 0.0, 161.0], [0.0, 299.0, 118.0], [0.0, 0.0, 1.0]])
    k2 = np.array([[297.0, 0.0, 158.0], [0.0, 298.0, 122.0], [0.0, 0.0, 1.0]])
    d1 = np.array([-0.28, 0.09, 0.0012, -0.0008, 0.0])
    d2 = np.array([-0.25, 0.07, -0.0006, 0.0010, 0.0])
    rotation = cv2.Rodrigues(np.array([0.012, -0.025, 0.008]))[0]
    translation = np.array([-0.07, 0.0012, 0.0009]).reshape(3, 1)
    r1, r2, p1, p2, _, _, _ = cv2.stereoRectify(k1, d1, k2, d2, (WIDTH, HEIGHT), rotation,
                                                translation, flags=cv2.CALIB_ZERO_DISPARITY,
                                                alpha=0.0)
    return (CameraModel.from_fields(WIDTH, HEIGHT, k1.ravel(), d1, r1.ravel(), p1.ravel(),
                                    name='left'),
            CameraModel.from_fields(WIDTH, HEIGHT, k2.ravel(), d2, r2.ravel(), p2.ravel(),
                                    name='right'))


def rectified_verged_pair() -> tuple[CameraModel, CameraModel]:
    """Cameras that deliver rectified images, cx 3.5 px apart (a non-zero cx offset)."""
    def camera(cx: float, tx: float, name: str) -> CameraModel:
        k = [300.0, 0.0, cx, 0.0, 300.0, 119.5, 0.0, 0.0, 1.0]
        p = [300.0, 0.0, cx, tx, 0.0, 300.0, 119.5, 0.0, 0.0, 0.0, 1.0, 0.0]
        return CameraModel.from_fields(WIDTH, HEIGHT, k, [0.0] * 5, np.eye(3).ravel(), p,
                                       name=name)
    return camera(159.5, 0.0, 'left'), camera(156.0, -300.0 * 0.07, 'right')


def unrectified(image: np.ndarray, camera: CameraModel) -> np.ndarray:
    """The raw image whose rectification by ``camera`` is ``image``."""
    u, v = np.meshgrid(np.arange(WIDTH, dtype=np.float64), np.arange(HEIGHT, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], -1).reshape(-1, 1, 2)
    where = cv2.undistortPoints(pixels, camera.K, camera.D, R=camera.R, P=camera.P)
    maps = where.reshape(HEIGHT, WIDTH, 2).astype(np.float32)
    return cv2.remap(image, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR)


@pytest.fixture(scope='module', params=['distorted', 'pre-rectified'])
def rig(request):
    """(left camera, right camera, raw RGB left, raw RGB right)."""
    pair = render_scene('sphere')
    if request.param == 'pre-rectified':
        return (*rectified_verged_pair(), pair.left, pair.right)
    left, right = small_distorted_rig()
    return left, right, unrectified(pair.left, left), unrectified(pair.right, right)


def images_in(encoding: str, left: np.ndarray, right: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    if encoding == 'mono8':
        return (cv2.cvtColor(left, cv2.COLOR_RGB2GRAY), cv2.cvtColor(right, cv2.COLOR_RGB2GRAY))
    if encoding == 'bgr8':
        return np.ascontiguousarray(left[..., ::-1]), np.ascontiguousarray(right[..., ::-1])
    return left, right


def plain_steps(pipeline: StereoPipeline, left_image: np.ndarray, right_image: np.ndarray,
                encoding: str, left: CameraModel, right: CameraModel) -> dict[str, np.ndarray]:
    """What process() stands for, step by step with the public functions."""
    rectifier = StereoRectifier(left, right)
    left_rect, right_rect = rectifier.rectify(left_image, right_image)
    result = pipeline.matcher.compute(left_rect, right_rect, cx_offset=rectifier.cx_offset,
                                      encoding=encoding)
    left_rgb = np.ascontiguousarray(to_rgb(left_rect, encoding))
    depth = depth_map(result.disparity, rectifier.Q, result.min_disparity)
    points, colours = points_from_disparity(result.disparity, rectifier.Q, result.min_disparity,
                                            image=left_rgb, R_left=rectifier.R_left,
                                            step=pipeline.point_step, encoding='rgb8')
    return {'disparity': result.disparity, 'depth': depth, 'left_rgb': left_rgb,
            'points': points, 'colours': np.asarray(colours)}


@pytest.mark.parametrize('step', [1, 2])
@pytest.mark.parametrize('encoding', ['mono8', 'rgb8', 'bgr8'])
def test_process_gives_what_the_plain_steps_give(rig, encoding, step):
    left, right, raw_left, raw_right = rig
    left_image, right_image = images_in(encoding, raw_left, raw_right)
    pipeline = StereoPipeline({'min_disparity': 16, 'disparity_range': 64}, point_step=step)
    shot = pipeline.process(7, left_image, right_image, encoding, left, right)
    expected = plain_steps(pipeline, left_image, right_image, encoding, left, right)
    assert isinstance(shot, StereoShot) and shot.stamp_ns == 7
    np.testing.assert_array_equal(shot.disparity.disparity, expected['disparity'])
    np.testing.assert_array_equal(shot.depth, expected['depth'])        # NaN where NaN
    assert shot.depth.dtype == np.float32
    np.testing.assert_array_equal(shot.left_rgb, expected['left_rgb'])
    assert shot.left_rgb.flags.c_contiguous and shot.left_rgb.shape == (HEIGHT, WIDTH, 3)
    np.testing.assert_array_equal(shot.points, expected['points'])
    np.testing.assert_array_equal(shot.colours, expected['colours'])
    assert shot.points.dtype == np.float32 and shot.colours.dtype == np.uint8
    # The scene was found: most of the sphere and backdrop, some pixels without a depth.
    assert len(shot.points) > 0.4 * (HEIGHT // step) * (WIDTH // step)
    assert np.isnan(shot.depth).any()


def test_the_shot_is_not_changed_by_the_next_frame(rig):
    left, right, raw_left, raw_right = rig
    pipeline = StereoPipeline({'min_disparity': 16, 'disparity_range': 64})
    first = pipeline.process(1, raw_left, raw_right, 'rgb8', left, right)
    kept = {name: np.array(getattr(first, name))
            for name in ('depth', 'left_rgb', 'points', 'colours')}
    pipeline.process(2, raw_right, raw_left, 'rgb8', left, right)
    for name, values in kept.items():
        np.testing.assert_array_equal(getattr(first, name), values)


@pytest.mark.parametrize('encoding', ['mono8', 'rgb8', 'bgr8'])
def test_rectify_frame_is_rectify_then_grey(rig, encoding):
    left, right, raw_left, raw_right = rig
    left_image, right_image = images_in(encoding, raw_left, raw_right)
    rectifier = rectifier_for(left, right)
    frame = rectifier.rectify_frame(left_image, right_image, encoding)
    left_rect, right_rect = rectifier.rectify(left_image, right_image)
    np.testing.assert_array_equal(frame.left_grey, to_grey(left_rect, encoding))
    np.testing.assert_array_equal(frame.right_grey, to_grey(right_rect, encoding))
    rgb = to_rgb(left_rect, encoding)
    np.testing.assert_array_equal(frame.left_rgb, rgb)
    np.testing.assert_array_equal(frame.left_rgba[..., :3], rgb)
    with pytest.raises(ValueError, match='one is mono, the other colour'):
        rectifier.rectify_frame(left_image[..., 0] if encoding != 'mono8' else left_image,
                                np.dstack([right_image] * 3) if encoding == 'mono8'
                                else right_image, encoding)


def awkward_disparity() -> np.ndarray:
    """A disparity with every kind of pixel: valid, invalid, NaN, inf, zero, negative."""
    rng = np.random.default_rng(4)
    disparity = rng.uniform(10.0, 60.0, (HEIGHT, WIDTH)).astype(np.float32)
    disparity[rng.random((HEIGHT, WIDTH)) < 0.3] = 15.0           # invalid (below 16)
    disparity[0, :8] = [np.nan, np.inf, -np.inf, 0.0, -0.0, -3.0, 16.0, 1e-30]
    return disparity


@pytest.mark.parametrize('step', [1, 2, 3])
@pytest.mark.parametrize('kind', ['none', 'mono8', 'rgb8', 'bgr8', 'rgba8'])
def test_depth_and_points_is_depth_map_and_points_from_disparity(kind, step):
    left, right = small_distorted_rig()
    rectifier = StereoRectifier(left, right)
    disparity = awkward_disparity()
    rgb = render_scene('sphere').left
    images = {'none': (None, 'rgb8', None), 'mono8': (rgb[..., 1], 'rgb8', rgb[..., 1]),
              'rgb8': (rgb, 'rgb8', rgb), 'bgr8': (rgb[..., ::-1], 'bgr8', rgb),
              'rgba8': (cv2.cvtColor(rgb, cv2.COLOR_RGB2RGBA), 'rgba8', rgb)}
    image, encoding, as_rgb = images[kind]
    both = depth_and_points(disparity, rectifier.Q, 16.0, image=image, R_left=rectifier.R_left,
                            step=step, encoding=encoding)
    np.testing.assert_array_equal(both.depth, depth_map(disparity, rectifier.Q, 16.0))
    points, colours = points_from_disparity(disparity, rectifier.Q, 16.0, image=as_rgb,
                                            R_left=rectifier.R_left, step=step)
    np.testing.assert_array_equal(both.points, points)
    if image is None:
        assert both.colours is None and colours is None
    else:
        np.testing.assert_array_equal(both.colours, colours)
    # The depth is the points' z in the rectified camera, where there are points.
    sampled = both.depth[::step, ::step]
    finite = np.isfinite(sampled)
    assert finite.sum() == len(points)
    np.testing.assert_allclose((points @ rectifier.R_left.T)[:, 2], sampled[finite], rtol=1e-5)
    assert np.isnan(both.depth[0, :6]).all() and np.isfinite(both.depth[0, 6])


def test_a_colour_image_must_say_its_layout():
    left, right = rectified_verged_pair()
    q = StereoRectifier(left, right).Q
    disparity = np.full((HEIGHT, WIDTH), 30.0, np.float32)
    rgba = np.zeros((HEIGHT, WIDTH, 4), np.uint8)
    with pytest.raises(ValueError, match="'rgba8'"):
        depth_and_points(disparity, q, 16.0, image=rgba, encoding='rgb8')
    with pytest.raises(ValueError, match="'rgba8'"):
        points_from_disparity(disparity, q, 16.0, image=rgba[..., :3], encoding='rgba8')


def test_typed_configuration_is_taken_too():
    config = DisparityConfig.from_parameters({'min_disparity': 16, 'disparity_range': 64})
    assert StereoPipeline(config).matcher.config is config
