"""The graph's Fast DDS profile (dds_profile.py): what it sets, when it stays out of the
way, and that a camera-sized image published best effort arrives whole in another process."""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ElementTree

import pytest

from inhand_common.dds_profile import (
    PROFILES_VARIABLE,
    PUBLICATION_MODE_VARIABLE,
    SHM_SEGMENT,
    UDP_BUFFER,
    profile_xml,
    shipped_profile,
)

NS = '{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}'


def test_the_profile_is_fast_dds_xml_with_a_large_segment_and_socket_buffers():
    root = ElementTree.fromstring(profile_xml(writer_heartbeat_ns=20_000_000))
    descriptors = {d.find(f'{NS}type').text: d for d in root.iter(f'{NS}transport_descriptor')}
    assert int(descriptors['SHM'].find(f'{NS}segment_size').text) == SHM_SEGMENT >= 8 * 921_600
    assert int(descriptors['UDPv4'].find(f'{NS}receiveBufferSize').text) == UDP_BUFFER
    participant = root.find(f'{NS}participant')
    assert participant.get('is_default_profile') == 'true'
    assert participant.find(f'{NS}rtps/{NS}useBuiltinTransports').text == 'false'
    assert root.find(f'{NS}data_writer/{NS}times/{NS}heartbeatPeriod/{NS}nanosec').text == \
        '20000000'
    assert ElementTree.fromstring(profile_xml()).find(f'{NS}data_writer') is None


def test_the_profile_is_named_for_the_session_and_a_users_own_is_left_alone(monkeypatch):
    monkeypatch.delenv(PROFILES_VARIABLE, raising=False)
    monkeypatch.delenv('FASTDDS_DEFAULT_PROFILES_FILE', raising=False)
    monkeypatch.delenv('RMW_IMPLEMENTATION', raising=False)
    with shipped_profile() as path:
        assert path is not None and os.environ[PROFILES_VARIABLE] == str(path)
        assert path.read_text() == profile_xml()
    assert PROFILES_VARIABLE not in os.environ and not path.exists()
    monkeypatch.setenv('FASTDDS_DEFAULT_PROFILES_FILE', '/etc/mine.xml')
    with shipped_profile() as path:
        assert path is None and PROFILES_VARIABLE not in os.environ
    monkeypatch.delenv('FASTDDS_DEFAULT_PROFILES_FILE')
    monkeypatch.setenv('RMW_IMPLEMENTATION', 'rmw_cyclonedds_cpp')
    with shipped_profile() as path:
        assert path is None


CHILD = '''
import sys, time
import rclpy
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image
from inhand_common.dds_profile import shipped_profile
role, count = sys.argv[1], int(sys.argv[2])
with shipped_profile():
    rclpy.init()
    node = rclpy.create_node('profile_' + role)
    if role == 'writer':
        publisher = node.create_publisher(Image, 'stereo/left/image_raw', qos_profile_sensor_data)
        image = Image(height=480, width=640, encoding='rgb8', step=1920, data=bytes(921600))
        deadline = time.monotonic() + 20
        while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(1.0)
        for k in range(count):
            image.header.frame_id = str(k)
            publisher.publish(image)
            time.sleep(1 / 15)
        time.sleep(1.0)
    else:
        got = set()
        node.create_subscription(Image, 'stereo/left/image_raw',
                                 lambda m: got.add(m.header.frame_id), qos_profile_sensor_data)
        print('ready', flush=True)
        deadline = time.monotonic() + 30
        while len(got) < count and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        print('received', len(got), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
'''


