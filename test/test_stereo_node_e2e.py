"""The stereo node over real DDS: a bundled bag's image pair and the fingertips go through the
whole graph (registration, occupancy, stereo), and the textured map comes out."""

from __future__ import annotations

import subprocess
import time

import numpy as np
import pytest
import yaml
from scipy.spatial import cKDTree

from conftest import WORKSPACE
from inhand_common.ground_truth import in_frame, load_truth
from inhand_common.point_cloud import from_point_cloud2
from inhand_mapping.cloud_layouts import seen_points
from inhand_mapping.map_io import load_local_maps, load_npz, read_ply
from inhand_tools.launching import ProcessGroup, mapping_graph
from polling import wait_until
from ros_helpers import BackgroundNode, call_trigger, executable_path

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
        def arrived():
            with self.lock:
                return dict(self.latest) if predicate(self.latest) else None

        def said():
            with self.lock:
                return f'wanted topics: only {sorted(self.latest)} arrived'
        return wait_until(arrived, timeout, said, period=0.1)


def _with_fusion(tmp_path, config: str, fusion: str) -> str:
    """The shipped mapping file with the occupancy node's ``fusion`` set."""
    document = yaml.safe_load((WORKSPACE / 'config' / config).read_text())
    section = next(value for key, value in document.items() if key.endswith('occupancy_node'))
    section['ros__parameters']['fusion'] = fusion
    path = tmp_path / f'{fusion}_{config}'
    path.write_text(yaml.safe_dump(document))
    return str(path)


@pytest.fixture(scope='module')
def two_pair_bag(tmp_path_factory):
    """A held cat turned in front of the fixed rig, with a pair before the exploration and
    one 20 s into it (another side of the cat)."""
    bag = tmp_path_factory.mktemp('two_pairs') / 'cat_two_pairs'
    subprocess.run([executable_path('simulate_session'), '--object', 'cat', '--moving',
                    '--rate', '15', '--duration', '40', '--seed', '5', '--stereo',
                    '--stereo-shots', '2', '--output', str(bag), '--quiet'], check=True,
                   capture_output=True, timeout=300)
    return bag


@pytest.mark.parametrize('bag, config, fusion', [('cat_static', 'mapping_static.yaml', 'none'),
                                                 ('two_pairs', 'mapping.yaml', 'product')])
