"""The two parts of plain CDR that every decoder here reads the same way.

``sensor_msgs/PointCloud2`` (``point_cloud.py``) and ``geometry_msgs/PoseStamped``
(``inhand_mapping/pose_cdr.py``) are read straight from their serialized bytes. Both start
with the 4-byte encapsulation header that says the byte order, and both hold strings; a
string must come out as rclpy gives it to a node, or the two decoders (and our encoders)
would disagree about the same bytes. No rclpy here.
"""

from __future__ import annotations

__all__ = ['CDR_BE', 'CDR_LE', 'ENCAPSULATION', 'byte_order', 'decode_string']

CDR_BE = 0x0000
CDR_LE = 0x0001
ENCAPSULATION = 4   # bytes: representation id (big-endian), then 2 option bytes


def byte_order(data, type_name: str) -> str:
    """``'<'`` or ``'>'``, the byte order the encapsulation header of ``data`` gives;
    ValueError naming ``type_name`` for a buffer too short or another representation."""
    if len(data) < ENCAPSULATION:
        raise ValueError(f'{type_name} CDR truncated: {len(data)} bytes, no encapsulation '
                         'header')
    kind = (data[0] << 8) | data[1]
    if kind == CDR_LE:
        return '<'
    if kind == CDR_BE:
        return '>'
    raise ValueError(f'unsupported CDR encapsulation 0x{kind:04x} (expected 0x0001 CDR_LE '
                     f'or 0x0000 CDR_BE; XCDR2 and parameter lists are not {type_name})')


def decode_string(field: bytes, what: str, type_name: str) -> str:
    """A CDR string from its ``field`` bytes (the length's worth, terminator included):
    up to the first NUL, as rclpy reads it. ValueError naming ``what`` when it is not
    NUL-terminated or not UTF-8. An empty field is the empty string (some writers encode it
    as length 0)."""
    if not field:
        return ''
    if field[-1] != 0:
        raise ValueError(f'{type_name} CDR malformed: {what} is not NUL-terminated')
    try:
        return field[:field.index(0)].decode('utf-8')
    except UnicodeDecodeError as error:
        raise ValueError(f'{type_name} CDR malformed: {what} is not UTF-8 ({error})') from None
