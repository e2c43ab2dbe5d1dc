"""The virtual stereo rig (inhand_sim.stereo_rig) and the object textures (inhand_sim.textures).

Most renders are 320 x 240 crops of the default 600 px camera (the textures at their real
scale, a quarter of the pixels); one test times full 640 x 480 pairs and prints the times.
"""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from inhand_common.rotations import quaternion_to_matrix
from inhand_sim.objects import OBJECT_NAMES, get_object
from inhand_sim.session import SessionSettings, _static_pose
from inhand_sim.stereo_rig import (
    BACKDROP,
    DEFAULT_DISTANCE,
    DEFAULT_TARGET,
    OBJECT,
    TABLE,
    StereoRig,
    compiled_sdf,
    distort_normalized,
    render_pair,
    static_object_pose,
    undistort_normalized,
)
from inhand_sim.textures import (
    backdrop_colour,
    surface_appearance,
    surface_colour,
    table_colour,
    value_noise,
)

DISTORTION = (-0.32, 0.14, 0.0012, -0.0009, -0.02)


def crop_rig(**fields) -> StereoRig:
    """The default viewpoint through a 320 x 240 window of the 600 px camera."""
    return StereoRig(width=320, height=240, focal=600.0, cx=161.3, cy=118.6, **fields)


def render(name: str, seed: int = 0, rig: StereoRig | None = None, **options):
    obj = get_object(name)
    return render_pair(rig or crop_rig(), obj, static_object_pose(obj), np.random.default_rng(seed),
                       table=True, **options)


@pytest.fixture(scope='module')
def shots():
    return {name: render(name) for name in OBJECT_NAMES}


def luminance(image: np.ndarray) -> np.ndarray:
    return image.astype(float) @ np.array([0.299, 0.587, 0.114])


# --- geometry ------------------------------------------------------------------------------

def test_compiled_sdf_is_the_object_models_sdf():
    rng = np.random.default_rng(3)
    for name in OBJECT_NAMES:
        obj = get_object(name)
        lo, hi = obj.bounds[0] - 0.02, obj.bounds[1] + 0.02
        points = rng.uniform(lo, hi, (20_000, 3))
        surface, _ = obj.sample_surface(2_000, rng)
        points = np.concatenate([points, surface])
        assert np.max(np.abs(compiled_sdf(obj, points) - obj.sdf(points))) < 1e-12, name


def test_every_object_pixel_sees_the_exact_surface(shots):
    for name, shot in shots.items():
        obj = get_object(name)
        assert shot.mask.sum() > 3000, name
        on_object = shot.points('object')[shot.mask]
        assert np.max(np.abs(obj.sdf(on_object))) < 5e-4, name
        assert np.max(np.abs(obj.sdf(on_object))) < 2e-5, name   # in fact, sphere tracing's 1e-5
        assert shot.max_sdf_residual < 2e-5
        # What is not the object is outside it, on the table or on the backdrop plane.
        elsewhere = shot.points('object')[~shot.mask]
        assert np.min(obj.sdf(elsewhere)) > -1e-6, name
        assert set(np.unique(shot.surface)) == {BACKDROP, TABLE, OBJECT}
        table = shot.points('object')[shot.surface == TABLE]
        assert np.max(np.abs(table[:, 2] - obj.table_z)) < 1e-9


def test_disparity_is_f_b_over_z_and_the_right_camera_sees_the_point_there(shots):
    shot = shots['cat']
    f, baseline = shot.focal, shot.baseline
    assert np.allclose(shot.disparity, f * baseline / shot.depth, rtol=1e-12)
    # The true 3D point of each object pixel, projected by the right CameraInfo's P, lands
    # on the same row, ``disparity`` to the left.
    v, u = np.nonzero(shot.mask)
    camera_points = shot.points('camera')[v, u]
    projected = np.c_[camera_points, np.ones(len(u))] @ shot.right_camera.P.T
    u_right, v_right = projected[:, 0] / projected[:, 2], projected[:, 1] / projected[:, 2]
    assert np.allclose(u - u_right, shot.disparity[v, u], atol=1e-9)
    assert np.allclose(v_right, v, atol=1e-9)


