"""The live view (inhand_view): its schemas, its page's state, and the node over real DDS.

A Foxglove WebSocket client (foxglove_client.py) subscribes to the map a real occupancy node
publishes and to the frames, and saves the map through the protocol's service call; headless
Chromium loads the page during a replay of a bundled bag through the replay launcher and
the screenshot's pixels must show the map.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import cv2
import numpy as np
import pytest

from conftest import WORKSPACE
from foxglove_client import FoxgloveClient, frame_transforms
from inhand_mapping.cloud_layouts import MAP_CELL_DTYPE, TEXTURED_CELL_DTYPE
from inhand_tools.map_regions import regions
from inhand_view.frame_tree import FrameTree, Transform
from inhand_view.page_server import PageServer
from inhand_view.ros2msg_schemas import DELIMITER, DefinitionNotFound, MessageDefinitions
from inhand_view.view_state import ViewSettings, ViewState

# ------------------------------------------------------------------ plain modules


@pytest.mark.parametrize('type_name', [
    'sensor_msgs/msg/PointCloud2', 'geometry_msgs/msg/TransformStamped',
    'geometry_msgs/msg/PoseStamped', 'diagnostic_msgs/msg/DiagnosticArray',
    'sensor_msgs/msg/Image', 'sensor_msgs/msg/CameraInfo', 'stereo_msgs/msg/DisparityImage',
    'rcl_interfaces/msg/Log'])
def test_ros2msg_definitions_parse_back_to_the_ros_types(type_name):
    """rosbags reads ros2msg schemas out of MCAP files: what it makes of ours is every
    type exactly as ROS 2 Jazzy defines it."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    text = MessageDefinitions().message(type_name)
    parsed = get_types_from_msg(text, type_name)
    store = get_typestore(Stores.ROS2_JAZZY)
    assert type_name in parsed
    for name, definition in parsed.items():
        assert definition == store.fielddefs[name], name


def test_ros2msg_definition_layout_is_the_one_rosbag2_writes():
    text = MessageDefinitions().message('sensor_msgs/msg/PointCloud2')
    package_file = WORKSPACE / '.venv' / 'share' / 'sensor_msgs' / 'msg' / 'PointCloud2.msg'
    assert text.startswith(package_file.read_text())
    headers = [line for line in text.splitlines() if line.startswith('MSG: ')]
    # depth first, each once: Header, the Time it uses, then PointField
    assert headers == ['MSG: std_msgs/Header', 'MSG: builtin_interfaces/Time',
                       'MSG: sensor_msgs/PointField']
    assert text.count(f'\n{DELIMITER}\nMSG: ') == 3


def test_service_definitions_and_unknown_types():
    definitions = MessageDefinitions()
    request, response = definitions.service('std_srvs/srv/Trigger')
    assert request == '' and response.splitlines()[0].startswith('bool success')
    with pytest.raises(DefinitionNotFound, match=r'no_such_msgs/msg/Thing\.msg'):
        definitions.message('no_such_msgs/msg/Thing')
    with pytest.raises(DefinitionNotFound, match='not a type name'):
        definitions.message('PointCloud2')


def map_cloud(centres, probability, hits) -> np.ndarray:
    cells = np.zeros(len(centres), dtype=MAP_CELL_DTYPE)
    for axis, name in enumerate('xyz'):
        cells[name] = np.asarray(centres)[:, axis]
    cells['intensity'], cells['hits'] = probability, hits
    cells['first_touch'] = np.where(np.asarray(hits) > 0, 1.0, np.nan)
    return cells


