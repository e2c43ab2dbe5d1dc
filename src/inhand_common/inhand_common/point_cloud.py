"""numpy structured arrays <-> sensor_msgs/PointCloud2, without sensor_msgs_py.

The pip ROS wheels have no ``sensor_msgs_py``; this is the part of it we need, plus a
direct CDR writer for big clouds: ``serialize_point_cloud2`` builds the serialized message
with one copy of the point data, and ``publisher.publish(those_bytes)`` hands it to DDS
as is. Going through a message object instead costs three more copies of the data (the
array's bytes, ``array.array``, the ``data`` setter's own copy) and rclpy's conversion:
for a full 70^3 map (8 MB) that is most of the time a publication takes.

The way back has the same two doors: ``from_point_cloud2`` for a message object, and
``decode_point_cloud2`` for the serialized bytes a raw subscription or a bag gives (no
message object, no copy of the points, a ValueError naming what is malformed). Both read
the layout through ``points_of_layout``: either byte order, padded rows, fields of count > 1.
"""

from __future__ import annotations

import array
import struct
import sys
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

from inhand_common.cdr import ENCAPSULATION, byte_order, decode_string

__all__ = ['DecodedCloud', 'decode_point_cloud2', 'from_point_cloud2', 'points_of_layout',
           'serialize_point_cloud2', 'to_point_cloud2']

_TO_POINTFIELD = {
    np.dtype('int8'): PointField.INT8, np.dtype('uint8'): PointField.UINT8,
    np.dtype('int16'): PointField.INT16, np.dtype('uint16'): PointField.UINT16,
    np.dtype('int32'): PointField.INT32, np.dtype('uint32'): PointField.UINT32,
    np.dtype('float32'): PointField.FLOAT32, np.dtype('float64'): PointField.FLOAT64,
}
_FROM_POINTFIELD = {v: k for k, v in _TO_POINTFIELD.items()}
_MAX_ITEMSIZE = 2**31 - 1  # numpy's limit for one point (a C int)


def _native(points: np.ndarray) -> np.ndarray:
    """The array with every field in this machine's byte order (the message says which)."""
    if points.dtype.names is None:
        raise TypeError('a point cloud needs a structured array (named fields)')
    native = _native_dtype(points.dtype)
    return np.ascontiguousarray(points if native == points.dtype else points.astype(native))


def _fields(points: np.ndarray) -> list[tuple[str, int, int]]:
    """(name, offset, PointField datatype) of each field."""
    out = []
    for name in points.dtype.names:
        dtype, offset = points.dtype.fields[name][:2]
        if dtype not in _TO_POINTFIELD:
            raise TypeError(f'field {name!r}: {dtype} has no PointField datatype')
        out.append((name, offset, _TO_POINTFIELD[dtype]))
    return out


def to_point_cloud2(points: np.ndarray, frame_id: str, stamp) -> PointCloud2:
    """An unorganised cloud (height 1) from a structured array of scalar fields."""
    points = _native(points)
    msg = PointCloud2()
    msg.header.frame_id = frame_id
    msg.header.stamp = stamp
    msg.height = 1
    msg.width = int(points.shape[0])
    msg.fields = [PointField(name=name, offset=offset, datatype=datatype, count=1)
                  for name, offset, datatype in _fields(points)]
    msg.is_bigendian = sys.byteorder == 'big'
    msg.point_step = points.dtype.itemsize
    msg.row_step = msg.point_step * msg.width
    msg.is_dense = True
    msg.data = array.array('B', points.tobytes())
    return msg


def _cdr_align(buffer: bytearray, alignment: int) -> None:
    # CDR aligns relative to the payload, which starts after the 4-byte encapsulation.
    buffer.extend(b'\0' * (-(len(buffer) - 4) % alignment))


def _cdr_string(buffer: bytearray, text: str) -> None:
    data = text.encode('utf-8') + b'\0'
    _cdr_align(buffer, 4)
    buffer.extend(struct.pack('<I', len(data)))
    buffer.extend(data)