def test_a_known_surface_point_projects_into_both_cameras_by_its_disparity(shots):
    rig = crop_rig()
    obj = get_object('mug')
    shot = shots['mug']
    position, q = static_object_pose(obj)
    rotation = quaternion_to_matrix(q)
    samples, _ = obj.sample_surface(4000, np.random.default_rng(5))
    tracker = samples @ rotation.T + position
    u_left, v, u_right, z = rig.project(tracker)
    # The right camera by hand: its centre baseline along the left camera's x, same axes.
    in_right = (tracker - (rig.position + rig.baseline * rig.rotation[:, 0])) @ rig.rotation
    assert np.allclose(u_right, rig.focal * in_right[:, 0] / in_right[:, 2] + rig.cx, atol=1e-9)
    assert np.allclose(u_left - u_right, rig.focal * rig.baseline / z, rtol=1e-12)
    # The samples the left camera sees (the truth at their nearest pixel is the object, at
    # their depth to a millimetre) have the truth's disparity there, to the change of
    # disparity across half a pixel (a millimetre of depth is 0.3 px of disparity here).
    col, row = np.rint(u_left).astype(int), np.rint(v).astype(int)
    inside = (col >= 0) & (col < rig.width) & (row >= 0) & (row < rig.height)
    col, row, z, u_left, u_right = col[inside], row[inside], z[inside], u_left[inside], u_right[inside]
    seen = shot.mask[row, col] & (np.abs(shot.depth[row, col] - z) < 0.001)
    assert seen.sum() > 500
    error = np.abs(shot.disparity[row[seen], col[seen]] - (u_left - u_right)[seen])
    assert np.median(error) < 0.05 and np.max(error) < 0.35
    # And the truth's 3D point at that pixel is within a pixel's footprint of the sample.
    truth_points = shot.points('tracker')[row[seen], col[seen]]
    assert np.max(np.linalg.norm(truth_points - tracker[inside][seen], axis=1)) < 0.0015


