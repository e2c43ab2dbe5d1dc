"""Fuzzed Liberty streams: the parsers never raise and find the next good record.

Deterministic: every case uses random.Random(seed) with fixed seeds. Good records are
packed by hand with struct (not by the codec under test) and identified by their content,
so "recovered" means byte-exact values came back in order.
"""

import random
import struct

import pytest

from polhemus_liberty.protocol import AsciiStreamParser, BinaryStreamParser, OutputList, Reply, StationRecord

CRLF = b'\r\n'
LAYOUT = OutputList((8, 9, 2, 7, 1))    # 46-byte records ending in CR LF
LAYOUT_NO_CRLF = OutputList((9, 2, 4))  # 8 + 4 + 12 + 12 = 36 bytes, no CR LF to check
SIZES = {LAYOUT: 46, LAYOUT_NO_CRLF: 36}


def f32(v):
    return struct.unpack('<f', struct.pack('<f', v))[0]


class Maker:
    """Packs good records by hand and remembers what each one must decode to."""

    def __init__(self, rng, layout=LAYOUT, clean=True):
        self.rng = rng
        self.layout = layout
        self.clean = clean
        self.frame = 0

    def _one(self, station):
        rng = self.rng
        self.frame += 1
        frame = self.frame
        pos = tuple(f32(rng.uniform(-200.0, 200.0)) for _ in range(3))
        if self.layout is LAYOUT:
            ts = rng.getrandbits(32)
            quat = tuple(f32(rng.uniform(-1.0, 1.0)) for _ in range(4))
            data = (b'LY' + bytes([station]) + b'C \x00' + struct.pack('<H', 38)
                    + struct.pack('<II', ts, frame) + struct.pack('<3f', *pos)
                    + struct.pack('<4f', *quat) + CRLF)
            key = (station, ts, frame, pos, quat)
        else:
            euler = tuple(f32(rng.uniform(-180.0, 180.0)) for _ in range(3))
            data = (b'LY' + bytes([station]) + b'C \x00' + struct.pack('<H', 28)
                    + struct.pack('<I', frame) + struct.pack('<3f', *pos)
                    + struct.pack('<3f', *euler))
            key = (station, frame, pos, euler)
        return data, key

    def record(self, station=None):
        """(bytes, key). Clean records hold 'LY' only at the start and CR LF only at the end."""
        station = station if station is not None else self.rng.randint(1, 16)
        while True:
            data, key = self._one(station)
            if not self.clean:
                return data, key
            if b'LY' in data[1:]:
                continue
            if self.layout is LAYOUT and b'\r\n' in data[:-2]:
                continue
            return data, key


def key_of(record):
    if record.quaternion_wxyz is not None:
        return (record.station, record.timestamp_ms, record.frame_count, record.position,
                record.quaternion_wxyz)
    return (record.station, record.frame_count, record.position, record.euler_deg)


def feed_in_chunks(parser, stream, rng, max_chunk=97):
    out = []
    i = 0
    while i < len(stream):
        n = rng.randint(1, max_chunk)
        out += parser.feed(stream[i:i + n])
        i += n
    return out


def clean_garbage(rng, length, forbid=b''):
    """Random bytes without b'LY' (and without any byte in ``forbid``)."""
    out = bytearray()
    while len(out) < length:
        b = rng.randrange(256)
        if b in forbid or (out and out[-1] == 0x4C and b == 0x59):
            continue
        out.append(b)
    return bytes(out)


def conserved(parser, out, record_size):
    """Every byte fed is in a record, a reply, the drop count, or still pending."""
    used = sum(record_size for r in out if isinstance(r, StationRecord))
    used += sum(8 + len(r.payload) for r in out if isinstance(r, Reply))
    return parser.stats.bytes_dropped + used + parser.pending == parser.stats.bytes_in


# ----------------------------------------------------------------------------- binary

@pytest.mark.parametrize('layout', [LAYOUT, LAYOUT_NO_CRLF], ids=['crlf', 'no_crlf'])
@pytest.mark.parametrize('seed', range(25))
def test_clean_garbage_between_records(seed, layout):
    rng = random.Random(seed)
    maker = Maker(rng, layout)
    stream = bytearray()
    expected = []
    garbage_total = 0
    for _ in range(60):
        if rng.random() < 0.6:
            garbage = clean_garbage(rng, rng.randint(1, 80))
            stream += garbage
            garbage_total += len(garbage)
        data, key = maker.record()
        stream += data
        expected.append(key)
    parser = BinaryStreamParser(layout)
    out = feed_in_chunks(parser, bytes(stream), rng)
    assert [key_of(r) for r in out] == expected
    stats = parser.stats
    assert stats.records == len(expected)
    assert stats.bytes_in == len(stream)
    assert stats.bytes_dropped == garbage_total
    assert stats.resyncs > 0
    assert parser.pending == 0
    assert conserved(parser, out, SIZES[layout])


