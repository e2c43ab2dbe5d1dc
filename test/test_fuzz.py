"""Fuzzing of everything that reads outside input, with hypothesis.

Targets: the Liberty stream parser, the PoseStamped CDR codec, the PointCloud2 decoders
(``points_of_layout`` and ``decode_point_cloud2``), the map file readers (NPZ and PLY) and
the parameter checks of every node. Each property says what a correct reader does with any
input: refuse it with a ValueError (ParameterError for parameters), or give back exactly
what an independent reference reads from the same bytes (rosbags for PoseStamped, rclpy
for PointCloud2, plyfile for PLY, struct for point fields, the file's own arrays for NPZ).
Any other exception is a crash, any other value a wrong pose.

The test command runs each property on a bounded, derandomized set of inputs
(``INHAND_FUZZ_EXAMPLES`` unset: 150 each, the same every run). ``benchmark.sh fuzz``
runs them with random seeds for a million inputs or more and counts them (``INPUTS``).
"""

from __future__ import annotations

import atexit
import collections
import io
import json
import math
import os
import random
import shutil
import struct
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from plyfile import PlyData
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import PointCloud2, PointField

from inhand_common.parameters import ParameterError, validate
from inhand_common.point_cloud import decode_point_cloud2, points_of_layout, serialize_point_cloud2
from inhand_mapping.map_io import load_npz, read_ply, save_npz, save_ply
from inhand_mapping.mapping_config import (
    OCCUPANCY_PARAMETERS,
    REGISTRATION_PARAMETERS,
    OccupancyConfig,
    RegistrationConfig,
)
from inhand_mapping.occupancy import GridSpec, IntegrationCounts, OccupancyGrid
from inhand_mapping.pose_cdr import decode_pose_stamped, decode_pose_stamped_many, encode_pose_stamped
from inhand_stereo.disparity import DISPARITY_PARAMETERS, DisparityConfig
from inhand_stereo.stereo_config import STEREO_PARAMETERS, StereoConfig
from inhand_view.view_config import VIEW_PARAMETERS, ViewConfig
from polhemus_liberty.driver_config import DRIVER_PARAMETERS, DriverConfig
from polhemus_liberty.protocol import BinaryStreamParser, StationRecord
from test_liberty_fuzz import LAYOUT, Maker, conserved, key_of

EXAMPLES = int(os.environ.get('INHAND_FUZZ_EXAMPLES', '150'))
fuzz = settings(max_examples=EXAMPLES, deadline=None, database=None,
                derandomize='INHAND_FUZZ_EXAMPLES' not in os.environ,
                suppress_health_check=list(HealthCheck))
INPUTS: collections.Counter[str] = collections.Counter()   # inputs tried per target
STORE = get_typestore(Stores.ROS2_JAZZY)
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
SCRATCH = Path(tempfile.mkdtemp(prefix='inhand-fuzz-'))
atexit.register(shutil.rmtree, SCRATCH, ignore_errors=True)   # the run's files, not kept


def mutate(data: bytes, edits, cut, tail) -> bytes:
    """``data`` with bytes overwritten (``edits``: (position fraction, byte)), cut to a
    fraction of its length (``cut`` None: kept whole) and ``tail`` appended."""
    out = bytearray(data)
    for where, value in edits:
        if out:
            out[min(int(where * len(out)), len(out) - 1)] = value
    if cut is not None:
        out = out[:int(cut * len(out))]
    return bytes(out) + tail


edits = st.lists(st.tuples(st.floats(0, 1), st.integers(0, 255)), max_size=6)
cuts = st.none() | st.floats(0, 1)
tails = st.binary(max_size=8)


def same_bits(a, b) -> bool:
    """Floats equal bit for bit (NaN payloads included)."""
    return struct.pack(f'<{len(a)}d', *a) == struct.pack(f'<{len(b)}d', *b)


def same_points(a, b) -> bool:
    """Same fields holding the same bytes (padding between fields is not compared: a
    byte-swapped copy leaves it uninitialised)."""
    return a.dtype.names == b.dtype.names and len(a) == len(b) and \
        all(a[name].tobytes() == b[name].tobytes() for name in a.dtype.names)


# ----------------------------------------------------------------------------- Liberty

def _liberty_stream(seed, garbage, clean):
    rng = random.Random(seed)
    maker = Maker(rng)
    stream, keys = bytearray(), []
    for chunk in garbage:
        if clean:  # no sync pattern: every record must come out, nothing else
            chunk = chunk.replace(b'LY', b'L.').rstrip(b'L')
        stream += chunk
        data, key = maker.record()
        stream += data
        keys.append(key)
    return bytes(stream), keys