@pytest.mark.dds
def test_camera_images_published_best_effort_arrive_whole_in_another_process():
    """Fast DDS's defaults lose most of them (a 921,600-byte image goes over UDP in
    fragments); the graph's profile puts them through shared memory."""
    env = {key: value for key, value in os.environ.items()
           if key not in (PROFILES_VARIABLE, 'FASTDDS_DEFAULT_PROFILES_FILE')}
    env['ROS_DOMAIN_ID'] = str(100 + os.getpid() % 100)
    count = 30
    reader = subprocess.Popen([sys.executable, '-c', CHILD, 'reader', str(count)], env=env,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert reader.stdout.readline().strip() == 'ready'
        writer = subprocess.run([sys.executable, '-c', CHILD, 'writer', str(count)], env=env,
                                capture_output=True, text=True, timeout=60)
        assert writer.returncode == 0, writer.stderr
        out = reader.communicate(timeout=60)[0]
    finally:
        reader.kill()
    assert out.split()[-1] == str(count), out


def test_asynchronous_publication_is_asked_for_only_when_the_user_chose_no_mode(monkeypatch):
    """occupancy_node's large latched clouds are published asynchronously (dds_profile.py);
    the mode is the process's while the block runs, and a user's own choice stands."""
    for name in (PROFILES_VARIABLE, 'FASTDDS_DEFAULT_PROFILES_FILE', 'RMW_IMPLEMENTATION',
                 PUBLICATION_MODE_VARIABLE):
        monkeypatch.delenv(name, raising=False)
    with shipped_profile():
        assert PUBLICATION_MODE_VARIABLE not in os.environ
    with shipped_profile(asynchronous=True):
        assert os.environ[PUBLICATION_MODE_VARIABLE] == 'ASYNCHRONOUS'
    assert PUBLICATION_MODE_VARIABLE not in os.environ
    monkeypatch.setenv(PUBLICATION_MODE_VARIABLE, 'SYNCHRONOUS')
    with shipped_profile(asynchronous=True):
        assert os.environ[PUBLICATION_MODE_VARIABLE] == 'SYNCHRONOUS'
    assert os.environ[PUBLICATION_MODE_VARIABLE] == 'SYNCHRONOUS'
    from inhand_mapping.nodes.occupancy_node import ASYNCHRONOUS_PUBLISHING
    assert ASYNCHRONOUS_PUBLISHING


LATCHED_CHILD = '''
import sys, time
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import UInt8MultiArray
from inhand_common.dds_profile import shipped_profile
qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
role = sys.argv[1]
with shipped_profile(asynchronous=role == 'writer'):
    rclpy.init()
    node = rclpy.create_node('latched_' + role)
    if role == 'writer':
        publisher = node.create_publisher(UInt8MultiArray, 'occupancy/cloud', qos)
        for k in range(3):      # the last of three 8.2 MB maps, kept for a late reader
            publisher.publish(UInt8MultiArray(data=bytes([k]) * 8_232_000))
        print('published', flush=True)
        sys.stdin.readline()    # until the reader is done
    else:
        got = []
        node.create_subscription(UInt8MultiArray, 'occupancy/cloud',
                                 lambda m: got.append((len(m.data), m.data[0])), qos)
        deadline = time.monotonic() + 30
        while not got and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        print('received', got, flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
'''


@pytest.mark.dds
def test_an_asynchronous_writer_keeps_its_latest_large_message_for_a_late_reader():
    """The occupancy node's mode: a reader that starts after the map was published gets
    the latest map whole (transient local), through the asynchronous writer's thread."""
    env = {key: value for key, value in os.environ.items()
           if key not in (PROFILES_VARIABLE, 'FASTDDS_DEFAULT_PROFILES_FILE',
                          PUBLICATION_MODE_VARIABLE)}
    env['ROS_DOMAIN_ID'] = str(100 + (os.getpid() + 50) % 100)
    writer = subprocess.Popen([sys.executable, '-c', LATCHED_CHILD, 'writer'], env=env,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert writer.stdout.readline().strip() == 'published'
        reader = subprocess.run([sys.executable, '-c', LATCHED_CHILD, 'reader'], env=env,
                                capture_output=True, text=True, timeout=60)
        assert reader.returncode == 0, reader.stderr
        assert reader.stdout.split('\n')[0] == 'received [(8232000, 2)]', reader.stdout
    finally:
        writer.communicate('done\n', timeout=30)
        writer.kill()
