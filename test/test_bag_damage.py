"""Damage inside a bag's messages is found and said, not read without a word.

MCAP: every chunk's CRC and the data section's CRC (where the writer set them: rosbags, and
so the bundled bags, sets none; ``ros2 bag record`` sets chunk CRCs, so the tests stamp
them into a copy first, as that recorder would have written them). sqlite3: quick_check.
Random bytes over the middle of a stereo image used to be read as an image: build_map said
nothing was skipped and wrote its map over the good one.
"""

from __future__ import annotations

import random
import shutil
import struct
import subprocess
from pathlib import Path

import pytest

from inhand_common.bag_source import BagSource
from inhand_common.mcap_integrity import check_mcap, check_sqlite3, stamp_crcs
from inhand_mapping.map_io import load_npz
from ros_helpers import WORKSPACE, executable_path

BAGS = WORKSPACE / 'bags'
VALIDATION = Path('/work/shared/data/validation_sessions')
CONFIG = str(WORKSPACE / 'config' / 'mapping.yaml')
MAGIC = 8


def build_map(*args, timeout=120):
    return subprocess.run([executable_path('build_map'), *map(str, args), '--quiet'],
                          capture_output=True, text=True, timeout=timeout)


def top_records(data: bytes):
    """(opcode, offset, body start, body end) of the top-level records, up to DataEnd."""
    pos = MAGIC
    while pos + 9 <= len(data):
        opcode = data[pos]
        (length,) = struct.unpack_from('<Q', data, pos + 1)
        yield opcode, pos, pos + 9, pos + 9 + length
        if opcode == 0x0F:
            return
        pos += 9 + length


def chunk_messages(data: bytes, body: int):
    """(topic, payload start, payload end, log time) of the messages of the uncompressed
    chunk whose body starts at ``body`` (file offsets)."""
    (name_length,) = struct.unpack_from('<I', data, body + 28)
    assert data[body + 32:body + 32 + name_length] == b'', 'an uncompressed chunk'
    (records_length,) = struct.unpack_from('<Q', data, body + 32 + name_length)
    pos = body + 40 + name_length
    end = pos + records_length
    channels = {}
    while pos < end:
        opcode = data[pos]
        (length,) = struct.unpack_from('<Q', data, pos + 1)
        record = pos + 9
        if opcode == 0x04:
            channel_id, = struct.unpack_from('<H', data, record)
            (topic_length,) = struct.unpack_from('<I', data, record + 4)
            channels[channel_id] = data[record + 8:record + 8 + topic_length].decode()
        elif opcode == 0x05:
            channel_id, _, log_time = struct.unpack_from('<HIQ', data, record)
            yield channels[channel_id], record + 22, record + length, log_time
        pos = record + length


def image_payload(data: bytes, topic: str = '/stereo/left/image_raw'):
    """(chunk offset, payload start, payload end) of the first message of ``topic``."""
    for opcode, offset, body, _ in top_records(data):
        if opcode == 0x06:
            for name, start, end, _ in chunk_messages(data, body):
                if name == topic:
                    return offset, start, end
    raise AssertionError(f'no {topic} in the file')


def stamped_copy(tmp_path: Path, name: str = 'cat_moving') -> tuple[Path, Path]:
    """A bundled bag copied with its CRCs written in (as ``ros2 bag record`` writes them)."""
    bag = tmp_path / name
    shutil.copytree(BAGS / name, bag)
    (mcap,) = bag.glob('*.mcap')
    stamp_crcs(mcap)
    return bag, mcap


def overwrite(path: Path, at: int, count: int = 4096, seed: int = 7) -> None:
    data = bytearray(path.read_bytes())
    data[at:at + count] = random.Random(seed).randbytes(count)
    path.write_bytes(bytes(data))


def everything(bag: Path) -> tuple[dict[tuple[str, int], bytes], str | None]:
    with BagSource(bag) as source:
        read = {(topic, stamp): raw for topic, stamp, raw in source.messages(set(source.topics))}
        return read, source.problem


@pytest.fixture(scope='module')
def clean_messages():
    read, problem = everything(BAGS / 'cat_moving')
    assert problem is None
    return read


