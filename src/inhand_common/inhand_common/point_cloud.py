"""numpy structured arrays <-> sensor_msgs/PointCloud2, without sensor_msgs_py.

The pip ROS wheels have no ``sensor_msgs_py``; this is the part of it we need, plus a
direct CDR writer for big clouds: ``serialize_point_cloud2`` builds the serialized message
with one copy of the point data, and ``publisher.publish(those_bytes)`` hands it to DDS
as is. Going through a message object instead costs three more copies of the data (the
array's bytes, ``array.array``, the ``data`` setter's own copy) and rclpy's conversion:
for a full 70^3 map (8 MB) that is most of the time a publication takes.
"""

from __future__ import annotations

import array
import struct
import sys

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

__all__ = ['from_point_cloud2', 'serialize_point_cloud2', 'to_point_cloud2']

_TO_POINTFIELD = {
    np.dtype('int8'): PointField.INT8, np.dtype('uint8'): PointField.UINT8,
    np.dtype('int16'): PointField.INT16, np.dtype('uint16'): PointField.UINT16,
    np.dtype('int32'): PointField.INT32, np.dtype('uint32'): PointField.UINT32,
    np.dtype('float32'): PointField.FLOAT32, np.dtype('float64'): PointField.FLOAT64,
}
_FROM_POINTFIELD = {v: k for k, v in _TO_POINTFIELD.items()}


def _native(points: np.ndarray) -> np.ndarray:
    """The array with every field in this machine's byte order (the message says which)."""
    if points.dtype.names is None:
        raise TypeError('a point cloud needs a structured array (named fields)')
    fields = points.dtype.fields
    if all(fields[name][0].byteorder in ('=', '|') for name in points.dtype.names):
        return np.ascontiguousarray(points)
    native = np.dtype({'names': list(points.dtype.names),
                       'formats': [fields[n][0].newbyteorder('=') for n in points.dtype.names],
                       'offsets': [fields[n][1] for n in points.dtype.names],
                       'itemsize': points.dtype.itemsize})
    return np.ascontiguousarray(points.astype(native))


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
    """The points of a cloud as a structured array (a view of the message's bytes)."""
    if msg.is_bigendian != (sys.byteorder == 'big'):
        raise ValueError('big-endian point clouds are not supported on this machine')
    names, formats, offsets = [], [], []
    for field in msg.fields:
        if field.count != 1 or field.datatype not in _FROM_POINTFIELD:
            raise ValueError(f'field {field.name!r}: unsupported datatype {field.datatype} '
                             f'or count {field.count}')
        names.append(field.name)
        formats.append(_FROM_POINTFIELD[field.datatype])
        offsets.append(field.offset)
    dtype = np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                      'itemsize': msg.point_step})
    count = msg.width * msg.height
    buffer = memoryview(msg.data) if not isinstance(msg.data, (bytes, bytearray)) else msg.data
    return np.frombuffer(buffer, dtype=dtype, count=count)
