"""Liberty codec against byte layouts written out by hand from shared/liberty-protocol.md.

Every expected byte string here is built with struct.pack or literal bytes following the
protocol notes (header 'LY', station byte, command byte, error byte 0x20, reserved 0,
uint16 LE payload size; items little-endian; quaternion w first). None of it comes from
the codec under test, so a layout mistake in the codec cannot hide behind itself.
"""

import math
import struct

import numpy as np
import pytest

from polhemus_liberty import protocol as P
from polhemus_liberty.device_pose import record_to_pose
from polhemus_liberty.protocol import AsciiStreamParser, BinaryStreamParser, OutputList, Reply, StationRecord

CRLF = b'\r\n'
C45 = math.cos(math.radians(45.0))
S45 = math.sin(math.radians(45.0))


def f32(value):
    """The float32 the device would send for ``value``, back as a Python float."""
    return struct.unpack('<f', struct.pack('<f', value))[0]


def f32s(values):
    return tuple(f32(v) for v in values)


def header(station, payload_size, command=b'C', error=0x20, reserved=0):
    """An F1 header written out field by field from the protocol notes."""
    return (b'LY' + bytes([station]) + command + bytes([error]) + bytes([reserved])
            + struct.pack('<H', payload_size))


def records_only(out):
    return [r for r in out if isinstance(r, StationRecord)]


# ----------------------------------------------------------------------------- sizes

@pytest.mark.parametrize('codes, record_size', [
    ((2, 4, 1), 34),
    ((2, 7, 1), 38),
    ((8, 9, 2, 7, 1), 46),
    ((0,), 9),
    ((1,), 10),
    ((6,), 44),
    ((10, 11, 12), 20),
    ((0, 3, 5, 1), 35),
])
def test_record_sizes_match_the_protocol_notes(codes, record_size):
    layout = OutputList(codes)
    assert layout.record_size == record_size
    assert layout.payload_size == record_size - 8


def test_worked_example_size_field_is_30_for_2_7_1():
    assert OutputList((2, 7, 1)).payload_size == 30


# ----------------------------------------------------------------------------- binary layouts

# A fully literal record, O*,2,4,1: station 1, position (1, -2, 0.5), Euler (90, 0, -180).
LITERAL_2_4_1 = (
    b'LY' b'\x01' b'C' b' ' b'\x00' b'\x1a\x00'           # header, payload size 26
    b'\x00\x00\x80\x3f' b'\x00\x00\x00\xc0' b'\x00\x00\x00\x3f'   # 1.0, -2.0, 0.5
    b'\x00\x00\xb4\x42' b'\x00\x00\x00\x00' b'\x00\x00\x34\xc3'   # 90.0, 0.0, -180.0
    b'\r\n'
)


def test_literal_2_4_1_record_decodes():
    assert len(LITERAL_2_4_1) == 34
    parser = BinaryStreamParser(OutputList((2, 4, 1)))
    out = parser.feed(LITERAL_2_4_1)
    assert len(out) == 1
    record = out[0]
    assert isinstance(record, StationRecord)
    assert record.station == 1
    assert record.command == 'C'
    assert record.error == 0x20
    assert record.position == (1.0, -2.0, 0.5)
    assert record.euler_deg == (90.0, 0.0, -180.0)
    assert record.quaternion_wxyz is None
    assert record.frame_count is None
    assert parser.stats.records == 1
    assert parser.stats.bytes_dropped == 0
    assert parser.pending == 0


def test_literal_2_4_1_record_is_what_the_encoder_writes():
    record = StationRecord(station=1, position=(1.0, -2.0, 0.5), euler_deg=(90.0, 0.0, -180.0))
    assert P.encode_binary_record(OutputList((2, 4, 1)), record) == LITERAL_2_4_1


def _case_2_7_1():
    quat = (0.5, -0.5, 0.5, -0.5)
    data = (header(3, 30) + struct.pack('<3f', 12.25, -7.5, 30.0)
            + struct.pack('<4f', *quat) + CRLF)
    expected = dict(station=3, position=(12.25, -7.5, 30.0), quaternion_wxyz=quat)
    return (2, 7, 1), data, expected, 38