def _feed(stream, sizes):
    parser = BinaryStreamParser(LAYOUT)
    out, i, k = [], 0, 0
    while i < len(stream):
        n = sizes[k % len(sizes)] if sizes else len(stream)
        out += parser.feed(stream[i:i + n])
        i, k = i + n, k + 1
    return parser, out


@fuzz
@given(st.integers(0, 2**32), st.lists(st.binary(max_size=120), min_size=1, max_size=12),
       st.lists(st.integers(1, 97), max_size=8))
def test_liberty_records_between_clean_garbage_all_come_out_exactly(seed, garbage, sizes):
    INPUTS['liberty (garbage without a sync)'] += 1
    stream, keys = _liberty_stream(seed, garbage, clean=True)
    parser, out = _feed(stream, sizes)
    assert [key_of(r) for r in out] == keys
    assert conserved(parser, out, 46)


@fuzz
@given(st.integers(0, 2**32), st.lists(st.binary(max_size=120), min_size=1, max_size=12),
       st.lists(st.integers(1, 97), min_size=1, max_size=8))
def test_liberty_any_garbage_parses_the_same_in_any_chunks(seed, garbage, sizes):
    INPUTS['liberty (any garbage)'] += 1
    stream, keys = _liberty_stream(seed, garbage, clean=False)
    whole_parser, whole = _feed(stream, [])
    parser, chunked = _feed(stream, sizes)
    assert [key_of(r) for r in chunked] == [key_of(r) for r in whole]
    assert conserved(parser, chunked, 46)
    assert all(1 <= r.station <= 16 for r in chunked if isinstance(r, StationRecord))
    # The record after each garbage run may be swallowed by a header the garbage opened;
    # the one before the next garbage never is.
    assert keys[-1] in [key_of(r) for r in chunked]


# ----------------------------------------------------------------------------- PoseStamped

stamps = st.tuples(st.integers(-2**31, 2**31 - 1), st.integers(0, 2**32 - 1))
frame_ids = st.text(max_size=40).filter(lambda s: '\x00' not in s)
poses = st.tuples(*[st.floats(allow_nan=True, allow_infinity=True)] * 7)


def _rosbags_pose(sec, nanosec, frame_id, pose):
    types = STORE.types
    header = types['std_msgs/msg/Header'](
        stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec), frame_id=frame_id)
    body = types['geometry_msgs/msg/Pose'](
        position=types['geometry_msgs/msg/Point'](x=pose[0], y=pose[1], z=pose[2]),
        orientation=types['geometry_msgs/msg/Quaternion'](x=pose[3], y=pose[4], z=pose[5],
                                                          w=pose[6]))
    return types[POSE_STAMPED](header=header, pose=body)


def _fields_of_rosbags(message):
    p, o = message.pose.position, message.pose.orientation
    return (message.header.stamp.sec, message.header.stamp.nanosec, message.header.frame_id,
            (p.x, p.y, p.z, o.x, o.y, o.z, o.w))


def _encoded(sec, nanosec, frame_id, pose, little_endian):
    if little_endian:
        return encode_pose_stamped(sec, nanosec, frame_id, pose)
    return bytes(STORE.serialize_cdr(_rosbags_pose(sec, nanosec, frame_id, pose), POSE_STAMPED,
                                     little_endian=False))


def _same_pose(a, b) -> bool:
    return a[:3] == b[:3] and same_bits(a[3], b[3])


@fuzz
@given(stamps, frame_ids, poses, st.booleans(), st.integers(1, 5))
def test_pose_stamped_round_trips_bit_for_bit(stamp, frame_id, pose, little_endian, copies):
    INPUTS['PoseStamped round trip'] += 1
    sec, nanosec = stamp
    data = _encoded(sec, nanosec, frame_id, pose, little_endian)
    assert _same_pose(decode_pose_stamped(data), (sec, nanosec, frame_id, pose))
    assert _same_pose(_fields_of_rosbags(STORE.deserialize_cdr(data, POSE_STAMPED)),
                      (sec, nanosec, frame_id, pose))
    stamps_ns, names, values = decode_pose_stamped_many([data] * copies)
    assert list(stamps_ns) == [sec * 1_000_000_000 + nanosec] * copies
    assert names == [frame_id] * copies
    assert all(same_bits(row, pose) for row in values)


