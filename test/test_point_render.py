"""The point-splatting renderer of the texture benchmark's validation set
(``test/benchmarks/point_render.py``) against the exact picture of a sphere: its depth is
the ray's first intersection with the sphere, its mask the sphere's silhouette, and the two
images agree where the disparity says they should."""

from __future__ import annotations

import sys

import numpy as np
from scipy import ndimage

from inhand_sim.stereo_rig import StereoRig
from pose_sessions import fibonacci_sphere
from ros_helpers import WORKSPACE

sys.path.insert(0, str(WORKSPACE / 'test' / 'benchmarks'))
from point_render import render_samples

CENTRE = np.array([0.25, 0.0, 0.05])
RADIUS = 0.04


def test_a_sphere_of_samples_renders_at_its_true_depth_and_outline():
    rig = StereoRig.looking_at(target=CENTRE, direction=(0.3, -0.8, -0.5), distance=0.42)
    points = CENTRE + fibonacci_sphere(30_000, RADIUS)
    albedo = np.full((len(points), 3), 180.0)
    albedo[:, 0] = 100.0 + 100.0 * (points[:, 2] > CENTRE[2])     # two halves, two colours
    shot = render_samples(rig, points, albedo, np.random.default_rng(0))
    # the exact picture: each pixel centre's ray against the sphere
    columns, rows = np.meshgrid(np.arange(rig.width), np.arange(rig.height))
    rays = np.stack([(columns - rig.cx) / rig.focal, (rows - rig.cy) / rig.focal,
                     np.ones(columns.shape)], axis=-1)
    centre = rig.rotation.T @ (CENTRE - rig.position)              # in the camera frame
    a = np.sum(rays * rays, axis=-1)
    b = -2.0 * rays @ centre
    c = centre @ centre - RADIUS ** 2
    hit = b * b - 4.0 * a * c >= 0.0
    depth = (-b - np.sqrt(np.where(hit, b * b - 4.0 * a * c, 0.0))) / (2.0 * a)
    # the outline, to the discs' radius (1.4 px here): no hole inside, no blob outside
    assert not np.any(ndimage.binary_erosion(hit) & ~shot.mask)
    assert not np.any(shot.mask & ~ndimage.binary_dilation(hit, iterations=2))
    inner = ndimage.binary_erosion(hit, iterations=2) & shot.mask   # off the outline
    error = np.abs(shot.depth[inner] - depth[inner])
    assert np.median(error) < 0.0002 and np.percentile(error, 95) < 0.0015
    # behind the sphere: the backdrop, farther than the sphere everywhere
    assert shot.depth[~shot.mask].min() > depth[hit].max()
    # the right image shows the same surface where the left pixel's disparity points
    rows_in, cols_in = np.nonzero(inner)
    shift = np.rint(rig.focal * rig.baseline / shot.depth[inner]).astype(int)
    keep = cols_in - shift >= 0
    left = shot.left[rows_in[keep], cols_in[keep]].astype(int)
    right = shot.right[rows_in[keep], cols_in[keep] - shift[keep]].astype(int)
    assert np.median(np.abs(left - right)) <= 8
