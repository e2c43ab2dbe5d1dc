"""The stereo node over real DDS: a bundled bag's image pair and the fingertips go through the
whole graph (registration, occupancy, stereo), and the textured map comes out."""

from __future__ import annotations

import time

import numpy as np
import pytest

from conftest import WORKSPACE
from inhand_common.ground_truth import load_truth
from inhand_common.point_cloud import from_point_cloud2
from inhand_tools.launching import ProcessGroup, mapping_graph
from ros_helpers import BackgroundNode

pytestmark = pytest.mark.dds


class LatchedListener(BackgroundNode):
    """Keeps the latest message of each latched topic."""

    def __init__(self, topics):
        from inhand_mapping.qos import LATCHED_QOS
        super().__init__('test_stereo_listener')
        self.latest = {}
        for topic, msg_type in topics:
            self.node.create_subscription(
                msg_type, topic, lambda msg, topic=topic: self._keep(topic, msg), LATCHED_QOS)
        self.start()

    def _keep(self, topic, msg):
        with self.lock:
            self.latest[topic] = msg

    def wait_for(self, predicate, timeout: float = 60.0):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                if predicate(self.latest):
                    return dict(self.latest)
            time.sleep(0.1)
        with self.lock:
            raise AssertionError(f'only {sorted(self.latest)} arrived')


@pytest.mark.parametrize('bag, config', [('cat_static', 'mapping_static.yaml'),
                                         ('cat_moving', 'mapping.yaml')])
def test_a_bag_with_a_stereo_pair_gives_the_textured_map(tmp_path, bag, config):
    from sensor_msgs.msg import PointCloud2
    from stereo_msgs.msg import DisparityImage
    truth = load_truth(WORKSPACE / 'bags' / f'{bag}.truth.npz')
    topics = [('occupancy/occupied', PointCloud2), ('occupancy/textured', PointCloud2),
              ('stereo/points', PointCloud2), ('stereo/disparity', DisparityImage)]
    listener = LatchedListener(topics)
    try:
        with ProcessGroup() as group:
            mapping_graph(group, str(WORKSPACE / 'config' / config), str(tmp_path), bag,
                          stereo_config=str(WORKSPACE / 'config' / 'stereo.yaml'))
            assert group.run('replay', ['bag_replay', str(WORKSPACE / 'bags' / bag), '--fast',
                                        '--quiet']) == 0

            def complete(latest):
                # the textured map of the final occupied map (the latched ones of the end)
                return (all(topic in latest for topic, _ in topics)
                        and latest['occupancy/textured'].width
                        == latest['occupancy/occupied'].width > 600)
            latest = listener.wait_for(complete)
    finally:
        listener.close()
    disparity = latest['stereo/disparity']
    assert disparity.header.frame_id == 'stereo_left_optical'
    assert (disparity.f, round(disparity.t, 6)) == (600.0, 0.07)
    assert (disparity.min_disparity, disparity.max_disparity) == (48.0, 159.0)
    image = np.frombuffer(bytes(disparity.image.data), '<f4').reshape(480, 640)
    valid = image >= disparity.min_disparity
    object_pixels = truth.stereo.object_mask
    assert valid[object_pixels].mean() > 0.8          # the object is matched densely ...
    error = np.abs(image - truth.stereo.disparity)[object_pixels & valid]
    assert np.mean(error > 2.0) < 0.05                # ... and right (bad-2 under 5%)

    points = from_point_cloud2(latest['stereo/points'])
    assert latest['stereo/points'].header.frame_id == 'object' and len(points) > 10_000

    textured = from_point_cloud2(latest['occupancy/textured'])
    occupied = from_point_cloud2(latest['occupancy/occupied'])
    assert latest['occupancy/textured'].header.frame_id == 'object'
    assert np.array_equal(textured['x'], occupied['x'])       # every occupied cell, in order
    seen = textured['textured'].astype(bool)
    # The camera sees one side of the cat: a third or so of the surface, not all, not none.
    assert 0.15 < seen.mean() < 0.7, seen.mean()
    rgb = textured['rgb'].view(np.uint32)
    assert np.all(rgb[~seen] == 0) and np.all(rgb[seen] != 0)