def test_a_bag_with_a_stereo_pair_gives_the_textured_map(tmp_path, request, bag, config,
                                                         fusion):
    from sensor_msgs.msg import PointCloud2
    from stereo_msgs.msg import DisparityImage
    config = _with_fusion(tmp_path, config, fusion)
    bag_path = request.getfixturevalue('two_pair_bag') if bag == 'two_pairs' \
        else WORKSPACE / 'bags' / bag
    bag = bag_path.name
    pairs = 2 if bag == 'cat_two_pairs' else 1
    min_cells = 300 if pairs == 2 else 600
    truth = load_truth(f'{bag_path}.truth.npz')
    topics = [('occupancy/occupied', PointCloud2), ('occupancy/textured', PointCloud2),
              ('stereo/points', PointCloud2), ('stereo/disparity', DisparityImage),
              ('stereo/object', PointCloud2)]
    if fusion != 'none':
        topics.append(('vision/cloud', PointCloud2))
    listener = LatchedListener(topics)
    try:
        with ProcessGroup() as group:
            mapping_graph(group, config, str(tmp_path), bag,
                          stereo_config=str(WORKSPACE / 'config' / 'stereo.yaml'))
            # Two pairs 20 s apart: at --fast they come 25 ms apart, and the node takes the
            # newest when its worker is busy (pair_flow.py), so the first could be skipped
            # and the map would not be build_map's. At 5x they come 4 s apart.
            speed = ['--rate', '5'] if pairs == 2 else ['--fast']
            assert group.run('replay', ['bag_replay', str(bag_path), *speed, '--quiet']) == 0

            last_pair = truth.stereo.time + (20.0 if pairs == 2 else 0.0)

            def of_last_pair(message) -> bool:
                stamp = message.header.stamp.sec + message.header.stamp.nanosec * 1e-9
                return abs(stamp - last_pair) < 1e-3

            def complete(latest):
                # the textured map of the final occupied map (the latched ones of the end;
                # with fusion, of the map fused with the last pair's vision map: on a busy
                # machine the second pair's can come well after the first's has settled)
                return (all(topic in latest for topic, _ in topics)
                        and of_last_pair(latest['stereo/disparity'])
                        and (fusion == 'none' or of_last_pair(latest['vision/cloud']))
                        and latest['occupancy/textured'].width
                        == latest['occupancy/occupied'].width > min_cells)
            latest = listener.wait_for(complete)
            while True:       # until the graph is quiet: the map and its texture settled
                time.sleep(1.5)
                settled = listener.wait_for(complete)
                if all(settled[topic] is latest[topic] for topic, _ in topics):
                    break
                latest = settled
            assert call_trigger('occupancy/save').success
    finally:
        listener.close()
    disparity = latest['stereo/disparity']
    assert disparity.header.frame_id == 'stereo_left_optical'
    assert (disparity.f, round(disparity.t, 6)) == (600.0, 0.07)
    assert (disparity.min_disparity, disparity.max_disparity) == (48.0, 159.0)
    # the latest pair's: the second one is 20 s into the session
    stamp = disparity.header.stamp.sec + disparity.header.stamp.nanosec * 1e-9
    assert stamp == pytest.approx(truth.stereo.time + (20.0 if pairs == 2 else 0.0), abs=1e-6)
    if pairs == 1:          # the truth describes the first pair
        image = np.frombuffer(bytes(disparity.image.data), '<f4').reshape(480, 640)
        valid = image >= disparity.min_disparity
        object_pixels = truth.stereo.object_mask
        assert valid[object_pixels].mean() > 0.8          # the object is matched densely ...
        error = np.abs(image - truth.stereo.disparity)[object_pixels & valid]
        assert np.mean(error > 2.0) < 0.05                # ... and right (bad-2 under 5%)

    points = from_point_cloud2(latest['stereo/points'])
    assert latest['stereo/points'].header.frame_id == 'object' and len(points) > 10_000
    # the object's points, for the exploration node: on the object (not the table or the
    # backdrop), each with where the camera was
    seen, viewpoints = seen_points(from_point_cloud2(latest['stereo/object']))
    assert latest['stereo/object'].header.frame_id == 'object' and 3000 < len(seen) <= 20_000
    assert np.ptp(viewpoints, axis=0).max() < 1e-6
    if pairs == 1:      # static: the map frame is the tracker's, where the camera stands
        surface = in_frame(truth, 'tracker').surface_points
        assert np.allclose(viewpoints[0], truth.stereo.camera_pose[:3], atol=1e-4)
        distance, _ = cKDTree(surface).query(seen)
        assert np.median(distance) < 0.002 and np.mean(distance < 0.005) > 0.9

    textured = from_point_cloud2(latest['occupancy/textured'])
    occupied = from_point_cloud2(latest['occupancy/occupied'])
    assert latest['occupancy/textured'].header.frame_id == 'object'
    assert np.array_equal(textured['x'], occupied['x'])       # every occupied cell, in order
    seen = textured['textured'].astype(bool)
    # The camera sees one side of the cat: a third or so of the surface, not all, not none.
    assert 0.15 < seen.mean() < 0.7, seen.mean()
    rgb = textured['rgb'].view(np.uint32)
    assert np.all(rgb[~seen] == 0) and np.all(rgb[seen] != 0)

    # The saved map carries the colours, and it is build_map's of the same bag and files,
    # fused with the vision map when fusion is on.
    offline = subprocess.run([executable_path('build_map'), str(bag_path),
                              '--config', config, '--config',
                              str(WORKSPACE / 'config' / 'stereo.yaml'), '--output-dir',
                              str(tmp_path / 'offline'), '--quiet'],
                             capture_output=True, text=True, timeout=120)
    assert offline.returncode == 0, offline.stderr
    assert 'occupied cells seen by the stereo pair' in offline.stdout
    saved, built = (read_ply(folder / f'{bag}.ply')
                    for folder in (tmp_path, tmp_path / 'offline'))
    assert np.array_equal(saved['textured'], seen.astype(np.uint8))
    for field in ('x', 'y', 'z', 'intensity', 'red', 'green', 'blue', 'textured'):
        assert np.array_equal(saved[field], built[field]), field
    saved_grid, _ = load_npz(tmp_path / f'{bag}.npz')
    built_grid, _ = load_npz(tmp_path / 'offline' / f'{bag}.npz')
    assert np.array_equal(saved_grid.log_odds, built_grid.log_odds)
    saved_local = load_local_maps(tmp_path / f'{bag}.npz')
    built_local = load_local_maps(tmp_path / 'offline' / f'{bag}.npz')
    assert sorted(saved_local) == sorted(built_local) == \
        ([] if fusion == 'none' else ['touch', 'vision'])
    for name in saved_local:
        assert np.array_equal(saved_local[name], built_local[name]), name
    if fusion != 'none':
        # the vision map saw one side of the cat: some cells occupied, many free
        vision = saved_local['vision']
        assert (vision > 0).sum() > 100 and (vision < 0).sum() > 1000
        assert f'vision: {pairs} stereo pair(s)' in offline.stdout
    if pairs == 2:
        # each pair integrated once: the second saw cells the first did not
        first = _first_pair_vision(bag_path)
        assert np.count_nonzero(saved_local['vision'] > 0) > \
            np.count_nonzero(first > 0) + 20