def test_the_right_image_is_the_left_image_shifted_by_the_true_disparity():
    """Matte shading (no highlights), no noise: the right image sampled at x - d(x) gives
    the left image on the object (except where the right camera cannot see those points)."""
    shot = render('cat', specular=0.0, noise_sigma=0.0)
    h, w = shot.depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)

    def warped(extra: float) -> np.ndarray:
        map_x = (u - shot.disparity - extra).astype(np.float32)
        return cv2.remap(shot.right, map_x, v, cv2.INTER_LINEAR).astype(float)

    inner = cv2.erode(shot.mask.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    error = np.abs(warped(0.0) - shot.left.astype(float)).max(axis=2)[inner]
    error_off = np.abs(warped(1.5) - shot.left.astype(float)).max(axis=2)[inner]
    print(f'cat: |left - warped right| median {np.median(error):.1f}, with 1.5 px more '
          f'{np.median(error_off):.1f}')
    assert np.median(error) < 4.0
    assert np.median(error_off) > 2.0 * np.median(error)


# --- colours -------------------------------------------------------------------------------

def test_rendered_object_pixels_carry_the_shaded_surface_colour(shots):
    for name, shot in shots.items():
        on_object = shot.points('object')[shot.mask]
        truth = surface_colour(name, on_object).astype(int)
        # The albedo the renderer used is the texture at the truth's point.
        assert np.mean(np.abs(truth - shot.albedo[shot.mask].astype(int)) <= 1) > 0.999, name
        # The rendered colour is that albedo, shaded: they correlate.
        inner = cv2.erode(shot.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        rendered, albedo = luminance(shot.left)[inner], luminance(shot.albedo)[inner]
        correlation = np.corrcoef(rendered, albedo)[0, 1]
        print(f'{name}: correlation of rendered and true luminance {correlation:.3f}')
        assert correlation > 0.65, name
    # Under flat white light with no camera effects and one ray per pixel, a pixel is exactly
    # the surface colour.
    flat = render('cat', ambient=1.0, diffuse=0.0, specular=0.0, blur_sigma=0.0, noise_sigma=0.0,
                  edge_samples=1)
    assert np.array_equal(flat.left[flat.mask], flat.albedo[flat.mask])


def test_bottle_label_is_bright_and_textured_and_the_glass_dark_and_plain(shots):
    shot = shots['bottle']
    gray = luminance(shot.left)
    mean = cv2.blur(gray, (7, 7))
    local_std = np.sqrt(np.maximum(cv2.blur(gray * gray, (7, 7)) - mean * mean, 0.0))
    inner = cv2.erode(shot.mask.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    # Where the label is (textures.py: 4.5-14 cm above the bottom, facing +y), from the truth.
    points = shot.points('object')
    height = points[..., 2] + 0.14
    facing = np.arctan2(points[..., 1], points[..., 0] + 0.0375)
    label = inner & (height > 0.05) & (height < 0.135) & (np.abs(facing - np.pi / 2) < 1.1)
    glass = inner & (height > 0.16) & (height < 0.23)
    assert label.sum() > 500 and glass.sum() > 500
    print(f'bottle: label mean {gray[label].mean():.0f} local std {np.median(local_std[label]):.1f}; '
          f'glass mean {gray[glass].mean():.0f} local std {np.median(local_std[glass]):.1f}')
    assert gray[label].mean() > gray[glass].mean() + 80
    assert np.median(local_std[label]) > 3.0 * np.median(local_std[glass])


def test_textures_are_pure_functions_with_texture_and_plain_parts():
    rng = np.random.default_rng(11)
    for name in OBJECT_NAMES:
        obj = get_object(name)
        points, normals = obj.sample_surface(20_000, rng)
        colour = surface_colour(name, points, normals)
        assert colour.dtype == np.uint8 and colour.shape == (20_000, 3)
        assert np.array_equal(colour, surface_colour(name, points.copy()))
        assert np.array_equal(colour[::7], surface_colour(name, points[::7]))   # per point
        _, gloss = surface_appearance(name, points)
        assert np.all((gloss >= 0.0) & (gloss <= 1.0))
        assert len(np.unique(colour, axis=0)) > 300, name                     # textured
    # The bottle's glass is nearly uniform, its label is not.
    bottle = get_object('bottle')
    points, _ = bottle.sample_surface(40_000, rng)
    height = points[:, 2] + 0.14
    colour = surface_colour('bottle', points).astype(float)
    glass = (height > 0.17) & (height < 0.22)
    label = (height > 0.06) & (height < 0.13) & (points[:, 1] > 0.03)
    assert colour[glass].std(axis=0).max() < 3.0
    assert colour[label].std(axis=0).min() > 30.0
    for paint in (backdrop_colour, table_colour):
        plane = np.c_[rng.uniform(0, 0.3, 5000), rng.uniform(-0.2, 0.2, 5000), np.full(5000, 0.1)]
        assert paint(plane).dtype == np.uint8 and paint(plane).std(axis=0).min() > 10.0
    with pytest.raises(ValueError, match='no texture'):
        surface_colour('teapot', points)
    noise = value_noise(points, 0.01, seed=2)
    assert 0.0 <= noise.min() and noise.max() <= 1.0


# --- determinism, distortion, the rig --------------------------------------------------------

def test_same_inputs_and_seed_give_the_same_bytes():
    rig = StereoRig(width=160, height=120, focal=300.0, cx=80.5, cy=59.5)
    a = render('mug', seed=4, rig=rig)
    b = render('mug', seed=4, rig=rig)
    c = render('mug', seed=5, rig=rig)
    assert a.left.tobytes() == b.left.tobytes() and a.right.tobytes() == b.right.tobytes()
    assert a.depth.tobytes() == b.depth.tobytes() and a.albedo.tobytes() == b.albedo.tobytes()
    assert a.left.tobytes() != c.left.tobytes()
    assert a.depth.tobytes() == c.depth.tobytes()       # the seed is the pixel noise only
    # By name or by model, the same; without the table, backdrop and object only.
    pose = static_object_pose('mug')
    by_name = render_pair(rig, 'mug', pose, np.random.default_rng(4))
    by_model = render_pair(rig, get_object('mug'), pose, np.random.default_rng(4))
    assert by_name.left.tobytes() == by_model.left.tobytes()
    assert set(np.unique(by_name.surface)) == {BACKDROP, OBJECT}


@pytest.mark.parametrize('case', ['distortion', 'distortion and rectification'])
def test_rectifying_the_raw_render_gives_the_rectified_render(case):
    """OpenCV's rectification with the CameraInfo (K, D, R, P) turns the raw images into the
    ones an ideal rectified rig renders, within a few grey levels away from the border."""
    turn = cv2.Rodrigues(np.array([0.004, -0.012, 0.006]))[0]
    rectification = None if case == 'distortion' else (np.eye(3), turn)
    quiet = {'noise_sigma': 0.0, 'blur_sigma': 0.7}
    ideal = render('cat', **quiet)
    raw = render('cat', distortion=DISTORTION, rectification=rectification, **quiet)
    # The truth is the rectified left image's either way.
    assert np.array_equal(ideal.depth, raw.depth) and np.array_equal(ideal.mask, raw.mask)
    for side in ('left', 'right'):
        camera = getattr(raw, f'{side}_camera')
        assert np.allclose(camera.D, DISTORTION) and not camera.is_rectified_input
        map_x, map_y = cv2.initUndistortRectifyMap(camera.K, camera.D, camera.R, camera.P[:, :3],
                                                   camera.size, cv2.CV_32FC1)
        rectified = cv2.remap(getattr(raw, side), map_x, map_y, cv2.INTER_LINEAR).astype(float)
        target = getattr(ideal, side).astype(float)
        moved = np.abs(getattr(raw, side).astype(float) - target)[16:-16, 16:-16]
        error = np.abs(rectified - target)[16:-16, 16:-16]
        print(f'{case}, {side}: mean |rectified raw - ideal| {error.mean():.2f} '
              f'(median {np.median(error):.0f}, 90th percentile {np.percentile(error, 90):.0f}); '
              f'raw vs ideal {moved.mean():.1f}')
        # (A 0.3 px misregistration makes the mean 3.5 and the median 2 here.)
        assert error.mean() < 3.0 and np.median(error) <= 1.0
        assert moved.mean() > 3.0 * error.mean()


def test_plumb_bob_is_opencvs_and_inverts():
    rng = np.random.default_rng(2)
    x, y = rng.uniform(-0.6, 0.6, 500), rng.uniform(-0.45, 0.45, 500)
    xd, yd = distort_normalized(x, y, DISTORTION)
    expected, _ = cv2.projectPoints(np.c_[x, y, np.ones_like(x)], np.zeros(3), np.zeros(3), np.eye(3),
                                    np.array(DISTORTION))
    assert np.allclose(np.c_[xd, yd], expected[:, 0], atol=1e-12)
    xu, yu = undistort_normalized(xd, yd, DISTORTION)
    assert np.allclose(xu, x, atol=1e-11) and np.allclose(yu, y, atol=1e-11)


def test_the_rig_and_its_camera_infos():
    rig = StereoRig()
    assert (rig.width, rig.height, rig.focal, rig.baseline) == (640, 480, 600.0, 0.07)
    # It looks at the static object's centre from DEFAULT_DISTANCE, image down = tracker down-ish.
    u, v, _, z = rig.project(np.array([DEFAULT_TARGET]))
    assert abs(u[0] - rig.cx) < 1e-9 and abs(v[0] - rig.cy) < 1e-9
    assert abs(z[0] - DEFAULT_DISTANCE) < 1e-12
    assert rig.rotation[2, 1] > 0.5 and rig.position[2] < DEFAULT_TARGET[2]   # above (z down)
    assert np.allclose(rig.rotation.T @ rig.rotation, np.eye(3))
    assert np.allclose(rig.right_position - rig.position, rig.baseline * rig.rotation[:, 0])
    left, right = rig.cameras()
    assert left.is_rectified_input and right.is_rectified_input
    assert right.P[0, 3] == pytest.approx(-rig.focal * rig.baseline) and left.P[0, 3] == 0.0
    assert left.size == (640, 480) and np.allclose(left.K, rig.K)
    moved = StereoRig.looking_at(target=(0.3, 0.05, 0.0), direction=(0.0, 1.0, -1.0), distance=0.35)
    u, v, _, z = moved.project(np.array([(0.3, 0.05, 0.0)]))
    assert abs(u[0] - moved.cx) < 1e-9 and abs(z[0] - 0.35) < 1e-12
    with pytest.raises(ValueError):
        StereoRig(baseline=0.0)
    with pytest.raises(ValueError):
        rig.cameras(distortion=(0.1, 0.2))


def test_static_object_pose_is_the_sessions():
    for name in OBJECT_NAMES:
        obj = get_object(name)
        position, q = static_object_pose(obj, yaw_deg=30.0)
        settings = SessionSettings(object_name=name, static=True, static_yaw_deg=30.0)
        expected_position, expected_q = _static_pose(settings, obj)(np.zeros(1))
        assert np.allclose(position, expected_position[0], atol=1e-15)
        assert np.allclose(q, expected_q[0], atol=1e-15)


def test_render_time_of_a_full_pair_is_printed():
    rig = StereoRig()
    render('cat', rig=StereoRig(width=64, height=48, focal=60.0, cx=32.0, cy=24.0))   # compiled
    for name in OBJECT_NAMES:
        started = time.perf_counter()
        shot = render(name, rig=rig)
        print(f'{name}: 640 x 480 pair in {time.perf_counter() - started:.2f} s '
              f'({shot.mask.sum()} object pixels, object disparities '
              f'{shot.disparity[shot.mask].min():.0f}-{shot.disparity[shot.mask].max():.0f} px, '
              f'scene {shot.disparity.min():.0f}-{shot.disparity.max():.0f} px)')