def _case_8_9_2_7_1():
    quat = (C45, 0.0, 0.0, S45)
    data = (header(2, 38) + struct.pack('<I', 123456789) + struct.pack('<I', 4242)
            + struct.pack('<3f', -1.5, 2.75, 40.0) + struct.pack('<4f', *quat) + CRLF)
    expected = dict(station=2, timestamp_ms=123456789, frame_count=4242,
                    position=(-1.5, 2.75, 40.0), quaternion_wxyz=f32s(quat))
    return (8, 9, 2, 7, 1), data, expected, 46


def _case_3_5_0_1():
    # Extended-precision position and Euler (items 3 and 5), then one space byte, CR LF.
    pos = (1.0e-3, -123.456, 7.0)
    euler = (-179.5, 89.25, 0.125)
    data = (header(16, 27) + struct.pack('<3f', *pos) + struct.pack('<3f', *euler)
            + b' ' + CRLF)
    expected = dict(station=16, position=f32s(pos), euler_deg=euler)
    return (3, 5, 0, 1), data, expected, 35


def _case_6_10_11_12():
    # Direction cosines (9 floats), stylus, distortion (int32, negative), external sync;
    # no CR LF in this list.
    cosines = (0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    data = (header(5, 48, command=b'P') + struct.pack('<9f', *cosines)
            + struct.pack('<I', 1) + b'\xfd\xff\xff\xff' + struct.pack('<I', 7))
    expected = dict(station=5, command='P', direction_cosines=cosines, stylus=1,
                    distortion=-3, external_sync=7)
    return (6, 10, 11, 12), data, expected, 56


def _case_9_0_8():
    # Frame count, space, timestamp: odd total size, no CR LF.
    data = header(9, 9) + struct.pack('<I', 0xFFFFFFFF) + b' ' + struct.pack('<I', 0)
    expected = dict(station=9, frame_count=0xFFFFFFFF, timestamp_ms=0)
    return (9, 0, 8), data, expected, 17


CASES = {
    '2_7_1': _case_2_7_1,
    '8_9_2_7_1': _case_8_9_2_7_1,
    '3_5_0_1': _case_3_5_0_1,
    '6_10_11_12': _case_6_10_11_12,
    '9_0_8': _case_9_0_8,
}


def test_the_cases_cover_every_item_code():
    covered = {0, 1, 2, 4}  # literal 2_4_1 above
    for make in CASES.values():
        covered.update(make()[0])
    assert covered == set(range(13))


@pytest.mark.parametrize('name', sorted(CASES))
def test_hand_made_record_decodes(name):
    codes, data, expected, size = CASES[name]()
    assert len(data) == size
    parser = BinaryStreamParser(OutputList(codes))
    out = parser.feed(data)
    assert len(out) == 1
    record = out[0]
    assert isinstance(record, StationRecord)
    for field_name, value in expected.items():
        assert getattr(record, field_name) == value, field_name
    # Fields the list does not carry stay None.
    carried = {P.ITEMS[c].field for c in codes}
    for field_name in ('position', 'euler_deg', 'direction_cosines', 'quaternion_wxyz',
                       'timestamp_ms', 'frame_count', 'stylus', 'distortion', 'external_sync'):
        if field_name not in carried:
            assert getattr(record, field_name) is None, field_name
    assert parser.stats.bytes_dropped == 0
    assert parser.pending == 0


@pytest.mark.parametrize('name', ['2_7_1', '8_9_2_7_1', '6_10_11_12'])
def test_encoder_writes_the_hand_made_bytes(name):
    codes, data, expected, _ = CASES[name]()
    record = StationRecord(**expected)
    assert P.encode_binary_record(OutputList(codes), record) == data


@pytest.mark.parametrize('name', ['3_5_0_1', '9_0_8'])
def test_encoder_writes_item_0_as_a_space_byte(name):
    # Item 0 is "space" in the protocol notes (and format_ascii_record writes ' ' for it),
    # so the binary record carries 0x20 there, as the hand-made bytes do.
    codes, data, expected, _ = CASES[name]()
    record = StationRecord(**expected)
    encoded = P.encode_binary_record(OutputList(codes), record)
    assert len(encoded) == len(data)
    assert encoded == data


def test_error_byte_and_single_shot_command_are_reported():
    data = header(4, 26, command=b'P', error=ord('E')) + struct.pack('<6f', *range(6)) + CRLF
    parser = BinaryStreamParser(OutputList((2, 4, 1)))
    (record,) = parser.feed(data)
    assert record.command == 'P'
    assert record.error == ord('E')
    assert record.position == (0.0, 1.0, 2.0)
    assert parser.stats.error_records == 1


def test_payload_that_looks_like_a_header_does_not_break_sync():
    # Timestamp bytes spell 'LY', station 1, 'C'; a position float holds CR LF and 'LY'.
    ts = int.from_bytes(b'LY\x01C', 'little')
    x = struct.unpack('<f', b'\r\nLY')[0]
    data = (header(1, 38) + struct.pack('<I', ts) + struct.pack('<I', 7)
            + struct.pack('<3f', x, 0.0, 1.0) + struct.pack('<4f', 1.0, 0.0, 0.0, 0.0) + CRLF)
    stream = data * 3
    layout = OutputList((8, 9, 2, 7, 1))
    for cut in range(len(stream) + 1):
        parser = BinaryStreamParser(layout)
        out = parser.feed(stream[:cut]) + parser.feed(stream[cut:])
        assert [r.timestamp_ms for r in out] == [ts] * 3, cut
        assert all(r.position == (x, 0.0, 1.0) for r in out)
        assert parser.stats.bytes_dropped == 0


# ----------------------------------------------------------------------------- several stations

def _frame_8_9_2_7_1(stations, frame=100):
    """One tracker frame: every station's 46-byte record back to back."""
    data = b''
    expected = []
    for s in stations:
        pos = (float(s), -2.0 * s, 0.5 + s)
        quat = (0.5, 0.5, -0.5, 0.5) if s % 2 else (1.0, 0.0, 0.0, 0.0)
        data += (header(s, 38) + struct.pack('<II', 1000 + s, frame)
                 + struct.pack('<3f', *pos) + struct.pack('<4f', *quat) + CRLF)
        expected.append((s, 1000 + s, frame, pos, quat))
    return data, expected


def _summary(records):
    return [(r.station, r.timestamp_ms, r.frame_count, r.position, r.quaternion_wxyz)
            for r in records]


LAYOUT_46 = OutputList((8, 9, 2, 7, 1))


def test_several_stations_back_to_back_in_one_frame():
    data, expected = _frame_8_9_2_7_1([1, 2, 3, 4, 16])
    assert len(data) == 5 * 46
    parser = BinaryStreamParser(LAYOUT_46)
    out = parser.feed(data)
    assert _summary(out) == expected
    assert parser.stats.records == 5
    assert parser.stats.bytes_in == len(data)


def test_split_at_every_byte_boundary():
    data, expected = _frame_8_9_2_7_1([1, 2, 3, 4])
    for cut in range(len(data) + 1):
        parser = BinaryStreamParser(LAYOUT_46)
        first = parser.feed(data[:cut])
        assert len(first) == cut // 46, cut
        out = first + parser.feed(data[cut:])
        assert _summary(out) == expected, cut
        assert parser.pending == 0
        assert parser.stats.bytes_dropped == 0
        assert parser.stats.resyncs == 0


def test_split_at_every_pair_of_boundaries():
    data, expected = _frame_8_9_2_7_1([7, 8])
    n = len(data)
    for a in range(n + 1):
        for b in range(a, n + 1):
            parser = BinaryStreamParser(LAYOUT_46)
            out = parser.feed(data[:a]) + parser.feed(data[a:b]) + parser.feed(data[b:])
            assert _summary(out) == expected, (a, b)
            assert parser.stats.bytes_dropped == 0


def test_byte_at_a_time():
    data, expected = _frame_8_9_2_7_1([1, 2, 3])
    parser = BinaryStreamParser(LAYOUT_46)
    out = []
    for i in range(len(data)):
        got = parser.feed(data[i:i + 1])
        out += got
        # A record comes out exactly when its last byte arrives.
        assert len(got) == (1 if (i + 1) % 46 == 0 else 0), i
    assert _summary(out) == expected
    assert parser.stats.bytes_in == len(data)
    assert parser.stats.bytes_dropped == 0


@pytest.mark.parametrize('station', [0, 17, 200, 255])
def test_impossible_station_is_dropped_and_next_record_recovered(station):
    bad = header(station, 26) + struct.pack('<6f', *range(6)) + CRLF
    good = header(2, 26) + struct.pack('<6f', 1, 2, 3, 4, 5, 6) + CRLF
    parser = BinaryStreamParser(OutputList((2, 4, 1)))
    out = parser.feed(bad + good)
    assert [r.station for r in out] == [2]
    assert out[0].euler_deg == (4.0, 5.0, 6.0)
    assert parser.stats.bytes_dropped == len(bad)
    assert parser.stats.resyncs >= 1


def test_every_valid_station_is_accepted():
    layout = OutputList((2, 4, 1))
    data = b''.join(header(s, 26) + struct.pack('<6f', s, 0, 0, 0, 0, 0) + CRLF
                    for s in range(1, 17))
    out = BinaryStreamParser(layout).feed(data)
    assert [r.station for r in out] == list(range(1, 17))
    assert [r.position[0] for r in out] == [float(s) for s in range(1, 17)]


def test_wrong_size_field_and_missing_crlf_are_dropped():
    layout = OutputList((2, 4, 1))
    body = struct.pack('<6f', *range(6))
    wrong_size = header(1, 26 + 256) + body + CRLF  # same low byte, wrong high byte
    no_crlf = header(1, 26) + body + b'\r\r'
    good = header(3, 26) + body + CRLF
    parser = BinaryStreamParser(layout)
    out = parser.feed(wrong_size + no_crlf + good)
    assert [r.station for r in out] == [3]
    assert parser.stats.bytes_dropped == len(wrong_size) + len(no_crlf)
    assert parser.stats.reasons.get('bad size field', 0) >= 1
    assert parser.stats.reasons.get('missing CR LF', 0) >= 1


# ----------------------------------------------------------------------------- replies

def _station_map_reply(detected, active, station=0):
    return (b'LY' + bytes([station, 0x15]) + b' ' + b'\x00' + struct.pack('<H', 4)
            + struct.pack('<HH', detected, active))


def test_station_map_reply_accepted_during_setup():
    reply = _station_map_reply(0b1000_0000_0000_0101, 0b0000_0000_0000_0001)
    data, expected = _frame_8_9_2_7_1([1, 3])
    parser = BinaryStreamParser(LAYOUT_46, accept_replies=True)
    out = parser.feed(reply + data)
    assert len(out) == 3
    assert isinstance(out[0], Reply)
    assert out[0].command == 0x15
    assert out[0].payload == struct.pack('<HH', 0x8005, 0x0001)
    detected, active = P.decode_station_map(out[0].payload)
    assert detected == {1, 3, 16}
    assert active == {1}
    assert _summary(out[1:]) == expected
    assert parser.stats.replies == 1
    assert parser.stats.records == 2


def test_station_map_reply_split_byte_by_byte():
    reply = _station_map_reply(0x00FF, 0x000F)
    parser = BinaryStreamParser(LAYOUT_46, accept_replies=True)
    out = []
    for i in range(len(reply)):
        out += parser.feed(reply[i:i + 1])
    assert len(out) == 1 and isinstance(out[0], Reply)
    assert P.decode_station_map(out[0].payload) == (set(range(1, 9)), {1, 2, 3, 4})


def test_station_map_reply_skipped_while_streaming():
    reply = _station_map_reply(0x0003, 0x0003)
    data, expected = _frame_8_9_2_7_1([1, 2])
    parser = BinaryStreamParser(LAYOUT_46, accept_replies=False)
    out = parser.feed(data[:46] + reply + data[46:])
    assert all(isinstance(r, StationRecord) for r in out)
    assert _summary(out) == expected
    assert parser.stats.replies == 0
    assert parser.stats.bytes_dropped == len(reply)
    assert parser.stats.resyncs >= 1


def test_decode_station_map_empty_and_full():
    assert P.decode_station_map(struct.pack('<HH', 0, 0)) == (set(), set())
    assert P.decode_station_map(struct.pack('<HH', 0xFFFF, 0xFFFF)) == (
        set(range(1, 17)), set(range(1, 17)))


def test_encode_binary_reply_matches_hand_layout():
    payload = struct.pack('<HH', 5, 1)
    assert P.encode_binary_reply(0x15, payload) == _station_map_reply(5, 1)


# ----------------------------------------------------------------------------- ASCII

LINE_2_4_1 = b' 1C   10.0000  -5.0000  20.0000  40.0497  18.4085  19.4400\r\n'
GOOD_2_4_1 = b' 2C    1.0000   2.0000   3.0000   4.0000   5.0000   6.0000\r\n'


def test_ascii_line_decodes():
    assert len(LINE_2_4_1) == 60
    parser = AsciiStreamParser(OutputList((2, 4, 1)))
    (record,) = parser.feed(LINE_2_4_1)
    assert record.station == 1
    assert record.command == 'C'
    assert record.error == 0x20
    assert record.position == (10.0, -5.0, 20.0)
    assert record.euler_deg == (40.0497, 18.4085, 19.44)
    assert parser.stats.records == 1
    assert parser.stats.bad_lines == 0


def test_format_ascii_record_writes_the_hand_written_line():
    record = StationRecord(station=1, position=(10.0, -5.0, 20.0),
                           euler_deg=(40.0497, 18.4085, 19.44))
    assert P.format_ascii_record(OutputList((2, 4, 1)), record) == LINE_2_4_1


def test_ascii_fields_at_full_width_with_no_spaces_between():
    line = b'12P -100.0000-200.0000-300.0000-179.9999 -89.9999-179.9999\r\n'
    assert len(line) == 60
    (record,) = AsciiStreamParser(OutputList((2, 4, 1))).feed(line)
    assert record.station == 12
    assert record.command == 'P'
    assert record.position == (-100.0, -200.0, -300.0)
    assert record.euler_deg == (-179.9999, -89.9999, -179.9999)


def test_ascii_negative_number_overflowing_into_previous_field():
    # -1234.5678 needs 10 characters in a 9-wide field: the line is one longer and the
    # minus sign touches the previous number.
    line = b' 3C   10.0000-1234.5678  20.0000  40.0497-118.4085  19.4400\r\n'
    (record,) = AsciiStreamParser(OutputList((2, 4, 1))).feed(line)
    assert record.station == 3
    assert record.position == (10.0, -1234.5678, 20.0)
    assert record.euler_deg == (40.0497, -118.4085, 19.44)


def test_ascii_station_with_leading_zero():
    line = b'01C    1.0000   2.0000   3.0000   4.0000   5.0000   6.0000\r\n'
    (record,) = AsciiStreamParser(OutputList((2, 4, 1))).feed(line)
    assert record.station == 1
    assert record.position == (1.0, 2.0, 3.0)


def test_ascii_integer_items_and_quaternion():
    line = (b' 4C ' + b'     123456' + b'         42'
            + b'   1.5000' + b'  -2.2500' + b'  30.0000'
            + b'  0.70711' + b'  0.00000' + b' -0.70711' + b'  0.00000' + b'\r\n')
    assert len(line) == 4 + 22 + 27 + 36 + 2
    (record,) = AsciiStreamParser(OutputList((8, 9, 2, 7, 1))).feed(line)
    assert record.timestamp_ms == 123456 and isinstance(record.timestamp_ms, int)
    assert record.frame_count == 42 and isinstance(record.frame_count, int)
    assert record.position == (1.5, -2.25, 30.0)
    assert record.quaternion_wxyz == (0.70711, 0.0, -0.70711, 0.0)


def test_ascii_lines_split_across_feeds():
    stream = LINE_2_4_1 + GOOD_2_4_1
    for cut in range(len(stream) + 1):
        parser = AsciiStreamParser(OutputList((2, 4, 1)))
        out = parser.feed(stream[:cut]) + parser.feed(stream[cut:])
        assert [r.station for r in out] == [1, 2], cut


@pytest.mark.parametrize('bad', [
    b' 1C   10.0000  -5.0000  20.0000  40.0497  18.4085\r\n',                    # 5 numbers
    b' 1C   10.0000  -5.0000  20.0000  40.0497  18.4085  19.4400   1.0000\r\n',  # 7 numbers
    b' 0C   10.0000  -5.0000  20.0000  40.0497  18.4085  19.4400\r\n',           # station 0
    b'17C   10.0000  -5.0000  20.0000  40.0497  18.4085  19.4400\r\n',           # station 17
    b'99C   10.0000  -5.0000  20.0000  40.0497  18.4085  19.4400\r\n',           # station 99
    b' 1X   10.0000  -5.0000  20.0000  40.0497  18.4085  19.4400\r\n',           # command X
    b' 1C   10.0\xff00  -5.0000  20.0000  40.0497  18.4085  19.4400\r\n',        # non-ASCII
    b' 1C   10.0000  -5.0000  20.0000  40.0497  18.4085  19.44\xc3\xa9\r\n',     # UTF-8 e
    b'xxC   10.0000  -5.0000  20.0000  40.0497  18.4085  19.4400\r\n',           # no station
    b' 1C\r\n',                                                                  # no numbers
])
def test_bad_ascii_line_dropped_and_next_recovered(bad):
    parser = AsciiStreamParser(OutputList((2, 4, 1)))
    out = parser.feed(bad + GOOD_2_4_1)
    assert [r.station for r in out] == [2]
    assert out[0].position == (1.0, 2.0, 3.0)
    assert parser.stats.bad_lines == 1
    assert parser.stats.records == 1
    assert parser.stats.bytes_dropped > 0


def test_station_16_is_valid_in_ascii():
    line = b'16C    1.0000   2.0000   3.0000   4.0000   5.0000   6.0000\r\n'
    (record,) = AsciiStreamParser(OutputList((2, 4, 1))).feed(line)
    assert record.station == 16


def test_non_ascii_byte_replacing_any_character_drops_the_line():
    # The device's F0 output is plain ASCII; a byte >= 0x80 anywhere means the line was
    # corrupted on the way, so the line must not come out as a record.
    accepted = []
    for index in range(len(LINE_2_4_1) - 2):
        for byte in (0x80, 0xB1, 0xFF):
            line = bytearray(LINE_2_4_1)
            line[index] = byte
            parser = AsciiStreamParser(OutputList((2, 4, 1)))
            if parser.feed(bytes(line)):
                accepted.append((index, hex(byte)))
            elif parser.stats.bad_lines != 1:
                accepted.append((index, hex(byte), 'not counted'))
    assert accepted == []


def test_non_ascii_byte_inserted_into_a_line_drops_the_line():
    accepted = []
    for index in range(len(LINE_2_4_1) - 1):
        line = bytearray(LINE_2_4_1)
        line.insert(index, 0xFF)
        parser = AsciiStreamParser(OutputList((2, 4, 1)))
        out = parser.feed(bytes(line) + GOOD_2_4_1)
        if [r.station for r in out] != [2] or parser.stats.bad_lines != 1:
            accepted.append(index)
    assert accepted == []


def test_ascii_reply_line_only_while_accepting_replies():
    line = b' 0 WhoAmI text\r\n'
    parser = AsciiStreamParser(OutputList((2, 4, 1)), accept_replies=True)
    (reply,) = parser.feed(line)
    assert isinstance(reply, Reply)
    assert reply.station == 0
    assert b'WhoAmI text' in reply.payload
    assert parser.stats.replies == 1
    quiet = AsciiStreamParser(OutputList((2, 4, 1)), accept_replies=False)
    assert quiet.feed(line + GOOD_2_4_1)[0].station == 2
    assert quiet.stats.bad_lines == 1


def test_make_stream_parser_picks_the_format():
    layout = OutputList((2, 4, 1))
    assert isinstance(P.make_stream_parser(layout, binary=True), BinaryStreamParser)
    assert isinstance(P.make_stream_parser(layout, binary=False), AsciiStreamParser)
    assert P.make_stream_parser(layout, binary=True, accept_replies=True).accept_replies


# ----------------------------------------------------------------------------- Euler vs quaternion

def _qmul_wxyz(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return (w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2)


def _zyx_by_hand(az, el, roll):
    """qz(az) * qy(el) * qx(roll), (w, x, y, z), angles in degrees."""
    h = [math.radians(a) / 2 for a in (az, el, roll)]
    qz = (math.cos(h[0]), 0.0, 0.0, math.sin(h[0]))
    qy = (math.cos(h[1]), 0.0, math.sin(h[1]), 0.0)
    qx = (math.cos(h[2]), math.sin(h[2]), 0.0, 0.0)
    return _qmul_wxyz(_qmul_wxyz(qz, qy), qx)


# (azimuth, elevation, roll) in degrees and the quaternion (w, x, y, z) worked out by hand.
POSES = [
    ((90.0, 0.0, 0.0), (C45, 0.0, 0.0, S45)),
    ((0.0, 90.0, 0.0), (C45, 0.0, S45, 0.0)),
    ((0.0, 0.0, 90.0), (C45, S45, 0.0, 0.0)),
    ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)),
    ((30.0, 20.0, 10.0), (0.951548525, 0.038134576, 0.189307857, 0.239298338)),
    # A device answer with w < 0 is the same rotation.
    ((-120.0, 45.0, 170.0), (-0.289891742, 0.489066542, -0.780381982, -0.260347187)),
    # Elevation 90: Euler is degenerate but still one rotation.
    ((30.0, 90.0, 10.0), (0.69636424, -0.122787804, 0.69636424, 0.122787804)),
]