def _first_pair_vision(bag):
    """The vision map of a bag's first pair alone (the tracked rig of the shipped files)."""
    from inhand_stereo.vision_model import VisionMap
    from inhand_tools.bag_stereo_shot import read_configured_shot
    configs = [str(WORKSPACE / 'config' / 'mapping.yaml'),
               str(WORKSPACE / 'config' / 'stereo.yaml')]
    shot, why = read_configured_shot(bag, configs)
    assert shot is not None and len(shot.pairs.placed) == 2, why
    stereo = shot.config
    vision = VisionMap(stereo.grid, stereo.vision, stereo.clamp)
    shot.placed.integrate_into(vision, stereo.camera_pose, stereo.segmentation)
    return vision.log_odds


class PairPublisher(BackgroundNode):
    """Publishes stereo pairs and camera_infos as a camera driver would (reliably)."""

    def __init__(self):
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image
        super().__init__('test_pair_publisher')
        qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
        self.images = {side: self.node.create_publisher(Image, f'stereo/{side}/image_raw', qos)
                       for side in ('left', 'right')}
        self.infos = {side: self.node.create_publisher(CameraInfo, f'stereo/{side}/camera_info',
                                                       qos) for side in ('left', 'right')}
        self.start()

    def wait_matched(self, timeout: float = 20.0) -> None:
        deadline = time.monotonic() + timeout
        publishers = [*self.images.values(), *self.infos.values()]
        while any(p.get_subscription_count() == 0 for p in publishers):
            assert time.monotonic() < deadline, 'stereo_node did not subscribe'
            time.sleep(0.05)
        time.sleep(0.5)   # and the node's readers match ours

    def publish(self, sec: int, sizes=((64, 48), (64, 48)), encoding='rgb8', focal=60.0):
        from sensor_msgs.msg import CameraInfo, Image
        for side, (width, height) in zip(('left', 'right'), sizes):
            info = CameraInfo()
            info.header.stamp.sec = sec
            info.width, info.height = 64, 48
            info.distortion_model = 'plumb_bob'
            info.k = [focal, 0.0, 32.0, 0.0, focal, 24.0, 0.0, 0.0, 1.0]
            info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
            tx = 0.0 if side == 'left' else -focal * 0.07
            info.p = [focal, 0.0, 32.0, tx, 0.0, focal, 24.0, 0.0, 0.0, 0.0, 1.0, 0.0]
            self.infos[side].publish(info)
            image = Image()
            image.header.stamp.sec = sec
            image.width, image.height, image.encoding = width, height, encoding
            image.step = 3 * width
            image.data = bytes(3 * width * height)
            self.images[side].publish(image)