def _decode_or_none(data):
    try:
        return decode_pose_stamped(data)
    except ValueError:
        return None


@fuzz
@given(stamps, frame_ids, poses, st.booleans(), edits, cuts, tails,
       st.lists(st.tuples(edits, st.booleans()), max_size=4))
def test_damaged_pose_stamped_is_refused_or_read_as_rosbags_reads_it(
        stamp, frame_id, pose, little_endian, damage, cut, tail, others):
    INPUTS['PoseStamped damaged'] += 1
    base = _encoded(*stamp, frame_id, pose, little_endian)
    data = mutate(base, damage, cut, tail)
    ours = _decode_or_none(data)
    if ours is not None:
        try:
            theirs = _fields_of_rosbags(STORE.deserialize_cdr(data, POSE_STAMPED))
        except Exception:
            theirs = None
        # Accepted bytes hold the values where the layout puts them ...
        order = '<' if data[1] == 1 else '>'
        sec, nanosec, length = struct.unpack_from(order + 'iII', data, 4)
        at = 4 + ((12 + length + 7) & ~7)
        assert len(data) - (at + 56) in range(4)
        name = data[16:16 + length].split(b'\x00')[0].decode()
        assert _same_pose(ours, (sec, nanosec, name, struct.unpack_from(order + '7d', data, at)))
        assert _same_pose(decode_pose_stamped(encode_pose_stamped(*ours)), ours)
        # ... and the reference reads the same values (non-UTF-8 names aside, which only
        # we refuse).
        if theirs is not None:   # rosbags keeps what follows a NUL inside the name
            assert _same_pose((*theirs[:2], theirs[2].split('\x00')[0], theirs[3]), ours)
    # A batch decodes as its messages do one by one: all, or a ValueError.
    batch = [data] + [mutate(base, e, None, tail) if keep else data for e, keep in others]
    singles = [_decode_or_none(m) for m in batch]
    try:
        stamps_ns, names, values = decode_pose_stamped_many(batch)
    except ValueError:
        assert any(s is None for s in singles)
        return
    assert all(s is not None for s in singles)
    for single, ns, name, row in zip(singles, stamps_ns, names, values):
        assert ns == single[0] * 1_000_000_000 + single[1]
        assert name == single[2]
        assert same_bits(row, single[3])


# ----------------------------------------------------------------------------- PointCloud2

DATATYPES = {1: 'b', 2: 'B', 3: 'h', 4: 'H', 5: 'i', 6: 'I', 7: 'f', 8: 'd'}
field_names = st.sampled_from(['x', 'y', 'z', 'intensity', 'hits', 'rgb']) | st.text(max_size=6)
layout_fields = st.lists(st.tuples(field_names, st.integers(0, 40), st.integers(0, 10),
                                   st.integers(0, 3)), max_size=5)


def _layout_problem(fields, point_step, row_step, width, height, data_size) -> bool:
    """Whether the layout is one a reader must refuse (computed apart from the reader)."""
    names = [name for name, *_ in fields]
    if point_step >= 2**31:
        return True
    for name, offset, datatype, count in fields:
        if datatype not in DATATYPES or count < 1 or not name or names.count(name) > 1:
            return True
        if offset + struct.calcsize(DATATYPES[datatype]) * count > point_step:
            return True
    if width * height == 0:
        return False
    if point_step == 0 or (height > 1 and row_step < width * point_step):
        return True
    step = row_step if height > 1 else width * point_step
    return data_size < step * (height - 1) + width * point_step


@fuzz
@given(layout_fields, st.integers(0, 48), st.integers(0, 300), st.integers(0, 6),
       st.integers(0, 4), st.booleans(), st.binary(max_size=700))