@pytest.mark.parametrize('euler, quat', POSES)
def test_hand_quaternions_are_the_zyx_product(euler, quat):
    product = _zyx_by_hand(*euler)
    sign = 1.0 if np.dot(product, quat) >= 0 else -1.0
    assert np.allclose(sign * np.asarray(product), quat, atol=1e-8)


def _same_rotation(q1_xyzw, q2_xyzw, atol=1e-6):
    return abs(abs(float(np.dot(q1_xyzw, q2_xyzw))) - 1.0) < atol


@pytest.mark.parametrize('euler, quat', POSES)
def test_euler_record_and_quaternion_record_give_the_same_pose(euler, quat):
    pos = (10.0, -20.0, 30.0)
    both = (header(1, 42) + struct.pack('<3f', *pos) + struct.pack('<3f', *euler)
            + struct.pack('<4f', *quat) + CRLF)
    euler_only = header(1, 26) + struct.pack('<3f', *pos) + struct.pack('<3f', *euler) + CRLF
    quat_only = header(1, 30) + struct.pack('<3f', *pos) + struct.pack('<4f', *quat) + CRLF

    (rec_both,) = BinaryStreamParser(OutputList((2, 4, 7, 1))).feed(both)
    (rec_euler,) = BinaryStreamParser(OutputList((2, 4, 1))).feed(euler_only)
    (rec_quat,) = BinaryStreamParser(OutputList((2, 7, 1))).feed(quat_only)
    assert rec_both.euler_deg == f32s(euler)
    assert rec_both.quaternion_wxyz == f32s(quat)
    assert rec_euler.quaternion_wxyz is None and rec_quat.euler_deg is None

    pose_e = record_to_pose(rec_euler, 'cm')
    pose_q = record_to_pose(rec_quat, 'cm')
    assert pose_e is not None and pose_q is not None
    np.testing.assert_allclose(pose_e[0], [0.10, -0.20, 0.30], atol=1e-9)
    np.testing.assert_allclose(pose_q[0], [0.10, -0.20, 0.30], atol=1e-9)
    w, x, y, z = quat
    expected_xyzw = np.array([x, y, z, w])
    assert abs(np.linalg.norm(pose_e[1]) - 1.0) < 1e-12
    assert abs(np.linalg.norm(pose_q[1]) - 1.0) < 1e-12
    assert _same_rotation(pose_e[1], expected_xyzw)
    assert _same_rotation(pose_q[1], expected_xyzw)
    assert _same_rotation(pose_e[1], pose_q[1])


