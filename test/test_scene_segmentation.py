"""The object among a stereo shot's points (scene_segmentation.py): synthetic scenes with a
known answer, and the bundled static cat against the simulator's true object mask."""

from __future__ import annotations

import numpy as np

from inhand_common.ground_truth import load_truth
from inhand_mapping.occupancy import GridSpec
from inhand_stereo.scene_segmentation import segment_object
from inhand_tools.bag_stereo_shot import read_configured_shot
from ros_helpers import WORKSPACE

SPEC = GridSpec(0.3, 0.005, (0.0, 0.0, 0.0))


def _sphere(rng, n, centre, radius):
    direction = rng.normal(size=(n, 3))
    return np.asarray(centre) + radius * direction / np.linalg.norm(direction, axis=1,
                                                                      keepdims=True)


def _scene(rng):
    """A table at z = -0.05 under the whole workspace, a ball standing on it at the centre,
    a smaller ball on the table near a corner (clutter), points outside the grid and NaNs."""
    table = np.column_stack([rng.uniform(-0.14, 0.14, (6000, 2)), np.full(6000, -0.05)])
    table[:, 2] += rng.normal(0.0, 0.0005, 6000)
    ball = _sphere(rng, 3000, (0.0, 0.0, -0.01), 0.04)
    ball = ball[ball[:, 2] > -0.045]                   # the part above the table's tolerance
    clutter = _sphere(rng, 800, (0.11, 0.11, -0.03), 0.02)
    outside = rng.uniform(0.2, 0.4, (500, 3))
    nans = np.full((300, 3), np.nan)
    parts = [table, ball, clutter, outside, nans]
    labels = np.concatenate([np.full(len(part), k) for k, part in enumerate(parts)])
    order = rng.permutation(len(labels))
    return np.concatenate(parts)[order], labels[order]


def test_the_table_clutter_and_what_lies_outside_go_the_object_stays():
    points, labels = _scene(np.random.default_rng(0))
    found = segment_object(points, SPEC)
    assert np.array_equal(found.keep, labels == 1)
    assert found.support is not None
    assert np.allclose(found.support.normal, [0.0, 0.0, 1.0], atol=0.01)  # towards the ball
    assert abs(found.support.offset - 0.05) < 0.001
    assert found.in_workspace == int(np.sum(labels <= 2))
    assert found.clusters == 2


def test_a_plane_with_points_on_both_sides_is_not_a_support():
    # a box standing free: its largest face is a plane, but the rest of the box lies on
    # one side of it and the far wall on the other, so nothing is removed as a table
    rng = np.random.default_rng(1)
    face = np.column_stack([rng.uniform(-0.05, 0.05, (3000, 2)), np.zeros(3000)])
    above = np.column_stack([rng.uniform(-0.05, 0.05, (1500, 2)), rng.uniform(0.01, 0.04, 1500)])
    below = np.column_stack([rng.uniform(-0.05, 0.05, (1500, 2)),
                             rng.uniform(-0.04, -0.01, 1500)])
    points = np.concatenate([face, above, below])
    found = segment_object(points, SPEC)
    assert found.support is None and found.keep.all()


def test_the_same_points_give_the_same_answer_and_nothing_finite_gives_nothing():
    points, _ = _scene(np.random.default_rng(2))
    assert np.array_equal(segment_object(points, SPEC).keep, segment_object(points, SPEC).keep)
    empty = segment_object(np.full((10, 3), np.nan), SPEC)
    assert not empty.keep.any() and empty.in_workspace == 0 and empty.support is None


def test_the_bundled_static_cat_against_its_true_object_mask():
    configs = [str(WORKSPACE / 'config' / 'mapping_static.yaml'),
               str(WORKSPACE / 'config' / 'stereo.yaml')]
    shot, why = read_configured_shot(WORKSPACE / 'bags' / 'cat_static', configs)
    assert shot is not None, why
    stereo = shot.config
    truth = load_truth(WORKSPACE / 'bags' / 'cat_static.truth.npz')
    assert truth.stereo is not None
    points = shot.placed.pixel_points_in_map(stereo.camera_pose)
    found = segment_object(points, stereo.grid, stereo.segmentation)
    on_object = truth.stereo.object_mask.reshape(-1) & np.isfinite(points[:, 2])
    kept = found.keep
    assert found.support is not None                  # the table
    assert (kept & on_object).sum() / on_object.sum() > 0.95
    assert (kept & on_object).sum() / kept.sum() > 0.9