def test_view_state_map_cells_explored_region_and_colours():
    state = ViewState(ViewSettings(explored_fraction=0.25, max_cells=4))
    centres = np.array([[0.0025, 0.0025, 0.0025], [0.0075, 0.0025, 0.0025],
                        [0.0125, 0.0025, 0.0025], [0.0175, 0.0025, 0.0025],
                        [0.0225, 0.0025, 0.0025], [0.0275, 0.0025, 0.0025]])
    probability = np.array([0.9, 0.7, 0.4, 0.5, 0.95, 0.55], dtype=np.float32)
    hits = np.array([9, 3, 1, 0, 0, 0])
    state.set_map(map_cloud(centres, probability, hits))
    snapshot = state.snapshot()
    shown = snapshot['map']
    # evidence: above the prior or hit; at most max_cells, the most probable first
    kept = [0, 1, 4, 5]                       # 0.4 (hit) is the least probable of the five
    assert np.allclose(np.reshape(shown['position'], (-1, 3)) * 1e-4, centres[kept])
    assert shown['probability'] == [900, 700, 950, 550]
    assert shown['resolution'] == pytest.approx(0.005)
    most, _, cut, _ = regions(hits, np.where(hits > 0, 1.0, np.nan), 0.25)
    assert shown['explored'] == most[kept].astype(int).tolist() == [1, 0, 0, 0]
    assert snapshot['counts'].items() >= {'cells': 6, 'shown_cells': 4, 'hit_cells': 3,
                                          'explored_cells': 1,
                                          'explored_min_hits': int(cut)}.items()
    assert 'map' not in state.snapshot(since=snapshot['map_version'])
    # colours where occupancy/textured has them (matched by centre), -1 elsewhere
    textured = np.zeros(2, dtype=TEXTURED_CELL_DTYPE)
    for axis, name in enumerate('xyz'):
        textured[name] = centres[[1, 4], axis]
    textured['rgb'] = np.array([0x102030, 0xA0B0C0], dtype=np.uint32).view(np.float32)
    textured['textured'] = [1, 0]
    state.set_textured(textured)
    assert state.snapshot()['map']['colour'] == [-1, 0x102030, -1, -1]


def test_view_state_sends_the_shape_with_the_map_when_it_changed():
    state = ViewState(ViewSettings())
    version = state.snapshot()['map_version']
    assert state.snapshot()['shape'] is None
    triangle = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0]])
    state.set_shape([('part 0', 'triangles', triangle, (0.96, 0.51, 0.16, 0.85))], 'object')
    shown = state.snapshot(since=version)
    assert shown['map_version'] != version
    assert shown['shape'] == {'frame': 'object', 'items': [
        {'name': 'part 0', 'kind': 'triangles', 'points': [0, 0, 0, 100, 0, 0, 0, 100, 0],
         'rgba': [0.96, 0.51, 0.16, 0.85]}]}
    assert 'shape' not in state.snapshot(since=shown['map_version'])


def test_view_state_merges_map_updates_between_whole_maps():
    """occupancy/updates (map_updates.py) changes the cells it names and adds new ones (a
    provisional cell under a fingertip) until the next whole map replaces everything."""
    from inhand_mapping.map_updates import UPDATE_CELL_DTYPE
    state = ViewState(ViewSettings())
    centres = np.array([[0.0025, 0.0025, 0.0025], [0.0075, 0.0025, 0.0025]])
    state.set_map(map_cloud(centres, np.array([0.9, 0.7], dtype=np.float32), [3, 2]))
    version = state.snapshot()['map_version']
    update = np.zeros(2, dtype=UPDATE_CELL_DTYPE)
    for axis, name in enumerate('xyz'):
        update[name] = [centres[1, axis], 0.0125 if name == 'x' else 0.0025]
    update['intensity'], update['hits'], update['provisional'] = [0.95, 0.69], [4, 0], [0, 1]
    state.apply_updates(update)
    shown = state.snapshot(since=version)['map']
    assert np.allclose(np.reshape(shown['position'], (-1, 3)) * 1e-4,
                       [[0.0025, 0.0025, 0.0025], [0.0075, 0.0025, 0.0025],
                        [0.0125, 0.0025, 0.0025]])
    assert shown['probability'] == [900, 950, 690] and shown['hits'] == [3, 4, 0]
    state.set_map(map_cloud(centres[:1], np.array([0.8], dtype=np.float32), [1]))
    assert state.snapshot()['map']['probability'] == [800]