def test_record_to_pose_prefers_quaternion_and_converts_inches():
    # Euler says identity, quaternion says 90 deg about z: the quaternion wins.
    record = StationRecord(station=1, position=(1.0, 2.0, -3.0), euler_deg=(0.0, 0.0, 0.0),
                           quaternion_wxyz=(C45, 0.0, 0.0, S45))
    position, quaternion = record_to_pose(record, 'inch')
    np.testing.assert_allclose(position, [0.0254, 0.0508, -0.0762], atol=1e-12)
    assert _same_rotation(quaternion, [0.0, 0.0, S45, C45])


def test_record_to_pose_from_direction_cosines():
    # Row-major R of 90 deg about z: x -> y.
    record = StationRecord(station=1, position=(0.0, 0.0, 0.0),
                           direction_cosines=(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0))
    _, quaternion = record_to_pose(record, 'cm')
    assert _same_rotation(quaternion, [0.0, 0.0, S45, C45])


@pytest.mark.parametrize('record', [
    StationRecord(station=1, position=None, quaternion_wxyz=(1.0, 0.0, 0.0, 0.0)),
    StationRecord(station=1, position=(0.0, 0.0, 0.0)),
    StationRecord(station=1, position=(0.0, 0.0, 0.0), quaternion_wxyz=(0.0, 0.0, 0.0, 0.0)),
    StationRecord(station=1, position=(math.nan, 0.0, 0.0), quaternion_wxyz=(1.0, 0, 0, 0)),
    StationRecord(station=1, position=(0.0, 0.0, 0.0), quaternion_wxyz=(math.inf, 0, 0, 0)),
])
def test_record_to_pose_refuses_incomplete_or_corrupt_records(record):
    assert record_to_pose(record, 'cm') is None


