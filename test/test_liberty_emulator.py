"""The emulated device and its motion sources, without ROS."""

import os
import time
import uuid

import numpy as np
import pytest
import serial

from inhand_common.ros_names import station_pose_topic
from inhand_common.rotations import quaternion_normalize
from polhemus_liberty.device_model import LibertyDevice
from polhemus_liberty.emulator import LibertyEmulator
from polhemus_liberty.motion import BuiltinMotion, load_plhm_text, load_pose_bag
from polhemus_liberty.protocol import (
    CTRL_U,
    AsciiStreamParser,
    BinaryStreamParser,
    OutputList,
    decode_station_map,
)
from polling import wait_until


def test_device_power_on_state_and_commands():
    device = LibertyDevice(stations=(1, 3))
    device.set_poses({1: (np.array([0.1, 0.0, 0.2]), np.array([0, 0, 0, 1.0])),
                      3: (np.array([0.2, -0.1, 0.1]), np.array([0, 0, 0, 1.0]))})
    # Power-on: ASCII, inches, output list 2,4,1; P answers one record per station at once.
    reply = device.receive(b'P', now=0.0)
    lines = AsciiStreamParser(OutputList((2, 4, 1))).feed(reply)
    assert [r.station for r in lines] == [1, 3]
    assert lines[0].position == pytest.approx((0.1 / 0.0254, 0.0, 0.2 / 0.0254), abs=1e-4)
    assert device.receive(b'F1\rU1\rO*,9,2,7,1\rR3\r', now=0.0) == b''
    assert device.state.binary and device.state.centimetres and device.state.frame_rate == 120
    assert device.receive(b'O*,99\r', now=0.0).startswith(b'\r\n*** INVALID')
    assert device.receive(b'\r', now=0.0).startswith(b'\r\n*** INVALID')
    parser = BinaryStreamParser(OutputList((9, 2, 7, 1)), accept_replies=True)
    (reply,) = parser.feed(device.receive(bytes([CTRL_U]) + b'0\r', now=0.0))
    assert reply.command == CTRL_U and decode_station_map(reply.payload) == ({1, 3}, {1, 3})
    assert device.frame(now=0.1) == b''  # not streaming yet
    device.receive(b'C\r', now=0.1)
    records = parser.feed(device.frame(now=0.2))
    assert [r.station for r in records] == [1, 3]
    assert records[0].position == pytest.approx((10.0, 0.0, 20.0), abs=1e-5)
    first = records[0].frame_count
    device.skip_frame()
    assert parser.feed(device.frame(now=0.3))[0].frame_count == first + 2
    device.receive(b'Q\r', now=0.4)
    assert parser.feed(device.frame(now=0.5))[0].frame_count == 1


def test_a_replugged_device_counts_what_it_streams_before_the_host_is_back():
    """After a USB unplug the device goes on streaming; until the host writes to the port
    again nobody reads it, and the emulator counts those frames (the soak's allowance)."""
    port = f'/tmp/liberty-replug-{os.getpid()}-{uuid.uuid4().hex[:6]}'
    with LibertyEmulator(BuiltinMotion(), port) as emulator:
        with serial.Serial(port, timeout=0.1) as host:
            host.write(b'C\r')       # continuous output
            wait_until(lambda: emulator.stats.frames_sent >= 24, 5, 'streaming')
        assert emulator.stats.frames_before_host == 0
        gone = time.monotonic()
        emulator.disconnect(0.2)
        wait_until(lambda: emulator.stats.disconnects == 1 and emulator.link.connected, 5,
                   'the port back')
        back = time.monotonic()
        time.sleep(0.25)             # no host: what the device sends now reaches nobody
        unread = emulator.stats.frames_before_host
        rate = emulator.device.state.frame_rate
        # Counted from the moment the port is back, at least 0.2 s after it went (not from
        # when the wait above saw it back: under load that can be later, and the device
        # has streamed since)
        assert 0.2 * rate <= unread <= (time.monotonic() - gone - 0.2 + 0.05) * rate, (unread, rate)
        assert emulator.device.state.continuous
        with serial.Serial(port, timeout=0.1) as host:
            host.write(b'P')          # the host is back
            wait_until(lambda: emulator.device.commands_seen[-1:] == [b'P'], 5, 'the command')
            # the device streamed on until the host's byte arrived: a frame or two more on a
            # busy machine (the count stopped when the emulator read it, before the command)
            returned = emulator.stats.frames_before_host
            sent = emulator.stats.frames_sent
            host.write(b'C\r')
            wait_until(lambda: emulator.stats.frames_sent >= sent + 24, 5, 'streaming again')
        assert unread <= returned <= unread + (time.monotonic() - back) * rate
        assert emulator.stats.frames_before_host == returned    # none once the host is back
        assert f'before the host came back {returned}' in emulator.status()