def test_view_state_trails_keep_the_last_seconds_of_each_finger():
    state = ViewState(ViewSettings(trail_seconds=1.0, finger_labels=('thumb', 'index')))
    times = np.arange(24) * 0.125
    points = np.stack([times, np.zeros_like(times), np.zeros_like(times)], axis=1) * 0.01
    state.add_registered(points[:10], np.zeros(10, dtype=np.uint8), times[:10])
    state.add_registered(points[10:], np.zeros(14, dtype=np.uint8), times[10:])
    state.add_registered(points[:5], np.full(5, 2, dtype=np.uint8), times[:5])
    fingers = state.snapshot()['fingers']
    assert [f['label'] for f in fingers] == ['thumb', 'finger 2']
    trail = np.reshape(fingers[0]['trail'], (-1, 3)) * 1e-4
    assert len(trail) == 9                                # t = 1.875 ... 2.875
    assert np.allclose(trail, points[-9:], atol=5.1e-5)     # to 0.1 mm
    assert fingers[0]['tip'] == fingers[0]['trail'][-3:]
    state.add_registered(points[:2], np.zeros(2, dtype=np.uint8), times[:2])  # replayed again
    assert len(state.snapshot()['fingers'][0]['trail']) == 2 * 3
    assert state.snapshot()['counts']['fingertip_points'] == 31


def test_frame_tree_poses_both_ways_and_the_page_frames():
    half = math.sqrt(0.5)
    tree = FrameTree()
    tree.add(Transform('polhemus_source', 'object', 1.0, (0.1, 0.0, 0.0), (0, 0, half, half)))
    tree.add(Transform('object', 'object_centric', 1.0, (0.0, 0.02, 0.0), (0, 0, 0, 1), True))
    tree.add(Transform('polhemus_source', 'fingertip_thumb', 1.0, (0.1, 0.05, 0.0), (0, 0, 0, 1)))
    in_object = tree.poses_in('object')
    # object_centric's origin: 2 cm along object y, which is tracker -x after the 90 degree turn
    assert np.allclose(tree.poses_in('polhemus_source')['object_centric'][:3, 3], [0.08, 0, 0])
    assert np.allclose(in_object['fingertip_thumb'][:3, 3], [0.05, 0.0, 0.0])
    assert np.allclose(in_object['polhemus_source'] @ tree.poses_in('polhemus_source')['object'],
                       np.eye(4))
    assert tree.poses_in('elsewhere') == {}
    state = ViewState(ViewSettings())
    for transform in tree.transforms.values():
        state.add_transform(transform)
    frames = state.snapshot()['frames']
    assert frames['map_frame'] == 'object' and frames['tracker_frame'] == 'polhemus_source'
    assert frames['tracker']['object'][9:] == [0.1, 0.0, 0.0]
    assert set(frames['map']) == {'object', 'object_centric', 'polhemus_source',
                                  'fingertip_thumb'}


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(('127.0.0.1', 0))
        return probe.getsockname()[1]


def http(url: str, method: str = 'GET') -> tuple[int, bytes]:
    request = urllib.request.Request(url, method=method, data=b'' if method == 'POST' else None)
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, response.read()
    except urllib.error.HTTPError as error:
        return error.code, error.read()


def test_page_server_serves_the_page_the_state_and_the_actions():
    def broken():
        raise RuntimeError('no graph')
    server = PageServer('127.0.0.1', 0, lambda since: {'since': since},
                        {'save': lambda: (True, 'saved a.npz'), 'reset': broken})
    server.start()
    try:
        status, page = http(server.url)
        assert status == 200 and b'<canvas id="scene">' in page and b'view.js' in page
        assert b'fetch(' in http(server.url + 'view.js')[1]
        assert json.loads(http(server.url + 'state.json?since=7')[1]) == {'since': 7}
        assert json.loads(http(server.url + 'state.json')[1]) == {'since': None}
        assert json.loads(http(server.url + 'call/save', 'POST')[1]) == \
            {'name': 'save', 'success': True, 'message': 'saved a.npz'}
        assert json.loads(http(server.url + 'call/reset', 'POST')[1])['message'] == \
            'RuntimeError: no graph'
        assert http(server.url + 'call/format', 'POST')[0] == 404
        assert http(server.url + 'secrets')[0] == 404
        with pytest.raises(OSError):
            PageServer('127.0.0.1', server.port, lambda since: {}, {})
    finally:
        server.close()


