"""build_map on bags: MCAP and sqlite3, static and tracked, truncated and foreign bags."""

from __future__ import annotations

import math
import subprocess

import numpy as np
import pytest

from inhand_common.bag_source import BagSource
from inhand_common.ros_names import station_pose_topic
from inhand_common.rotations import rotate_vectors
from inhand_mapping.map_io import load_npz, read_ply
from pose_sessions import FINGERS, sphere_session, write_pose_bag
from ros_helpers import WORKSPACE, executable_path

CONFIG = str(WORKSPACE / 'config' / 'mapping.yaml')
STATIC_CONFIG = str(WORKSPACE / 'config' / 'mapping_static.yaml')


def build_map(*args, timeout=120):
    return subprocess.run([executable_path('build_map'), *map(str, args), '--quiet'],
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope='module')
def moving_bag(tmp_path_factory):
    frames, centre = sphere_session(seconds=6.0, surface_points=30, moving=True)
    return write_pose_bag(tmp_path_factory.mktemp('bags') / 'moving', frames), centre, frames


def test_tracked_map_lies_on_the_sphere(moving_bag, tmp_path):
    bag, centre, frames = moving_bag
    result = build_map(bag, '--config', CONFIG, '--output-dir', tmp_path, '--name', 'm')
    assert result.returncode == 0, result.stderr
    assert f'{3 * len(frames)} of {3 * len(frames)} fingertip positions' in result.stdout
    assert 'x real time' in result.stdout
    cells = read_ply(tmp_path / 'm.ply')
    xyz = np.stack([cells['x'], cells['y'], cells['z']], axis=1).astype(float)
    assert len(xyz) >= 20
    assert np.abs(np.linalg.norm(xyz - centre, axis=1) - 0.04).max() <= 0.005 * math.sqrt(3) / 2 + 1e-6
    grid, metadata = load_npz(tmp_path / 'm.npz')
    assert metadata['extra']['occupied_threshold'] == 0.8
    com = np.array(metadata['extra']['object_centric']['centre_of_mass'])
    assert np.linalg.norm(com - centre) < 0.01
    # The same cells expressed in object_centric: their weighted mean is the origin.
    centric = read_ply(tmp_path / 'm_object_centric.ply')
    weights = centric['intensity'].astype(float)
    mean = np.stack([centric[a] for a in 'xyz'], axis=1).astype(float).T @ weights / weights.sum()
    assert np.abs(mean).max() < 1e-6
    assert np.allclose(np.stack([centric[a] for a in 'xyz'], axis=1), xyz - com, atol=1e-6)


def test_without_registration_the_moving_object_smears(moving_bag, tmp_path):
    """Static mode on a moving object: the map is no longer the sphere. Its cells, brought
    into the object frame at the first pose (the tracked map's frame), mostly miss the
    shell the tracked map lies on."""
    bag, centre, frames = moving_bag
    tracked = build_map(bag, '--config', CONFIG, '--output-dir', tmp_path, '--name', 't')
    static = build_map(bag, '--config', STATIC_CONFIG, '--output-dir', tmp_path, '--name', 's')
    assert tracked.returncode == 0 and static.returncode == 0, static.stderr
    position, quaternion = frames[0][1]['object']
    off_shell = {}
    for name in ('t', 's'):
        cells = read_ply(tmp_path / f'{name}.ply')
        xyz = np.stack([cells['x'], cells['y'], cells['z']], axis=1).astype(float)
        if name == 's':    # tracker frame -> object frame at the first pose
            xyz = rotate_vectors(quaternion * np.array([-1.0, -1.0, -1.0, 1.0]), xyz - position)
        radial = np.abs(np.linalg.norm(xyz - centre, axis=1) - 0.04)
        off_shell[name] = float(np.mean(radial > 0.005 * math.sqrt(3) / 2 + 1e-6))
    assert off_shell['t'] == 0.0
    assert off_shell['s'] > 0.3