def test_point_cloud_layouts_read_each_field_where_it_lies(fields, point_step, row_step, width,
                                                          height, big, data):
    INPUTS['PointCloud2 layout'] += 1
    refuse = _layout_problem(fields, point_step, row_step, width, height, len(data))
    try:
        points = points_of_layout(fields, point_step, row_step, width, height, big, data)
    except ValueError:
        assert refuse
        return
    assert not refuse
    assert len(points) == width * height
    order = '>' if big else '<'
    step = row_step if height > 1 else width * point_step
    for index in range(len(points)):
        start = (index // width) * step + (index % width) * point_step if width else 0
        for name, offset, datatype, count in fields:
            code = DATATYPES[datatype]
            expected = data[start + offset:start + offset + struct.calcsize(code) * count]
            value = np.asarray(points[name][index])
            assert value.dtype.isnative
            assert value.astype(value.dtype.newbyteorder(order)).tobytes() == expected


def _cloud_message(fields, width, height, pad, big, data, frame_id, stamp):
    message = PointCloud2()
    message.header.frame_id = frame_id
    message.header.stamp.sec, message.header.stamp.nanosec = stamp[0], stamp[1] % 10**9
    message.height, message.width = height, width
    step = max((offset + struct.calcsize(DATATYPES[datatype]) for _, offset, datatype in fields),
               default=1)
    message.fields = [PointField(name=name, offset=offset, datatype=datatype, count=1)
                      for name, offset, datatype in fields]
    message.is_bigendian = big
    message.point_step = step
    message.row_step = step * width + pad
    size = message.row_step * height
    message.data = (data * (size // max(len(data), 1) + 1))[:size] if data else bytes(size)
    message.is_dense = True
    return message


good_fields = st.lists(st.tuples(st.sampled_from(['x', 'y', 'z', 'i', 'hits', 't']),
                                 st.integers(0, 24), st.sampled_from(sorted(DATATYPES))),
                       max_size=4, unique_by=lambda f: f[0])


@fuzz
@given(good_fields, st.integers(0, 5), st.integers(0, 3), st.integers(0, 8), st.booleans(),
       st.binary(min_size=1, max_size=64), frame_ids, stamps, edits, cuts, tails)
def test_point_cloud2_cdr_reads_as_rclpy_does(fields, width, height, pad, big, data, frame_id,
                                             stamp, damage, cut, tail):
    INPUTS['PointCloud2 CDR'] += 1
    message = _cloud_message(fields, width, height, pad, big, data, frame_id, stamp)
    raw = mutate(serialize_message(message), damage, cut, tail)
    try:
        reference = deserialize_message(raw, PointCloud2)
    except Exception:
        reference = None
    try:
        ours = decode_point_cloud2(raw)
    except ValueError as error:
        if reference is not None:   # only where we are stricter than rclpy: the layout, a
            # name that is not UTF-8 or not NUL-terminated, an is_bigendian byte of 2..255, an
            # encapsulation other than plain CDR (rclpy reads any as plain CDR)
            layout = [(f.name, f.offset, f.datatype, f.count) for f in reference.fields]
            assert _layout_problem(layout, reference.point_step, reference.row_step,
                                   reference.width, reference.height, len(reference.data)) \
                or any(word in str(error) for word in ('NUL', 'UTF-8', 'is_bigendian',
                                                    'encapsulation')), str(error)
        return
    assert reference is not None, 'accepted what rclpy cannot read'
    assert ours.frame_id == reference.header.frame_id
    assert (ours.sec, ours.nanosec) == (reference.header.stamp.sec, reference.header.stamp.nanosec)
    layout = [(f.name, f.offset, f.datatype, f.count) for f in reference.fields]
    expected = points_of_layout(layout, reference.point_step, reference.row_step,
                                reference.width, reference.height, reference.is_bigendian,
                                bytes(reference.data))
    assert same_points(ours.points, expected)


@fuzz
@given(st.lists(st.tuples(st.floats(width=32), st.floats(width=32), st.integers(0, 2**32 - 1)),
                max_size=20), frame_ids, stamps)
def test_point_cloud2_we_write_reads_back_exactly(rows, frame_id, stamp):
    INPUTS['PointCloud2 round trip'] += 1
    points = np.array([(x, y, h) for x, y, h in rows],
                      dtype=[('x', '<f4'), ('y', '<f4'), ('hits', '<u4')])
    raw = serialize_point_cloud2(points, frame_id, *stamp)
    cloud = decode_point_cloud2(raw)
    assert same_points(cloud.points, points)
    assert (cloud.frame_id, cloud.sec, cloud.nanosec) == (frame_id, *stamp)
    reference = deserialize_message(raw, PointCloud2)
    assert bytes(reference.data) == points.tobytes() and reference.header.frame_id == frame_id


# ----------------------------------------------------------------------------- map files

def _base_map():
    grid = OccupancyGrid(GridSpec(0.02, 0.005))
    rng = np.random.default_rng(3)
    grid.integrate(rng.uniform(-0.01, 0.01, (40, 3)), times=np.linspace(0, 2, 40))
    path = SCRATCH / 'base.npz'
    save_npz(grid, path)
    with np.load(path) as data:
        arrays = {name: data[name] for name in data.files}
    return path.read_bytes(), arrays, json.loads(bytes(arrays['metadata']).decode())


BASE_NPZ, BASE_ARRAYS, BASE_METADATA = _base_map()
json_values = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                           lambda inner: st.lists(inner, max_size=4)
                           | st.dictionaries(st.text(max_size=8), inner, max_size=4),
                           max_leaves=8)
array_dtypes = st.sampled_from(['<f8', '<f4', '<u4', '<i8', '|b1', '|u1', '<c16'])


def _check_loaded(grid, metadata, arrays):
    spec = grid.spec
    assert (spec.size, spec.resolution) == (float(metadata['size']), float(metadata['resolution']))
    assert grid.log_odds.shape == spec.shape
    assert np.array_equal(grid.log_odds, arrays['log_odds'])
    assert np.array_equal(grid.hits, arrays['hits'])
    assert np.array_equal(grid.first_touch, arrays['first_touch'], equal_nan=True)
    assert vars(grid.counts) == vars(IntegrationCounts(**metadata['counts']))  # missing: 0


@fuzz
@given(st.dictionaries(st.sampled_from(sorted(BASE_METADATA)) | st.text(max_size=10), json_values,
                       max_size=3),
       st.lists(st.sampled_from(sorted(BASE_METADATA)), max_size=2),
       st.lists(st.tuples(st.sampled_from(['log_odds', 'hits', 'first_touch']), array_dtypes,
                          st.lists(st.integers(0, 5), max_size=4)), max_size=2),
       st.none() | json_values)
@example({'sigma': 2.164135165258479e-285}, [], [], None)   # the million-input run: sigma^2 = 0
def test_map_npz_with_damaged_metadata_or_arrays_is_refused_or_read_as_written(
        changed, dropped, replaced, whole_metadata):
    INPUTS['map NPZ contents'] += 1
    metadata = {**BASE_METADATA, **changed}
    for key in dropped:
        metadata.pop(key, None)
    if whole_metadata is not None:
        metadata = whole_metadata
    arrays = dict(BASE_ARRAYS)
    for name, dtype, shape in replaced:
        arrays[name] = np.arange(math.prod(shape)).reshape(shape).astype(dtype)
    arrays['metadata'] = np.frombuffer(json.dumps(metadata).encode(), dtype=np.uint8)
    stream = io.BytesIO()
    np.savez(stream, **arrays)
    stream.seek(0)
    try:
        grid, _ = load_npz(stream)
    except ValueError:
        return
    _check_loaded(grid, metadata, arrays)


@fuzz
@given(edits, cuts, tails)
@example([(0.9609375, 1)], None, b'')   # the million-input run: an "encrypted" flag bit
def test_map_npz_with_damaged_bytes_is_refused_or_read_whole(damage, cut, tail):
    INPUTS['map NPZ bytes'] += 1
    stream = io.BytesIO(mutate(BASE_NPZ, damage, cut, tail))
    try:
        grid, _ = load_npz(stream)
    except ValueError:
        return
    _check_loaded(grid, BASE_METADATA, BASE_ARRAYS)   # the zip's CRCs guard the contents


def _base_ply():
    rng = np.random.default_rng(4)
    path = SCRATCH / 'base.ply'
    save_ply(path, rng.uniform(-0.1, 0.1, (6, 3)), rng.uniform(0, 1, 6), rng.integers(0, 9, 6),
             rng.uniform(0, 5, 6), colours=rng.integers(0, 256, (6, 3)), textured=[1, 0] * 3)
    return path.read_bytes()


BASE_PLY = _base_ply()
header_lines = st.sampled_from([
    b'comment x', b'format', b'format ascii 1.0', b'element vertex', b'element vertex -3',
    b'element vertex 99999999999999999999', b'element face 2', b'property float', b'property',
    b'property list uchar int vertex_indices', b'property float x', b'property uchar red',
    b'property double q', b'end_header', b'', b'obj_info y']) | st.binary(max_size=20)


def _header_end(data: bytes) -> int:
    """Offset of the PLY header's end_header line (its first word) in ``data``."""
    offset = 0
    for line in data.split(b'\n'):
        if line.split()[:1] == [b'end_header']:
            return offset + line.index(b'end_header')
        offset += len(line) + 1
    raise AssertionError('read_ply read a header without end_header')


@fuzz
@given(edits, cuts, tails, st.lists(st.tuples(st.floats(0, 1), header_lines), max_size=3))
# Found by the million-input runs: a control character inside a property name (we read
# it, plyfile splits there); a property before the element, and end_header early; a
# newline damaged into '!' before an inserted end_header (the test's own header cut).
@example([(0.671875, 28)], None, b'', [])
@example([], None, b'', [(0.0, b'property uchar red'), (0.5, b'end_header')])
@example([(0.5652588786739113, 33)], None, b'', [(0.75, b'end_header')])
def test_map_ply_is_refused_or_read_as_plyfile_reads_it(damage, cut, tail, inserted):
    INPUTS['map PLY'] += 1
    header_end = BASE_PLY.index(b'end_header\n')
    lines = BASE_PLY[:header_end].split(b'\n')
    for where, line in inserted:
        lines.insert(1 + int(where * (len(lines) - 1)), line.replace(b'\n', b' '))
    data = mutate(b'\n'.join(lines) + BASE_PLY[header_end:], damage, cut, tail)
    path = SCRATCH / 'fuzz.ply'
    path.write_bytes(data)
    try:
        ours = read_ply(path)
    except ValueError:
        return
    # What an independent reader sees, given the header without the blank and obj_info
    # lines we skip anywhere (plyfile: no blank lines, obj_info only before elements).
    # The header ends at the first line whose first word is end_header ("property uchar
    # red!end_header", a newline damaged into '!', is a property: the million-input run).
    end = _header_end(data)
    header = [line for line in data[:end].split(b'\n')
              if line.split() and line.split()[0] != b'obj_info']
    path.write_bytes(b'\n'.join(header) + b'\n' + data[end:])
    try:
        reference = PlyData.read(str(path))['vertex'].data
    except UnicodeDecodeError:   # plyfile wants ASCII even in comments; we skip them
        assert all(line.isascii() or line.split()[0] == b'comment'
                   for line in header)
        return
    assert ours.dtype.names == reference.dtype.names
    assert ours.tobytes() == np.asarray(reference, dtype=ours.dtype).tobytes()


# ----------------------------------------------------------------------------- parameters

def _stereo(values):
    return StereoConfig.from_parameters(values)


NODES = {
    'driver': (DRIVER_PARAMETERS, DriverConfig.from_parameters),
    'registration': (REGISTRATION_PARAMETERS, RegistrationConfig.from_parameters),
    'occupancy': (OCCUPANCY_PARAMETERS, OccupancyConfig.from_parameters),
    'stereo': (STEREO_PARAMETERS, _stereo),
    'disparity': (DISPARITY_PARAMETERS, DisparityConfig.from_parameters),
    'view': (VIEW_PARAMETERS, ViewConfig.from_parameters),
}
scalars = (st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12)
           | st.integers(-2**70, 2**70))


def _near(spec):
    """Values at and just beyond a parameter's bounds and choices."""
    out = [spec.default]
    for bound in (spec.minimum, spec.maximum):
        if bound is not None:
            out += [bound, bound - 1, bound + 1, bound * 1.000001, type(spec.default)(0)
                    if not spec.is_list else [bound]]
    out += list(spec.choices or ())
    return st.sampled_from(out)


@st.composite
def parameter_sets(draw):
    name = draw(st.sampled_from(sorted(NODES)))
    specs, _ = NODES[name]
    values = {}
    for spec in draw(st.lists(st.sampled_from(specs), max_size=4)):
        values[spec.name] = draw(_near(spec) | scalars | st.lists(scalars, max_size=4)
                                 | st.lists(_near(spec), max_size=4))
    if draw(st.booleans()):
        values[draw(st.text(max_size=12))] = draw(scalars)
    return name, values


@fuzz
@given(parameter_sets())
def test_parameters_are_refused_by_name_or_make_a_configuration(case):
    INPUTS['parameters'] += 1
    node, values = case
    specs, build = NODES[node]
    try:
        checked = validate(specs, values)
        build(checked)
    except ParameterError as error:
        assert error.problems
        assert all("'" in problem for problem in error.problems)   # each names what it refuses
        return
    for spec in specs:
        assert spec.problem(checked[spec.name]) is None


@pytest.mark.parametrize('value', [2**70, -2**70, 10**400], ids=['2^70', '-2^70', '10^400'])
def test_an_integer_too_large_for_a_float_parameter_is_refused_by_name(value):
    spec = next(s for s in OCCUPANCY_PARAMETERS if isinstance(s.default, float))
    with pytest.raises(ParameterError, match=spec.name):
        validate(OCCUPANCY_PARAMETERS, {spec.name: value})