def test_bad_pairs_are_refused_in_one_line_and_the_node_keeps_running():
    from ros_helpers import running
    config = str(WORKSPACE / 'config' / 'mapping_static.yaml')
    with running(['stereo_node', '--ros-args', '--params-file', config]) as node:
        publisher = PairPublisher()
        try:
            publisher.wait_matched()
            # one at a time: pairs that come while the node works on one are skipped (the
            # newest is taken, pair_flow.py), so each waits for the last one's answer
            for sec, options, expected in (
                    (1, {'sizes': ((64, 48), (32, 24))}, 'left image is 64x48 but right image is 32x24'),
                    (2, {'encoding': 'bayer_rggb8'}, "unsupported image encoding 'bayer_rggb8'"),
                    (3, {'focal': 0.0}, 'zero or negative focal length')):
                publisher.publish(sec, **options)
                deadline = time.monotonic() + 20
                while expected not in node.output():
                    assert time.monotonic() < deadline, node.output()
                    time.sleep(0.05)
            assert node.alive()
            refusals = [line for line in node.output().splitlines() if 'not used' in line]
            assert len(refusals) == 3, refusals            # one line each
            assert 'Traceback' not in node.output()
        finally:
            publisher.close()


def _wait_in_output(node, text: str, timeout: float) -> float:
    """Seconds until ``text`` appears in the node's output (AssertionError after timeout)."""
    started = time.monotonic()
    while text not in node.output():
        assert time.monotonic() - started < timeout, f'no {text!r} in:\n{node.output()}'
        time.sleep(0.05)
    return time.monotonic() - started


def test_the_stereo_node_takes_the_graphs_mode_from_the_registration_node():
    """The issue's graph: registration static, the stereo node on its defaults: the pair is
    placed (static), with no mode of the node's own to disagree."""
    from sensor_msgs.msg import PointCloud2

    from ros_helpers import running
    listener = LatchedListener([('stereo/points', PointCloud2)])
    publisher = PairPublisher()
    try:
        with running(['registration_node', '--ros-args', '-p', 'mode:=static']), \
                running(['stereo_node']) as stereo:
            _wait_in_output(stereo, 'placing the stereo pairs in static mode (from '
                            '/registration_node)', 30)
            publisher.wait_matched()
            publisher.publish(1)
            cloud = listener.wait_for(lambda latest: 'stereo/points' in latest, 20)
            assert cloud['stereo/points'].header.frame_id == 'object'
            assert 'waited' not in stereo.output()
    finally:
        publisher.close()
        listener.close()


def test_a_pair_that_cannot_be_placed_is_said_within_seconds_with_what_to_do():
    """No registration node: the mode is unknown, said within a few seconds; then a
    tracked registration node without object poses: that is said too, and diagnostics warn."""
    from ros_helpers import running
    publisher = PairPublisher()
    try:
        with running(['stereo_node']) as stereo:
            publisher.wait_matched()
            publisher.publish(1)
            waited = _wait_in_output(stereo, "the graph's mode is not known", 10)
            assert waited < 6.0
            assert 'Start the registration node' in stereo.output()
            with running(['registration_node', '--ros-args', '-p', 'mode:=tracked']):
                _wait_in_output(stereo, 'placing the stereo pairs in tracked mode', 30)
                _wait_in_output(stereo, 'no object pose has come on polhemus/object/pose', 10)
                assert 'static mode' in stereo.output().split('no object pose has come')[-1]
    finally:
        publisher.close()