def test_sqlite3_bag_gives_the_same_map_as_mcap(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from inhand_mapping.pose_cdr import encode_pose_stamped
    frames, _ = sphere_session(seconds=2.0, surface_points=50, moving=True, seed=3)
    mcap = write_pose_bag(tmp_path / 'as_mcap', frames)
    store = get_typestore(Stores.ROS2_JAZZY)
    with Writer(tmp_path / 'as_sqlite', version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        connections = {n: w.add_connection('/' + station_pose_topic(n), 'geometry_msgs/msg/PoseStamped',
                                           typestore=store) for n in ('object', *FINGERS)}
        for t, frame in frames:
            ns = int(round(t * 1e9))
            for name, (p, q) in frame.items():
                w.write(connections[name], ns, encode_pose_stamped(
                    ns // 10**9, ns % 10**9, 'polhemus_source', (*p, *q)))
    for bag, name in ((mcap, 'a'), (tmp_path / 'as_sqlite', 'b')):
        result = build_map(bag, '--config', CONFIG, '--output-dir', tmp_path, '--name', name)
        assert result.returncode == 0, result.stderr
    a, _ = load_npz(tmp_path / 'a.npz')
    b, _ = load_npz(tmp_path / 'b.npz')
    assert a.counts.integrated == 3 * len(frames)
    assert np.array_equal(a.log_odds, b.log_odds)


def test_truncated_bag_is_reported_and_what_was_read_is_mapped(moving_bag, tmp_path):
    bag, _, frames = moving_bag
    (mcap,) = bag.glob('*.mcap')
    data = mcap.read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(data[:int(len(data) * 0.7)])
    result = build_map(cut, '--config', CONFIG, '--output-dir', tmp_path, '--name', 'cut')
    assert result.returncode == 1, result.stdout + result.stderr
    assert 'truncated or damaged' in result.stderr
    assert 'up to byte' in result.stderr and f'of {len(data[:int(len(data) * 0.7)])}' in result.stderr
    read = int(result.stdout.split(' messages,')[0].split()[-1])
    assert 0 < read < 4 * len(frames)
    grid, metadata = load_npz(tmp_path / 'cut.npz')
    assert grid.counts.integrated > 0 and metadata['extra']['truncated']


def test_a_bag_from_which_nothing_is_mapped_leaves_a_good_map_alone(moving_bag, tmp_path):
    """build_map on an unreadable bag used to write an empty map over a good one."""
    bag, _, _ = moving_bag
    assert build_map(bag, '--config', CONFIG, '--output-dir', tmp_path, '--name', 'm',
                     '--quiet').returncode == 0
    good = {p.name: p.read_bytes() for p in tmp_path.glob('m*')}
    # One object pose, then fingertips only: a bag that reads but maps nothing (every
    # fingertip is later than the last object pose, never extrapolated).
    session = sphere_session(seconds=0.5)[0]
    frames = [(session[0][0], {'object': session[0][1]['object']})] + \
        [(t, {k: v for k, v in frame.items() if k != 'object'}) for t, frame in session[10:]]
    cut = write_pose_bag(tmp_path / 'no_object', frames)
    result = build_map(cut, '--config', CONFIG, '--output-dir', tmp_path, '--name', 'm',
                       '--quiet')
    assert result.returncode == 1, result.stdout + result.stderr
    assert 'nothing could be mapped' in result.stderr and '--force' in result.stderr
    assert {p.name: p.read_bytes() for p in tmp_path.glob('m*')} == good
    forced = build_map(cut, '--config', CONFIG, '--output-dir', tmp_path, '--name', 'm',
                       '--quiet', '--force')
    assert forced.returncode == 0, forced.stderr
    grid, _ = load_npz(tmp_path / 'm.npz')
    assert grid.hits.sum() == 0


@pytest.mark.parametrize('content, expected', [
    (b'not a bag at all', 'cannot open as a rosbag2 bag'),
    (b'', 'cannot open as a rosbag2 bag'),
])
def test_foreign_files_are_refused(tmp_path, content, expected):
    path = tmp_path / 'thing.mcap'
    path.write_bytes(content)
    result = build_map(path, '--output-dir', tmp_path)
    assert result.returncode == 2
    assert expected in result.stderr
    assert not (tmp_path / 'thing.npz').exists()


def test_bag_without_the_driver_topics_is_refused(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    String = store.types['std_msgs/msg/String']
    with Writer(tmp_path / 'chatter', version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/chatter', String.__msgtype__, typestore=store)
        writer.write(connection, 1, store.serialize_cdr(String(data='hi'), String.__msgtype__))
    result = build_map(tmp_path / 'chatter', '--config', CONFIG, '--output-dir', tmp_path)
    assert result.returncode == 2
    assert 'no polhemus/index/pose' in result.stderr and "it has ['chatter']" in result.stderr


def test_a_bag_without_the_object_pose_says_to_map_it_static(tmp_path):
    frames, _ = sphere_session(seconds=2.0, surface_points=20, moving=False)
    bag = write_pose_bag(tmp_path / 'standing', [(t, {k: v for k, v in frame.items() if k != 'object'})
                                                 for t, frame in frames])
    result = build_map(bag, '--config', CONFIG, '--output-dir', tmp_path)
    assert result.returncode == 2
    assert 'no polhemus/object/pose in this bag' in result.stderr
    assert 'map it in static mode (--config config/mapping_static.yaml' in result.stderr
    result = build_map(bag, '--config', STATIC_CONFIG, '--output-dir', tmp_path)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / 'standing.npz').exists()


def test_bad_override_is_refused_with_its_name(moving_bag, tmp_path):
    bag, _, _ = moving_bag
    result = build_map(bag, '--set', 'sensor_sigma=-1', '--output-dir', tmp_path)
    assert result.returncode == 2
    assert "parameter 'sensor_sigma' = -1.0 is refused" in result.stderr
    result = build_map(bag, '--set', 'no_such=1', '--output-dir', tmp_path)
    assert result.returncode == 2 and "unknown parameter 'no_such'" in result.stderr
    result = build_map(bag, '--set', 'pass_tme=0.2', '--output-dir', tmp_path)
    assert result.returncode == 2 and "(did you mean 'pass_time'?)" in result.stderr


def test_a_bad_config_file_is_one_line_and_exit_code_2(moving_bag, tmp_path):
    bag, _, _ = moving_bag
    bad = tmp_path / 'bad.yaml'
    bad.write_text('/**/occupancy_node:\n  ros__parameters:\n    resolution: [0.005\n')
    for config, message in ((bad, f'{bad}: not valid YAML at line 4'),
                            (tmp_path / 'missing.yaml', 'cannot read the parameter file')):
        result = build_map(bag, '--config', config, '--output-dir', tmp_path)
        assert result.returncode == 2, result.stderr
        assert message in result.stderr and 'Traceback' not in result.stderr


def without_crcs(data: bytearray) -> bytearray:
    """An MCAP file's chunk and data section CRCs set to 0 (not set), in place."""
    import struct
    pos = 8                                        # after the magic
    while pos + 9 <= len(data):
        opcode = data[pos]
        (length,) = struct.unpack_from('<Q', data, pos + 1)
        if opcode == 0x06:                         # Chunk: start, end, size, then the CRC
            data[pos + 9 + 24:pos + 9 + 28] = bytes(4)
        elif opcode == 0x0F:                       # DataEnd: the data section's CRC
            data[pos + 9:pos + 13] = bytes(4)
            break
        pos += 9 + length
    return data


@pytest.mark.parametrize('damage', ['length', 'garbage'])
def test_a_damaged_bag_loses_only_the_damaged_part(tmp_path, damage):
    """A bag without CRCs (the bundled bag with its CRCs cleared, as another writer leaves
    them; with them the damaged chunk is left out whole, test_bag_damage.py): a message
    record whose length field is overwritten (rosbags: OverflowError) or 200 bytes of
    garbage over a record (rosbags ends the chunk early without a word) lost every message
    after it. Reading record by record resyncs at the next message that parses; one line
    says what was skipped."""
    import shutil
    import struct
    source = WORKSPACE / 'bags' / 'cat_static'
    (mcap,) = source.glob('*.mcap')
    data = without_crcs(bytearray(mcap.read_bytes()))
    with BagSource(source) as clean:
        total = sum(1 for _ in clean.messages(set(clean.topics)))
    # message records of the chunk: opcode 5, a sane length, another message after it
    starts = [p for p in range(len(data) - 9) if data[p] == 5
              and 22 <= struct.unpack_from('<Q', data, p + 1)[0] < 10_000
              and data[p + 9 + struct.unpack_from('<Q', data, p + 1)[0]] == 5]
    at = starts[len(starts) // 3]
    if damage == 'length':
        data[at + 1:at + 9] = b'\xff' * 8
    else:
        data[at:at + 200] = bytes(range(200))
    bag = tmp_path / 'damaged'
    shutil.copytree(source, bag)
    (bag / mcap.name).write_bytes(bytes(data))
    with BagSource(bag) as damaged:
        read = sum(1 for _ in damaged.messages(set(damaged.topics)))
        problem = damaged.problem
    assert total - 3 <= read < total, (read, total)
    assert problem and 'damaged place(s)' in problem and '\n' not in problem, problem
    result = build_map(bag, '--config', STATIC_CONFIG, '--output-dir', tmp_path, '--name', 'm')
    assert result.returncode == 1, result.stdout + result.stderr
    assert 'Traceback' not in result.stderr and 'damaged place(s)' in result.stderr
    grid, _ = load_npz(tmp_path / 'm.npz')
    assert grid.counts.integrated >= 3 * 1790      # of the bag's 3 x 1,800 fingertips
