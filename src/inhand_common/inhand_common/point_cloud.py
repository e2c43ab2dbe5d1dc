"""numpy structured arrays <-> sensor_msgs/PointCloud2, without sensor_msgs_py.

The pip ROS wheels have no ``sensor_msgs_py``; this is the small part of it we need, with
the fast path: ``data`` is set from an ``array.array('B', ...)`` built straight from the
array's bytes (assigning a bytes object or a list makes rclpy check every element).
"""

from __future__ import annotations

import array
import sys

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

__all__ = ['to_point_cloud2', 'from_point_cloud2', 'pack_rgb']

_TO_POINTFIELD = {
    np.dtype('int8'): PointField.INT8, np.dtype('uint8'): PointField.UINT8,
    np.dtype('int16'): PointField.INT16, np.dtype('uint16'): PointField.UINT16,
    np.dtype('int32'): PointField.INT32, np.dtype('uint32'): PointField.UINT32,
    np.dtype('float32'): PointField.FLOAT32, np.dtype('float64'): PointField.FLOAT64,
}
_FROM_POINTFIELD = {v: k for k, v in _TO_POINTFIELD.items()}


def to_point_cloud2(points: np.ndarray, frame_id: str, stamp) -> PointCloud2:
    """An unorganised cloud (height 1) from a structured array of scalar fields."""
    points = np.ascontiguousarray(points)
    if points.dtype.names is None:
        raise TypeError('to_point_cloud2 needs a structured array (named fields)')
    fields = []
    for name in points.dtype.names:
        dtype, offset = points.dtype.fields[name][:2]
        base = dtype.newbyteorder('=') if dtype.byteorder not in ('=', '|') else dtype
        fields.append(PointField(name=name, offset=offset, datatype=_TO_POINTFIELD[base],
                                 count=1))
    msg = PointCloud2()
    msg.header.frame_id = frame_id
    msg.header.stamp = stamp
    msg.height = 1
    msg.width = int(points.shape[0])
    msg.fields = fields
    msg.is_bigendian = sys.byteorder == 'big'
    msg.point_step = points.dtype.itemsize
    msg.row_step = msg.point_step * msg.width
    msg.is_dense = True
    msg.data = array.array('B', points.tobytes())
    return msg


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


def pack_rgb(red, green, blue) -> np.ndarray:
    """float32 holding packed 0x00RRGGBB: the PCL/RViz ``rgb`` field convention."""
    packed = (np.asarray(red, dtype=np.uint32) << 16) | \
        (np.asarray(green, dtype=np.uint32) << 8) | np.asarray(blue, dtype=np.uint32)
    return packed.astype(np.uint32).view(np.float32)