# ----------------------------------------------------------------------------- commands

def test_command_bytes():
    assert P.cmd_format(True) == b'F1\r'
    assert P.cmd_format(False) == b'F0\r'
    assert P.cmd_units(True) == b'U1\r'
    assert P.cmd_units(False) == b'U0\r'
    assert P.cmd_output_list([8, 9, 2, 7, 1]) == b'O*,8,9,2,7,1\r'
    assert P.cmd_output_list((2, 4, 1), station=3) == b'O3,2,4,1\r'
    assert P.cmd_hemisphere([1, 0, 0]) == b'H*,1,0,0\r'
    assert P.cmd_hemisphere((0.0, 0.0, 0.0)) == b'H*,0,0,0\r'
    assert P.cmd_hemisphere((0, 0, -1), station=2) == b'H2,0,0,-1\r'
    assert P.cmd_frame_rate(240) == b'R4\r'
    assert P.cmd_frame_rate(120) == b'R3\r'
    assert P.CMD_CONTINUOUS == b'C\r'
    assert P.CMD_SINGLE == b'P'
    assert P.CMD_STATION_MAP == b'\x150\r'
    assert P.CMD_WHOAMI == b'\x16\r'
    assert P.CMD_FLUSH == b'\r'
    assert P.CMD_RESET_COUNTERS == b'Q\r'