def serialize_point_cloud2(points: np.ndarray, frame_id: str, sec: int, nanosec: int) -> bytes:
    """The little-endian CDR of the PointCloud2 ``to_point_cloud2`` would build, for
    ``publisher.publish(bytes)``; one copy of the point data."""
    if sys.byteorder != 'little':
        raise NotImplementedError('serialize_point_cloud2 writes little-endian CDR only')
    points = _native(points)
    head = bytearray(b'\x00\x01\x00\x00')  # CDR little-endian, no options
    head.extend(struct.pack('<iI', sec, nanosec))
    _cdr_string(head, frame_id)
    _cdr_align(head, 4)
    fields = _fields(points)
    head.extend(struct.pack('<III', 1, points.shape[0], len(fields)))  # height, width, fields
    for name, offset, datatype in fields:
        _cdr_string(head, name)
        _cdr_align(head, 4)
        head.extend(struct.pack('<IB', offset, datatype))
        _cdr_align(head, 4)
        head.extend(struct.pack('<I', 1))  # count
    head.extend(struct.pack('<?', False))  # is_bigendian
    _cdr_align(head, 4)
    size = points.dtype.itemsize * points.shape[0]
    head.extend(struct.pack('<III', points.dtype.itemsize, size, size))  # steps, data length
    return b''.join((head, memoryview(points).cast('B'), b'\x01'))  # ..., is_dense


def from_point_cloud2(msg: PointCloud2) -> np.ndarray:
    """The points of a cloud as a structured array, row after row (``points_of_layout``)."""
    layout = [(f.name, f.offset, f.datatype, f.count) for f in msg.fields]
    return points_of_layout(layout, msg.point_step, msg.row_step, msg.width, msg.height,
                            msg.is_bigendian, msg.data)


def points_of_layout(fields: Sequence[tuple[str, int, int, int]], point_step: int,
                     row_step: int, width: int, height: int, is_bigendian: bool,
                     data) -> np.ndarray:
    """The ``width * height`` points a PointCloud2's layout describes, as a structured array.

    ``fields`` are (name, offset, PointField datatype, count); a field of count > 1 becomes
    a subarray. A view of ``data`` when the rows are contiguous and in this machine's byte
    order, else a copy in native order. ValueError says what does not fit: an unknown
    datatype, a field beyond ``point_step``, a ``row_step`` shorter than a row, or data
    shorter than the rows need.
    """
    if point_step > _MAX_ITEMSIZE:
        raise ValueError(f'point_step {point_step} is beyond {_MAX_ITEMSIZE} bytes')
    names, formats, offsets = [], [], []
    order = '>' if is_bigendian else '<'
    for name, offset, datatype, count in fields:
        if datatype not in _FROM_POINTFIELD:
            raise ValueError(f'field {name!r}: unknown PointField datatype {datatype}')
        if count < 1:
            raise ValueError(f'field {name!r}: count {count} (at least 1)')
        element = _FROM_POINTFIELD[datatype].newbyteorder(order)
        size = element.itemsize * count
        if offset + size > point_step:
            raise ValueError(f'field {name!r}: bytes {offset}..{offset + size} do not fit in '
                             f'a point of {point_step} bytes')
        if not name or name in names:
            raise ValueError(f'field {name!r}: field names must be non-empty and unique')
        names.append(name)
        formats.append(element if count == 1 else (element, (count,)))
        offsets.append(offset)
    dtype = np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                      'itemsize': point_step})
    points = width * height
    if points == 0:
        return np.empty(0, dtype=_native_dtype(dtype))
    if point_step == 0:
        raise ValueError(f'point_step is 0 for {points} points')
    row = width * point_step
    if height > 1 and row_step < row:
        raise ValueError(f'row_step {row_step} is shorter than a row ({width} points of '
                         f'{point_step} bytes)')
    step = row_step if height > 1 else row
    need = step * (height - 1) + row
    buffer = memoryview(data).cast('B') if not isinstance(data, (bytes, bytearray)) else data
    if len(buffer) < need:
        raise ValueError(f'data is {len(buffer)} bytes; {height} row(s) of {width} points of '
                         f'{point_step} bytes need {need}')
    if step == row:
        array = np.frombuffer(buffer, dtype=dtype, count=points)
    else:  # padded rows (an organised cloud): gather them
        array = np.ndarray((height, width), dtype=dtype, buffer=buffer,
                           strides=(step, point_step)).reshape(points)
    native = _native_dtype(dtype)
    return array if native == dtype else array.astype(native)