def test_garbage_ending_in_L_before_a_record():
    maker = Maker(random.Random(1))
    data, key = maker.record()
    for garbage in (b'L', b'LL', b'xL', b'YL', b'\x00L\x00L'):
        parser = BinaryStreamParser(LAYOUT)
        out = parser.feed(garbage) + parser.feed(data)
        assert [key_of(r) for r in out] == [key], garbage
        assert parser.stats.bytes_dropped == len(garbage)


def _adversarial_garbage(rng, maker, size):
    """Garbage full of sync bytes, plausible headers, partial and whole records."""
    parts = []
    length = 0
    while length < size:
        kind = rng.randrange(9)
        if kind == 0:
            part = b'LY'
        elif kind == 1:  # plausible data header with the right size field
            part = b'LY' + bytes([rng.randint(1, 16)]) + rng.choice([b'C', b'P']) + b' \x00' \
                + struct.pack('<H', 38)
        elif kind == 2:  # header with a wrong size, station or command
            part = b'LY' + bytes([rng.randrange(256), rng.randrange(256)]) + b' \x00' \
                + struct.pack('<H', rng.randrange(65536))
        elif kind == 3:  # reply-looking header (Ctrl-U) with a random size
            part = b'LY\x00\x15 \x00' + struct.pack('<H', rng.randrange(0, 64))
        elif kind == 4:  # truncated real record
            data, _ = maker.record()
            part = data[:rng.randint(1, len(data) - 1)]
        elif kind == 5:
            part = CRLF
        elif kind == 6:  # plausible header followed by random bytes and CR LF
            part = b'LY\x01C \x00' + struct.pack('<H', 38) + bytes(
                rng.randrange(256) for _ in range(rng.randint(0, 40))) + CRLF
        else:
            part = bytes(rng.randrange(256) for _ in range(rng.randint(1, 20)))
        parts.append(part)
        length += len(part)
    return b''.join(parts)


@pytest.mark.parametrize('accept_replies, gap', [(False, 46), (True, 1032 + 46)])
@pytest.mark.parametrize('seed', range(15))
def test_adversarial_garbage_then_clean_gap(seed, accept_replies, gap):
    rng = random.Random(1000 + seed)
    maker = Maker(rng)
    stream = bytearray()
    markers = []
    for _ in range(25):
        stream += _adversarial_garbage(rng, maker, rng.randint(10, 300))
        # A clean gap at least as long as the longest window a header can open
        # (no sync, no CR LF), then a good record that must come out.
        stream += clean_garbage(rng, gap, forbid=b'\r\n')
        data, key = maker.record()
        stream += data
        markers.append(key)
    parser = BinaryStreamParser(LAYOUT, accept_replies=accept_replies)
    out = feed_in_chunks(parser, bytes(stream), rng, max_chunk=300)
    keys = [key_of(r) for r in out if isinstance(r, StationRecord)]
    # Each marker comes out, in order (garbage may add records of its own in between).
    it = iter(keys)
    assert all(any(k == m for k in it) for m in markers)
    assert parser.stats.bytes_in == len(stream)
    assert 0 < parser.stats.bytes_dropped <= parser.stats.bytes_in
    assert parser.stats.resyncs > 0
    assert conserved(parser, out, 46)
    if not accept_replies:
        assert not any(isinstance(r, Reply) for r in out)


@pytest.mark.parametrize('seed', range(25))
def test_truncated_records_then_good_ones(seed):
    rng = random.Random(2000 + seed)
    maker = Maker(rng)
    stream = bytearray()
    expected = []
    truncated_total = 0
    for _ in range(80):
        data, key = maker.record()
        if rng.random() < 0.3:
            cut = rng.randint(1, len(data) - 1)
            stream += data[:cut]
            truncated_total += cut
        else:
            stream += data
            expected.append(key)
    data, key = maker.record()  # always end on a whole record
    stream += data
    expected.append(key)
    parser = BinaryStreamParser(LAYOUT)
    out = feed_in_chunks(parser, bytes(stream), rng)
    assert [key_of(r) for r in out] == expected
    assert parser.stats.bytes_dropped == truncated_total
    assert parser.pending == 0