def test_random_bytes_inside_an_image_leave_its_chunk_out_and_say_so(tmp_path, clean_messages):
    bag, mcap = stamped_copy(tmp_path)
    data = mcap.read_bytes()
    chunk, start, end = image_payload(data)
    assert end - start > 3 * 4096
    overwrite(mcap, (start + end) // 2 - 2048)
    (chunk_body,) = [body for opcode, offset, body, _ in top_records(data) if offset == chunk]
    in_chunk = {(name.lstrip('/'), stamp) for name, _, _, stamp in chunk_messages(data, chunk_body)}

    read, problem = everything(bag)

    assert problem and '\n' not in problem, problem
    assert f'1 chunk fails its CRC (at byte {chunk})' in problem, problem
    assert 'stereo/left/image_raw: 1 message at 0.00 s' in problem, problem
    assert 'stereo/right/image_raw: 1 message at 0.00 s' in problem, problem
    assert f'left out {len(in_chunk)} messages' in problem, problem
    # the damaged chunk's messages are not given, every other one is, byte for byte
    assert not set(read) & in_chunk
    assert set(read) == set(clean_messages) - in_chunk
    assert all(raw == clean_messages[key] for key, raw in read.items())
    with BagSource(bag) as source:
        assert source.topics['stereo/left/image_raw'].count == 0
        assert source.topics['polhemus/object/pose'].count == 1800


def test_build_map_keeps_a_good_map_from_a_damaged_bag_unless_forced(tmp_path):
    good, _ = stamped_copy(tmp_path / 'good')
    out = tmp_path / 'maps'
    first = build_map(good, '--config', CONFIG, '--output-dir', out, '--name', 'm')
    assert first.returncode == 0, first.stdout + first.stderr
    assert 'bag check: cat_moving.mcap: 2 of 2 chunk CRCs match; data section CRC: match' \
        in first.stdout
    before = {p.name: p.read_bytes() for p in out.glob('m*')}
    assert 'm.npz' in before and 'm.ply' in before

    bag, mcap = stamped_copy(tmp_path / 'damaged')
    _, start, end = image_payload(mcap.read_bytes(), '/stereo/right/image_raw')
    overwrite(mcap, (start + end) // 2)

    refused = build_map(bag, '--config', CONFIG, '--output-dir', out, '--name', 'm')
    assert refused.returncode == 2, refused.stdout + refused.stderr
    assert 'fails its CRC' in refused.stderr and 'stereo/right/image_raw: 1 message' in refused.stderr
    assert '--force' in refused.stderr and 'Traceback' not in refused.stderr
    assert {p.name: p.read_bytes() for p in out.glob('m*')} == before

    forced = build_map(bag, '--config', CONFIG, '--output-dir', out, '--name', 'm', '--force')
    assert forced.returncode == 1, forced.stdout + forced.stderr
    assert 'stereo/right/image_raw: 1 message' in forced.stderr
    _, metadata = load_npz(out / 'm.npz')
    assert 'fails its CRC' in metadata['extra']['truncated']

    # no map there yet: written, the damage said in one line, exit code 1
    fresh = build_map(bag, '--config', CONFIG, '--output-dir', tmp_path / 'new', '--name', 'm')
    assert fresh.returncode == 1, fresh.stdout + fresh.stderr
    (line,) = [line for line in fresh.stderr.splitlines() if 'fails its CRC' in line]
    assert 'stereo/left/image_raw: 1 message at 0.00 s' in line
    assert (tmp_path / 'new' / 'm.npz').exists()


def test_damage_outside_the_chunks_fails_the_data_section_crc(tmp_path, clean_messages):
    bag, mcap = stamped_copy(tmp_path)
    data = bytearray(mcap.read_bytes())
    # the Header record's library string: no reader needs it, only the CRC sees it
    opcode, _, body, body_end = next(top_records(bytes(data)))
    assert opcode == 0x01
    data[body_end - 1] ^= 0x20
    mcap.write_bytes(bytes(data))
    report = check_mcap(mcap)
    assert report.data_section_only and report.chunks_with_crc == 2 and not report.bad_chunks

    read, problem = everything(bag)
    assert problem and 'data section CRC does not match although all 2 chunk CRCs do' in problem
    assert '\n' not in problem
    assert read == clean_messages       # the messages themselves check out


def test_a_compressed_chunk_that_fails_is_left_out_and_named(tmp_path):
    """zstd chunks (rosbags' storage compression): the CRC is over the decompressed records;
    a chunk that no longer decompresses is named from the message index after it."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    string = store.types['std_msgs/msg/String']
    bag = tmp_path / 'zstd'
    writer = Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    rng = random.Random(1)
    with writer:
        chatter = writer.add_connection('/chatter', string.__msgtype__, typestore=store)
        for k in range(400):   # ~1.2 MB: more than one chunk
            text = ''.join(rng.choice('abcdefgh ') for _ in range(3000))
            writer.write(chatter, 1_000_000_000 + k * 10_000_000,
                         bytes(store.serialize_cdr(string(data=text), string.__msgtype__)))
    (mcap,) = bag.glob('*.mcap')
    stamp_crcs(mcap)
    data = mcap.read_bytes()
    chunks = [(offset, body, end) for opcode, offset, body, end in top_records(data)
              if opcode == 0x06]
    assert len(chunks) >= 2 and data[chunks[0][1] + 32:chunks[0][1] + 36] == b'zstd'
    clean, problem = everything(bag)
    assert problem is None and len(clean) == 400
    offset, body, end = chunks[1]
    overwrite(mcap, (body + end) // 2, 64)

    read, problem = everything(bag)
    assert problem and f'1 chunk fails its CRC (at byte {offset})' in problem, problem
    lost = len(clean) - len(read)
    assert lost > 0 and f'left out {lost} messages: chatter: {lost} messages from ' in problem
    assert all(clean[key] == raw for key, raw in read.items())


def test_sqlite3_page_damage_is_said(tmp_path):
    """sqlite3 keeps no per-message checksum; quick_check finds a damaged page structure."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    bag = tmp_path / 'as_sqlite'
    with AnyReader([BAGS / 'cat_moving'], default_typestore=store) as reader, \
            Writer(bag, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        connections = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=store)
                       for c in reader.connections}
        for connection, stamp, raw in reader.messages():
            writer.write(connections[connection.id], stamp, raw)
    (database,) = bag.glob('*.db3')
    assert not check_sqlite3(database).damaged
    with BagSource(bag) as source:
        assert source.problem is None
    # 4 KiB in the middle of the file: the images' overflow pages and their chain
    overwrite(database, database.stat().st_size // 2)
    with BagSource(bag) as source:
        problem = source.problem
        poses = sum(1 for _ in source.messages({'polhemus/index/pose'}))
    assert problem and 'fails sqlite3 quick_check' in problem and '\n' not in problem, problem
    assert poses == 1800


@pytest.mark.parametrize('bag', sorted(p.name for p in BAGS.iterdir() if p.is_dir()))
def test_bundled_bags_carry_crcs_and_raise_no_false_alarm(bag):
    """The simulator stamps its bags' CRCs (rosbags' writer sets none), the bundled ones too:
    every one matches, and rosbags' own chunk check (it reads every chunk) agrees."""
    (mcap,) = (BAGS / bag).glob('*.mcap')
    report = check_mcap(mcap)
    assert not report.damaged and report.stopped is None, report
    assert report.chunks_with_crc == report.chunks > 0 and report.data_crc == 'match'
    with BagSource(BAGS / bag) as source:
        assert source.problem is None
    read, problem = everything(BAGS / bag)
    assert problem is None and len(read) > 0


def test_random_bytes_in_the_middle_of_a_bundled_bag_are_said(tmp_path):
    """The case as a user meets it: 4 KiB of random bytes written into the middle of a
    bundled bag, as it is shipped."""
    copy = tmp_path / 'cat_moving'
    shutil.copytree(BAGS / 'cat_moving', copy)
    (mcap,) = copy.glob('*.mcap')
    overwrite(mcap, mcap.stat().st_size // 2)
    with BagSource(copy) as source:
        problem = source.problem
        images = sum(1 for _ in source.messages({'stereo/left/image_raw'}))
        poses = sum(1 for _ in source.messages({'polhemus/index/pose'}))
    assert problem and 'fails its CRC' in problem and 'stereo/left/image_raw: 1 message' in \
        problem and '\n' not in problem, problem
    assert images == 0 and poses == 1800


@pytest.mark.skipif(not VALIDATION.is_dir(), reason='no validation sessions on this machine')
def test_validation_sessions_raise_no_false_alarm(tmp_path):
    bags = sorted(p for p in VALIDATION.iterdir() if p.is_dir() and any(p.glob('*.mcap')))
    assert bags
    for bag in bags:
        (mcap,) = bag.glob('*.mcap')
        report = check_mcap(mcap)
        assert not report.damaged and report.stopped is None, (bag, report)
        with BagSource(bag) as source:
            assert source.problem is None, (bag, source.problem)
            assert source.checked == [f'{mcap.name}: {report.checked()}']
        # and with CRCs stamped in: all match, by our check and by rosbags' reading
        copy = tmp_path / bag.name
        shutil.copytree(bag, copy)
        stamp_crcs(copy / mcap.name)
        report = check_mcap(copy / mcap.name)
        assert report.chunks_with_crc == report.chunks and report.data_crc == 'match', bag
        read, problem = everything(copy)
        assert problem is None and read, (bag, problem)


def _record(opcode: int, body: bytes) -> bytes:
    return struct.pack('<BQ', opcode, len(body)) + body


def _string(text: str) -> bytes:
    return struct.pack('<I', len(text)) + text.encode()


def _mcap_with_chunk(records: bytes, compression: str, compressed: bytes, crc: int) -> bytes:
    string = _string
    chunk = struct.pack('<QQQI', 1, 2, len(records), crc) + string(compression) + \
        struct.pack('<Q', len(compressed)) + compressed
    return (b'\x89MCAP0\r\n' + _record(0x01, string('ros2') + string('test'))
            + _record(0x06, chunk) + _record(0x0F, struct.pack('<I', 0))
            + _record(0x02, struct.pack('<QQI', 0, 0, 0)) + b'\x89MCAP0\r\n')


@pytest.mark.parametrize('compression', ['lz4', 'zstd', ''])
def test_chunk_crcs_are_over_the_decompressed_records(tmp_path, compression):
    import zlib

    import lz4.frame
    try:
        from compression import zstd  # Python 3.14
    except ImportError:
        from backports import zstd
    compress = {'lz4': lz4.frame.compress, 'zstd': zstd.compress, '': bytes}[compression]
    records = _record(0x05, struct.pack('<HIQQ', 1, 0, 1, 1) + bytes(range(256)) * 40)
    path = tmp_path / 'one_chunk.mcap'
    for crc, payload, expected in (
            (zlib.crc32(records), compress(records), None),
            (zlib.crc32(records) ^ 1, compress(records), 'CRC mismatch'),
            (zlib.crc32(records), compress(records[:-1] + b'\x01'), 'CRC mismatch'),
            (0, compress(records[:-1] + b'\x01'), None)):   # no CRC set: nothing to check
        path.write_bytes(_mcap_with_chunk(records, compression, payload, crc))
        report = check_mcap(path)
        assert report.chunks == 1 and report.chunks_with_crc == (1 if crc else 0)
        assert [chunk.reason for chunk in report.bad_chunks] == ([expected] if expected else [])
    if compression:
        path.write_bytes(_mcap_with_chunk(records, compression, b'\x00' * 64, zlib.crc32(records)))
        (bad,) = check_mcap(path).bad_chunks
        assert bad.reason.startswith('does not decompress')


def test_a_broken_record_between_chunks_is_said_even_without_crcs(tmp_path, clean_messages):
    """rosbags reads the chunks through the summary and never sees the records between
    them; the walk over the data section does."""
    bag = tmp_path / 'cat_moving'
    shutil.copytree(BAGS / 'cat_moving', bag)
    (mcap,) = bag.glob('*.mcap')
    data = bytearray(mcap.read_bytes())
    index = next(offset for opcode, offset, _, _ in top_records(bytes(data)) if opcode == 0x07)
    data[index + 1:index + 9] = struct.pack('<Q', 1 << 40)
    mcap.write_bytes(bytes(data))
    read, problem = everything(bag)
    assert problem == (f'{mcap.name}: the record at byte {index} runs past the end of the file; '
                       'the data section after it is not checked')
    assert read == clean_messages