def _native_dtype(dtype: np.dtype) -> np.dtype:
    return np.dtype({'names': list(dtype.names),
                     'formats': [dtype.fields[n][0].newbyteorder('=') for n in dtype.names],
                     'offsets': [dtype.fields[n][1] for n in dtype.names],
                     'itemsize': dtype.itemsize})


class DecodedCloud(NamedTuple):
    """A PointCloud2 read straight from its CDR: the points and the header."""

    points: np.ndarray
    frame_id: str
    sec: int
    nanosec: int


class _CdrReader:
    """Reads CDR fields in order, aligned relative to the payload (byte 4 on)."""

    def __init__(self, data) -> None:
        self.data = memoryview(data).cast('B')
        self.byteorder = 'little' if byte_order(self.data, 'PointCloud2') == '<' else 'big'
        self.offset = ENCAPSULATION

    def take(self, size: int, what: str, alignment: int = 1) -> memoryview:
        start = self.offset + (-(self.offset - ENCAPSULATION) % alignment)
        end = start + size
        if end > len(self.data):
            raise ValueError(f'PointCloud2 CDR truncated: {what} needs bytes {start}..{end} '
                             f'of {len(self.data)}')
        self.offset = end
        return self.data[start:end]

    def uint32(self, what: str) -> int:
        return int.from_bytes(self.take(4, what, 4), self.byteorder)

    def int32(self, what: str) -> int:
        return int.from_bytes(self.take(4, what, 4), self.byteorder, signed=True)

    def uint8(self, what: str) -> int:
        return self.take(1, what)[0]

    def string(self, what: str) -> str:
        length = self.uint32(f'the length of {what}')
        return decode_string(bytes(self.take(length, what)), what, 'PointCloud2')


_FIELD_CDR_MIN = 13  # name length (4) + offset (4) + datatype (1) + count (4)


def decode_point_cloud2(data) -> DecodedCloud:
    """Points and header of a serialized sensor_msgs/PointCloud2 (either CDR byte order).

    What ``from_point_cloud2(deserialize_message(data, PointCloud2))`` gives, without
    building the message (no copy of the data when it is contiguous) and with a ValueError
    that says what is wrong where rclpy prints to stderr and raises RMWError.
    """
    cdr = _CdrReader(data)
    sec = cdr.int32('header.stamp.sec')
    nanosec = cdr.uint32('header.stamp.nanosec')
    frame_id = cdr.string('header.frame_id')
    height = cdr.uint32('height')
    width = cdr.uint32('width')
    count = cdr.uint32('the number of fields')
    if count * _FIELD_CDR_MIN > len(cdr.data) - cdr.offset:
        raise ValueError(f'PointCloud2 CDR malformed: {count} fields cannot fit in the '
                         f'{len(cdr.data) - cdr.offset} bytes left')
    fields = []
    for index in range(count):
        name = cdr.string(f'the name of field {index}')
        fields.append((name, cdr.uint32(f'field {name!r} offset'),
                       cdr.uint8(f'field {name!r} datatype'),
                       cdr.uint32(f'field {name!r} count')))
    is_bigendian = cdr.uint8('is_bigendian')
    point_step = cdr.uint32('point_step')
    row_step = cdr.uint32('row_step')
    size = cdr.uint32('the length of data')
    payload = cdr.take(size, 'data')
    cdr.uint8('is_dense')
    if is_bigendian > 1:
        raise ValueError(f'PointCloud2 CDR malformed: is_bigendian is {is_bigendian}')
    points = points_of_layout(fields, point_step, row_step, width, height, bool(is_bigendian),
                              payload)
    return DecodedCloud(points, frame_id, sec, nanosec)