@pytest.mark.parametrize('seed', range(25))
def test_truncated_records_without_crlf_lose_at_most_the_next(seed):
    # Without a trailing CR LF to check, a truncated record can swallow the start of the
    # next one; the loss must stop there.
    rng = random.Random(2500 + seed)
    maker = Maker(rng, LAYOUT_NO_CRLF)
    stream = bytearray()
    keys = []
    after_truncation = set()
    previous_truncated = False
    for _ in range(80):
        data, key = maker.record()
        if previous_truncated:
            after_truncation.add(key)
        if rng.random() < 0.3:
            stream += data[:rng.randint(1, len(data) - 1)]
            previous_truncated = True
        else:
            stream += data
            keys.append(key)
            previous_truncated = False
    parser = BinaryStreamParser(LAYOUT_NO_CRLF)
    out = feed_in_chunks(parser, bytes(stream), rng)
    got = {key_of(r) for r in out}
    lost = [k for k in keys if k not in got]
    assert set(lost) <= after_truncation
    assert conserved(parser, out, 36)


def _flip(data, rng):
    data = bytearray(data)
    bit = rng.randrange(len(data) * 8)
    data[bit // 8] ^= 1 << (bit % 8)
    return bytes(data)


def _flipped_stream(maker, rng, probability: float, max_flips: int):
    """150 records, each flipped (1 to ``max_flips`` bits) with ``probability``: the stream,
    the records' keys and the indices of the flipped ones."""
    stream = bytearray()
    keys = []
    flipped = set()
    for i in range(150):
        data, key = maker.record()
        if rng.random() < probability:
            for _ in range(rng.randint(1, max_flips)):
                data = _flip(data, rng)
            flipped.add(i)
        stream += data
        keys.append(key)
    return bytes(stream), keys, flipped


@pytest.mark.parametrize('accept_replies', [False, True])
@pytest.mark.parametrize('seed', range(25))
def test_bit_flips_clean_records(seed, accept_replies):
    rng = random.Random(3000 + seed)
    stream, keys, flipped = _flipped_stream(Maker(rng), rng, 0.25, 1)
    parser = BinaryStreamParser(LAYOUT, accept_replies=accept_replies)
    out = feed_in_chunks(parser, stream, rng)
    records = [r for r in out if isinstance(r, StationRecord)]
    got = [key_of(r) for r in records]
    # Every record that was not flipped comes out intact and in order.
    intact = [k for i, k in enumerate(keys) if i not in flipped]
    assert [k for k in got if k in set(intact)] == intact
    # A flipped record comes out once (perhaps altered) or not at all.
    assert len(out) <= len(keys)
    lost = len(keys) - len(out)
    assert 0 <= lost <= len(flipped)
    assert conserved(parser, out, 46)


@pytest.mark.parametrize('layout', [LAYOUT, LAYOUT_NO_CRLF], ids=['crlf', 'no_crlf'])
@pytest.mark.parametrize('seed', range(25))
def test_bit_flips_raw_records_loss_is_bounded(seed, layout):
    # Random payloads (they may hold 'LY' or CR LF), up to three flips per record,
    # neighbours may both be flipped.
    rng = random.Random(4000 + seed)
    stream, keys, flipped = _flipped_stream(Maker(rng, layout, clean=False), rng, 0.2, 3)
    parser = BinaryStreamParser(layout)
    out = feed_in_chunks(parser, stream, rng)
    got = {key_of(r) for r in out}
    lost = {i for i, k in enumerate(keys) if i not in flipped and k not in got}
    # Only the neighbour right after a flipped record may be lost with it.
    assert lost <= {i + 1 for i in flipped}
    assert len(out) <= len(keys)
    assert conserved(parser, out, SIZES[layout])


@pytest.mark.parametrize('accept_replies', [False, True])
@pytest.mark.parametrize('seed', range(15))
def test_wrong_size_fields_are_dropped(seed, accept_replies):
    rng = random.Random(5000 + seed)
    maker = Maker(rng)
    stream = bytearray()
    expected = []
    bad_total = 0
    bad_sizes = [0, 1, 30, 37, 39, 46, 38 + 256, 38 << 8, 0xFFFF]
    for _ in range(100):
        data, key = maker.record()
        if rng.random() < 0.3:
            size = rng.choice(bad_sizes + [rng.randrange(65536)])
            if size == 38:
                size = 39
            data = data[:6] + struct.pack('<H', size) + data[8:]
            stream += data
            bad_total += len(data)
        else:
            stream += data
            expected.append(key)
    parser = BinaryStreamParser(LAYOUT, accept_replies=accept_replies)
    out = feed_in_chunks(parser, bytes(stream), rng)
    assert [key_of(r) for r in out] == expected
    assert parser.stats.bytes_dropped == bad_total
    assert parser.stats.reasons.get('bad size field', 0) >= 1


def test_all_impossible_station_numbers_are_dropped():
    rng = random.Random(6000)
    maker = Maker(rng)
    stream = bytearray()
    expected = []
    bad_total = 0
    for station in [0] + list(range(17, 256)):
        bad, _ = maker.record(station=station)
        good, key = maker.record()
        stream += bad + good
        bad_total += len(bad)
        expected.append(key)
    parser = BinaryStreamParser(LAYOUT)
    out = feed_in_chunks(parser, bytes(stream), rng)
    assert [key_of(r) for r in out] == expected
    assert all(1 <= r.station <= 16 for r in out)
    assert parser.stats.bytes_dropped == bad_total
    assert parser.stats.reasons.get('bad station', 0) >= 240


def _random_stream(rng, length, sync_rich):
    if not sync_rich:
        return bytes(rng.randrange(256) for _ in range(length))
    out = bytearray()
    while len(out) < length:
        r = rng.random()
        if r < 0.1:
            out += b'LY'
        elif r < 0.15:
            out += b'LY' + bytes([rng.randint(0, 17)]) + rng.choice([b'C', b'P', b'\x15']) \
                + b' \x00' + struct.pack('<H', rng.choice([38, 4, rng.randrange(2048)]))
        elif r < 0.2:
            out += CRLF
        else:
            out.append(rng.randrange(256))
    return bytes(out)


@pytest.mark.parametrize('accept_replies', [False, True])
@pytest.mark.parametrize('sync_rich', [False, True])
@pytest.mark.parametrize('seed', range(12))
def test_random_bytes_in_random_chunks(seed, sync_rich, accept_replies):
    rng = random.Random(7000 + seed)
    stream = _random_stream(rng, 6000, sync_rich)
    parser = BinaryStreamParser(LAYOUT, accept_replies=accept_replies)
    out = feed_in_chunks(parser, stream, rng, max_chunk=200)
    stats = parser.stats
    assert stats.bytes_in == len(stream)
    assert 0 <= stats.bytes_dropped <= stats.bytes_in
    assert stats.records == sum(isinstance(r, StationRecord) for r in out)
    assert stats.replies == sum(isinstance(r, Reply) for r in out)
    assert conserved(parser, out, 46)
    for r in out:
        if isinstance(r, StationRecord):
            assert 1 <= r.station <= 16 and r.command in 'CP'
    # After a clean gap the next good record is found.
    gap = 1100 if accept_replies else 46
    data, key = Maker(rng).record()
    tail = parser.feed(clean_garbage(rng, gap, forbid=b'\r\n') + data)
    assert key in [key_of(r) for r in tail if isinstance(r, StationRecord)]
    assert parser.pending == 0


def test_reset_drops_a_partial_record():
    rng = random.Random(8000)
    maker = Maker(rng)
    first, _ = maker.record()
    second, key = maker.record()
    parser = BinaryStreamParser(LAYOUT)
    assert parser.feed(first[:20]) == []
    assert parser.pending == 20
    parser.reset()
    assert parser.pending == 0
    assert parser.stats.bytes_dropped == 20
    assert [key_of(r) for r in parser.feed(second)] == [key]


# ----------------------------------------------------------------------------- ASCII

ASCII_LAYOUT = OutputList((2, 4, 1))
NOT_DIGIT = bytes(b for b in range(256) if b not in b'0123456789 \n')


def good_line(rng):
    station = rng.randint(1, 16)
    values = [rng.uniform(-999.0, 999.0) for _ in range(6)]
    text = b'%2dC ' % station + b''.join(b'%9.4f' % v for v in values) + CRLF
    key = (station, tuple(float(b'%.4f' % v) for v in values[:3]),
           tuple(float(b'%.4f' % v) for v in values[3:]))
    return text, key


def ascii_key(record):
    return (record.station, record.position, record.euler_deg)


def garbage_line(rng):
    """Random bytes without LF whose first byte cannot start a station number."""
    body = bytes(rng.choice(range(256)) for _ in range(rng.randint(0, 70)))
    body = body.replace(b'\n', b'')
    return bytes([rng.choice(NOT_DIGIT)]) + body + rng.choice([CRLF, b'\n'])


@pytest.mark.parametrize('seed', range(25))
def test_ascii_garbage_lines_between_good_lines(seed):
    rng = random.Random(9000 + seed)
    stream = bytearray()
    expected = []
    bad = 0
    for _ in range(80):
        if rng.random() < 0.4:
            stream += garbage_line(rng)
            bad += 1
        text, key = good_line(rng)
        stream += text
        expected.append(key)
    parser = AsciiStreamParser(ASCII_LAYOUT)
    out = feed_in_chunks(parser, bytes(stream), rng)
    assert [ascii_key(r) for r in out] == expected
    assert parser.stats.bad_lines == bad
    assert parser.stats.records == len(expected)
    assert parser.stats.bytes_in == len(stream)
    assert 0 < parser.stats.bytes_dropped <= parser.stats.bytes_in
    assert parser.pending == 0


def test_ascii_bytes_dropped_counts_whole_garbage_lines():
    garbage = [b'hello\r\n', b'#\x80\xff garbage 1 2 3\r\n', b'?\n']
    text, key = good_line(random.Random(1))
    parser = AsciiStreamParser(ASCII_LAYOUT)
    out = parser.feed(b''.join(garbage) + text)
    assert [ascii_key(r) for r in out] == [key]
    assert parser.stats.bad_lines == 3
    assert parser.stats.resyncs == 3
    # Every byte of a dropped line (its CR and LF included) counts as dropped.
    assert parser.stats.bytes_dropped == sum(len(g) for g in garbage)


@pytest.mark.parametrize('seed', range(20))
def test_ascii_broken_good_lines(seed):
    # Good lines with a field cut out, a line cut short and glued to the next, or a
    # station out of range, then good lines that must come out.
    rng = random.Random(9500 + seed)
    stream = bytearray()
    expected = []
    for _ in range(60):
        text, key = good_line(rng)
        kind = rng.randrange(4)
        if kind == 0:
            start = 4 + 9 * rng.randrange(6)
            stream += text[:start] + text[start + 9:]           # 5 numbers
        elif kind == 1:
            stream += b'%2d' % rng.choice([0, 17, 42, 99]) + text[2:]
        elif kind == 2:
            stream += text[:rng.randint(1, 30)] + b'\r\n'       # cut short: < 6 numbers
        else:
            stream += text
            expected.append(key)
    text, key = good_line(rng)
    stream += text
    expected.append(key)
    parser = AsciiStreamParser(ASCII_LAYOUT)
    out = feed_in_chunks(parser, bytes(stream), rng)
    assert [ascii_key(r) for r in out] == expected


@pytest.mark.parametrize('accept_replies', [False, True])
@pytest.mark.parametrize('seed', range(15))
def test_ascii_random_bytes_in_random_chunks(seed, accept_replies):
    rng = random.Random(9900 + seed)
    alphabet = b'0123456789 .-+eECP\r\n' + bytes(range(256))
    stream = bytes(rng.choice(alphabet) for _ in range(8000))
    parser = AsciiStreamParser(ASCII_LAYOUT, accept_replies=accept_replies)
    out = feed_in_chunks(parser, stream, rng, max_chunk=300)
    stats = parser.stats
    assert stats.bytes_in == len(stream)
    assert 0 <= stats.bytes_dropped <= stats.bytes_in
    for r in out:
        if isinstance(r, StationRecord):
            assert 1 <= r.station <= 16
            assert len(r.position) == 3 and len(r.euler_deg) == 3
        else:
            assert accept_replies and r.station == 0
    # A line break ends whatever partial line is pending; the next line is good.
    text, key = good_line(rng)
    tail = parser.feed(b'\r\n' + text)
    assert [ascii_key(r) for r in tail if isinstance(r, StationRecord)][-1:] == [key]
    assert parser.pending == 0


def test_ascii_over_long_line_is_dropped_and_next_recovered():
    rng = random.Random(9999)
    text, key = good_line(rng)
    parser = AsciiStreamParser(ASCII_LAYOUT)
    junk = b'x' * 5000
    out = []
    for i in range(0, len(junk), 700):
        out += parser.feed(junk[i:i + 700])
    assert parser.pending <= parser.max_line + 700
    out += parser.feed(b'\r\n' + text)
    assert [ascii_key(r) for r in out] == [key]
    assert parser.stats.reasons.get('line too long', 0) >= 1