def test_hemisphere_picks_the_solution_on_its_side():
    device = LibertyDevice(stations=(1,))
    device.set_poses({1: (np.array([-0.1, 0.05, 0.2]), np.array([0, 0, 0, 1.0]))})
    device.receive(b'F1\rU1\rO*,2,7,1\rC\r', now=0.0)
    parser = BinaryStreamParser(OutputList((2, 7, 1)))
    (record,) = parser.feed(device.frame(now=0.0))
    assert record.position == pytest.approx((10.0, -5.0, -20.0), abs=1e-5)  # mirrored to +x
    device.receive(b'H*,0,0,0\r', now=0.0)  # hemisphere tracking: reported as is
    (record,) = parser.feed(device.frame(now=0.0))
    assert record.position == pytest.approx((-10.0, 5.0, 20.0), abs=1e-5)


def test_builtin_motion_is_deterministic_and_keeps_fingers_on_the_sphere():
    motion = BuiltinMotion()
    a, b = motion.sample(1.234), motion.sample(1.234)
    for station in motion.stations:
        assert np.array_equal(a[station][0], b[station][0])
    for t in np.linspace(0, 20, 50):
        poses = motion.sample(t)
        centre = poses[4][0]
        for finger in (1, 2, 3):
            assert np.linalg.norm(poses[finger][0] - centre) == pytest.approx(0.04, abs=1e-9)


def test_text_recording_skips_a_cut_off_line(tmp_path):
    path = tmp_path / 'rec.txt'
    path.write_text('1, 1.0, 2.0, 3.0, 90.0, 0.0, 0.0, 10\n'
                    '2, 4.0, 5.0, 6.0, 0.0, 0.0, 0.0, 10\n'
                    '1, 1.5, 2.0, 3.0, 90.0, 0.0, 0.0, 35\n'
                    '2, 4.0, 5.')
    motion = load_plhm_text(path)
    assert motion.stations == (1, 2) and motion.malformed_lines == 1
    assert np.allclose(motion.times, [0.0, 0.025])
    first = motion.sample(0.0)
    assert np.allclose(first[1][0], [0.01, 0.02, 0.03])
    assert np.allclose(first[1][1], [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    # Station 2 is missing from the second frame: it holds its last pose.
    assert np.allclose(motion.sample(0.03)[2][0], [0.04, 0.05, 0.06])
    assert np.allclose(motion.sample(0.03)[1][0], [0.015, 0.02, 0.03])
    with pytest.raises(ValueError, match='no lines'):
        (tmp_path / 'empty.txt').write_text('nothing here\n')
        load_plhm_text(tmp_path / 'empty.txt')


def test_bag_motion_groups_poses_by_stamp(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    PoseStamped = store.types['geometry_msgs/msg/PoseStamped']
    Header = store.types['std_msgs/msg/Header']
    Time = store.types['builtin_interfaces/msg/Time']
    Pose = store.types['geometry_msgs/msg/Pose']
    Point = store.types['geometry_msgs/msg/Point']
    Quaternion = store.types['geometry_msgs/msg/Quaternion']
    bag = tmp_path / 'bag'
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {name: writer.add_connection('/' + station_pose_topic(name), PoseStamped.__msgtype__,
                                                   typestore=store)
                       for name in ('thumb', 'object')}
        for i in range(3):
            stamp = Time(sec=100, nanosec=i * 4_166_667)
            for k, name in enumerate(('thumb', 'object')):
                q = quaternion_normalize([0.1 * i, 0, 0, 1])
                msg = PoseStamped(header=Header(stamp=stamp, frame_id='polhemus_source'),
                                  pose=Pose(position=Point(x=0.1 * i, y=float(k), z=0.0),
                                            orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])))
                writer.write(connections[name], 100 * 10**9 + i * 4_166_667,
                             store.serialize_cdr(msg, PoseStamped.__msgtype__))
    motion = load_pose_bag(bag, {'thumb': 1, 'object': 4})
    assert motion.stations == (1, 4)
    assert np.allclose(motion.times, [0.0, 0.004166667, 0.008333334])
    pose = motion.sample(0.005)
    assert np.allclose(pose[1][0], [0.1, 0.0, 0.0]) and np.allclose(pose[4][0], [0.1, 1.0, 0.0])
    with pytest.raises(ValueError, match='no topics polhemus/<name>/pose'):
        load_pose_bag(bag, {'index': 2})