@pytest.mark.parametrize('hz', [60, 0, 119, 241, 480])
def test_frame_rate_refuses_unsupported_rates(hz):
    with pytest.raises(ValueError):
        P.cmd_frame_rate(hz)


@pytest.mark.parametrize('codes', [
    (), (13,), (-1,), (2, 99),                          # unknown
    (2, 3), (4, 5), (2, 2), (8, 8), (6, 6, 1), (7, 7),  # same quantity twice
    (1, 2), (2, 1, 4), (1, 2, 7),                       # CR LF not last
    (1, 2, 1), (2, 1, 1),                               # an extra CR LF not last
])
def test_output_list_refusals(codes):
    with pytest.raises(ValueError):
        OutputList(codes)


def test_output_list_accepts_spaces_and_default():
    assert OutputList((0, 2, 0, 4, 0, 1)).record_size == 8 + 3 + 24 + 2
    assert OutputList(P.DEFAULT_OUTPUT_ITEMS).record_size == 46
    assert OutputList((2, 4, 1)) == OutputList([2, 4, 1])
    assert OutputList((2, 4, 1)) != OutputList((2, 7, 1))


def test_encoder_refuses_records_missing_a_listed_item():
    with pytest.raises(ValueError):
        P.encode_binary_record(OutputList((2, 7, 1)), StationRecord(station=1,
                                                                    position=(0, 0, 0)))