# ------------------------------------------------------------------ the node over DDS

def live_view_args(http_port: int, foxglove_port: int, *extra: str) -> list[str]:
    return ['live_view', '--ros-args', '-p', f'http_port:={http_port}',
            '-p', f'foxglove_port:={foxglove_port}', *extra]


def wait_for_page(url: str, process, timeout: float = 30.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert process.alive(), process.output()
        try:
            return json.loads(http(url + 'state.json')[1])
        except OSError:
            time.sleep(0.1)
    raise AssertionError(f'no page at {url}:\n{process.output()}')


@pytest.mark.dds
def test_busy_ports_stop_the_node_with_one_line_naming_the_parameter():
    with socket.socket() as taken:
        taken.bind(('127.0.0.1', 0))
        taken.listen()
        busy, other = taken.getsockname()[1], free_port()
        from ros_helpers import executable_path
        for parameter, args in (('http_port', live_view_args(busy, other)),
                                ('foxglove_port', live_view_args(other, busy))):
            result = subprocess.run([executable_path(args[0]), *args[1:]], capture_output=True,
                                    text=True, timeout=60)
            assert result.returncode == 2, result.stdout + result.stderr
            lines = result.stderr.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith(
                f"live_view: parameter '{parameter}' = {busy} is refused: 127.0.0.1:{busy} is "
                'in use'), result.stderr


# Cell centres of the occupancy node's default grid (0.35 m cube at 0, 5 mm cells).
TOUCHES = np.array([[0.0025, 0.0025, 0.0025], [0.0125, -0.0075, 0.0225],
                    [-0.0225, 0.0175, -0.0125]])


@pytest.mark.dds
def test_foxglove_client_gets_the_map_frames_and_saves_through_the_protocol(tmp_path):
    import rclpy
    from geometry_msgs.msg import TransformStamped
    from rclpy.node import Node
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    from inhand_common.point_cloud import from_point_cloud2, serialize_point_cloud2
    from inhand_mapping.cloud_layouts import pack_registered
    from inhand_mapping.qos import DATA_QOS, LATCHED_QOS
    from ros_helpers import running

    http_port, foxglove_port = free_port(), free_port()
    context = rclpy.Context()
    rclpy.init(context=context)
    node = Node('test_live_view_feeder', context=context)
    points = node.create_publisher(PointCloud2, 'registration/points', DATA_QOS)
    transforms = node.create_publisher(TransformStamped, 'transforms', 10)
    static = node.create_publisher(TransformStamped, 'transforms_static', LATCHED_QOS)
    client = None
    started = time.time_ns()
    try:
        with running(['occupancy_node', '--ros-args', '-p', f'output_dir:={tmp_path}',
                      '-p', 'map_name:=view_test']) as occupancy, \
                running(live_view_args(http_port, foxglove_port)) as view:
            page = f'http://127.0.0.1:{http_port}/'
            wait_for_page(page, view)
            deadline = time.monotonic() + 30
            while points.get_subscription_count() < 2 or static.get_subscription_count() < 1:
                assert time.monotonic() < deadline, occupancy.output() + view.output()
                time.sleep(0.05)
            time.sleep(0.5)   # discovery: let both readers match the writers too
            points.publish(serialize_point_cloud2(
                pack_registered(TOUCHES, [1.0, 1.0, 1.0], [0, 1, 2]), 'object', 1, 0))
            half = math.sqrt(0.5)
            for publisher, child, parent, xyz, q in (
                    (transforms, 'object', 'polhemus_source', (0.1, 0.2, 0.3), (0.0, 0.0, half, half)),
                    (static, 'object_centric', 'object', (0.0, 0.01, 0.0), (0.0, 0.0, 0.0, 1.0))):
                msg = TransformStamped()
                msg.header.frame_id, msg.child_frame_id = parent, child
                msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 500_000_000
                t, r = msg.transform.translation, msg.transform.rotation
                t.x, t.y, t.z = xyz
                r.x, r.y, r.z, r.w = q
                publisher.publish(msg)

            client = FoxgloveClient(f'ws://127.0.0.1:{foxglove_port}')
            assert client.subprotocol == 'foxglove.sdk.v1'
            cloud = client.channel('/occupancy/cloud')
            assert (cloud['encoding'], cloud['schemaEncoding'], cloud['schemaName']) == \
                ('cdr', 'ros2msg', 'sensor_msgs/msg/PointCloud2')
            assert cloud['schema'] == MessageDefinitions().message('sensor_msgs/msg/PointCloud2')

            def touched(payload: bytes) -> bool:
                return int(from_point_cloud2(deserialize_message(payload, PointCloud2))['hits']
                           .astype(bool).sum()) == len(TOUCHES)
            stamp, payload = client.message(client.subscribe('/occupancy/cloud'), touched)
            cells = from_point_cloud2(deserialize_message(payload, PointCloud2))
            hit = cells[cells['hits'] > 0]
            centres = np.stack([hit['x'], hit['y'], hit['z']], axis=1)
            assert np.allclose(sorted(map(tuple, centres)), sorted(map(tuple, TOUCHES)),
                               atol=1e-7)
            assert started <= stamp <= time.time_ns()          # the receive time

            frames = client.subscribe('/frame_transforms')
            _, payload = client.message(frames, lambda p: any(
                t['child'] == 'object' for t in frame_transforms(p)))
            moved = next(t for t in frame_transforms(payload) if t['child'] == 'object')
            assert moved['parent'] == 'polhemus_source' and moved['stamp'] == 12.5
            assert moved['translation'] == pytest.approx((0.1, 0.2, 0.3))
            assert moved['rotation'] == pytest.approx((0, 0, half, half))
            channel = client.channel('/transforms_static')
            assert channel['schemaName'] == 'geometry_msgs/msg/TransformStamped'

            service = client.service('/occupancy/save')
            assert service['type'] == 'std_srvs/srv/Trigger'
            answer = deserialize_message(
                client.call('/occupancy/save', serialize_message(Trigger.Request())),
                Trigger.Response)
            assert answer.success, answer.message
            assert (tmp_path / 'view_test.npz').is_file() and 'view_test.ply' in answer.message

            # A client that comes later gets the latched map and every frame's latest
            # transform, although nothing new is published.
            late = FoxgloveClient(f'ws://127.0.0.1:{foxglove_port}')
            try:
                late.message(late.subscribe('/occupancy/cloud'), touched, timeout=5)
                _, payload = late.message(late.subscribe('/frame_transforms'), timeout=5)
                assert {t['child'] for t in frame_transforms(payload)} == \
                    {'object', 'object_centric'}
            finally:
                late.close()

            state = json.loads(http(page + 'state.json')[1])
            assert state['counts']['fingertip_points'] == 3, state
            assert state['counts']['refused_transforms'] == 0, view.output()
            assert state['frames']['tracker']['object'][9:] == [0.1, 0.2, 0.3]
            assert state['calls']['save']['success']
            reset = json.loads(http(page + 'call/reset', 'POST')[1])
            assert reset == {'name': 'reset', 'success': True, 'message': 'map cleared'}
    finally:
        if client is not None:
            client.close()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


# ------------------------------------------------------------------ the page in a browser

def chromium() -> str | None:
    return shutil.which('chromium') or shutil.which('chromium-browser')


def screenshot(url: str, path, profile) -> np.ndarray:
    """The page as headless Chromium draws it (1280 x 800), as an RGB image."""
    command = [chromium(), '--headless', '--disable-gpu', '--disable-dev-shm-usage',
               '--hide-scrollbars',
               '--force-device-scale-factor=1', '--window-size=1280,800',
               '--virtual-time-budget=5000', f'--user-data-dir={profile}',
               f'--screenshot={path}', url]
    if os.geteuid() == 0:
        command.insert(1, '--no-sandbox')      # Chromium's sandbox refuses root
    result = subprocess.run(command, capture_output=True, text=True, timeout=60)
    image = cv2.imread(str(path))
    assert image is not None, result.stdout + result.stderr
    return image[..., ::-1]


def map_pixels(image: np.ndarray) -> int:
    """Pixels of the drawing (left of the side panel, below the header) in the colours of
    probability above 0.5: pale yellow to red."""
    scene = image[40:, :940].astype(int)
    r, g, b = scene[..., 0], scene[..., 1], scene[..., 2]
    return int(np.count_nonzero((r >= 170) & (b <= 140) & (r - b >= 80) & (g <= r)))


@pytest.mark.dds
def test_page_in_headless_chromium_draws_the_map_of_a_replayed_bag(tmp_path, monkeypatch):
    from ros_helpers import running
    from test_launch_scripts import children_alive, descendants
    if chromium() is None:
        if os.environ.get('CI') == 'true':
            pytest.fail('no chromium on CI: launch_scripts/install_browser.sh should have '
                        'installed it')
        pytest.skip('no chromium (bash launch_scripts/install_browser.sh installs it)')
    (tmp_path / 'cat_static').symlink_to(WORKSPACE / 'bags' / 'cat_static')  # no truth: no metrics
    http_port, foxglove_port = free_port(), free_port()
    log = open(tmp_path / 'launch.log', 'w+')
    launcher = subprocess.Popen(
        [sys.executable, str(WORKSPACE / 'launch_scripts' / 'replay_bag.py'),
         str(tmp_path / 'cat_static'), '--output', str(tmp_path / 'out'), '--no-render',
         '--view', '--http-port', str(http_port), '--foxglove-port', str(foxglove_port)],
        stdout=log, stderr=subprocess.STDOUT, text=True)
    try:
        # The page with an empty map: a view alone in a DDS domain of its own (the tests'
        # graphs use 100-199).
        lonely_http = free_port()
        with monkeypatch.context() as patch:
            patch.setenv('ROS_DOMAIN_ID', str(200 + os.getpid() % 30))
            lonely = running(live_view_args(lonely_http, free_port()))
        with lonely as lonely:
            empty_url = f'http://127.0.0.1:{lonely_http}/'
            wait_for_page(empty_url, lonely)
            empty = screenshot(empty_url + '?colour=probability', tmp_path / 'empty.png',
                               tmp_path / 'profile-empty')
            assert json.loads(http(empty_url + 'state.json')[1])['counts']['cells'] == 0
        deadline = time.monotonic() + 120
        while 'live view at' not in (tmp_path / 'launch.log').read_text():
            assert launcher.poll() is None and time.monotonic() < deadline, \
                (tmp_path / 'launch.log').read_text()
            time.sleep(0.2)
        page = f'http://127.0.0.1:{http_port}/'
        counts = json.loads(http(page + 'state.json')[1])['counts']
        assert counts['fingertip_points'] == 5400 and counts['occupied_cells'] > 500, counts
        assert counts['explored_cells'] > 0
        full = screenshot(page + '?colour=probability', tmp_path / 'map.png',
                          tmp_path / 'profile-map')
        textured = screenshot(page, tmp_path / 'textured.png', tmp_path / 'profile-textured')
        drawn, blank = map_pixels(full), map_pixels(empty)
        print(f'map pixels: {drawn} with the map, {blank} without; textured page '
              f'{map_pixels(textured)}; screenshots in {tmp_path}')
        assert drawn > 5000 and drawn > 20 * max(blank, 1), (drawn, blank)
        assert textured.std() > 10                                     # not a blank page
        answer = json.loads(http(page + 'call/save', 'POST')[1])
        assert answer['success'] and (tmp_path / 'out' / 'cat_static.npz').is_file(), answer
        started = descendants(launcher.pid)
        launcher.send_signal(signal.SIGINT)
        assert launcher.wait(60) == 0, (tmp_path / 'launch.log').read_text()
        time.sleep(0.5)
        assert children_alive(started) == []
    finally:
        if launcher.poll() is None:   # Ctrl-C: its process group stops what it started
            launcher.send_signal(signal.SIGINT)
            try:
                launcher.wait(60)
            except subprocess.TimeoutExpired:
                launcher.kill()
                launcher.wait()
        log.close()
