"""Readable text of ROS messages for ``topic_echo``: YAML-like, as ``ros2 topic echo`` prints.

Nested messages are indented two spaces per level, arrays of numbers are one flow list
cut to the first ``array_limit`` items (unless ``full_length``) with the count, arrays of
messages are block lists, and ``no_arr`` replaces every array by its type and length.
float32 fields are printed at float32 precision (0.1, not 0.10000000149011612).
A ``sensor_msgs/PointCloud2`` anywhere in a message is shown as its header, size and
fields, and its first points decoded (``inhand_common.point_cloud.from_point_cloud2``)
in place of the data bytes.

Field paths: ``pose.position.x``, ``fields[0].name``, ``data[-1]``; checked against the
message type before anything is received (``check_field_path``).
"""

from __future__ import annotations

import array
import json
import re
from dataclasses import dataclass

import numpy as np

__all__ = ['FieldPathError', 'Options', 'check_field_path', 'format_message', 'get_field',
           'is_scalar', 'parse_field_path', 'type_name']

_PART = re.compile(r'([A-Za-z_][A-Za-z0-9_]*)?((?:\[-?\d+\])*)$')
_INDEX = re.compile(r'\[(-?\d+)\]')
_POINTFIELD_TYPES = {1: 'INT8', 2: 'UINT8', 3: 'INT16', 4: 'UINT16', 5: 'INT32', 6: 'UINT32',
                     7: 'FLOAT32', 8: 'FLOAT64'}
_YAML_PLAIN = re.compile(r'^[A-Za-z_/][A-Za-z0-9_./ -]*$')
_YAML_WORDS = {'true', 'false', 'yes', 'no', 'on', 'off', 'null', '~', 'y', 'n'}


class FieldPathError(ValueError):
    """A --field path that does not fit the message type."""


@dataclass
class Options:
    array_limit: int = 16
    full_length: bool = False
    no_arr: bool = False
    points: int = 5


def type_name(cls) -> str:
    """'pkg/msg/Type' of an rclpy message class."""
    return f'{cls.__module__.split(".")[0]}/msg/{cls.__name__}'


def parse_field_path(text: str) -> list[str | int]:
    """'a.b[2].c' -> ['a', 'b', 2, 'c']; FieldPathError if malformed."""
    path: list[str | int] = []
    for part in text.split('.'):
        match = _PART.match(part)
        if not part or not match or (not match.group(1) and not match.group(2)) or \
                (not match.group(1) and not path):
            raise FieldPathError(f"--field '{text}': expected names and [index] separated by "
                                 "dots, like pose.position.x or fields[0].name")
        if match.group(1):
            path.append(match.group(1))
        path.extend(int(i) for i in _INDEX.findall(match.group(2)))
    return path


# -- types ---------------------------------------------------------------------------------

def _parse_type(text: str):
    """('msg', cls) | ('seq', element) | ('prim', name) from a field type string."""
    text = text.strip()
    if text.startswith('sequence<') and text.endswith('>'):
        inner = text[len('sequence<'):-1].rsplit(',', 1)[0] if ',' in text else \
            text[len('sequence<'):-1]
        return ('seq', _parse_type(inner))
    bracket = re.match(r'^(.*)\[\d*\]$', text)
    if bracket:
        return ('seq', _parse_type(bracket.group(1)))
    if '/' in text:
        from inhand_tools.message_types import message_class
        return ('msg', message_class(text))
    return ('prim', text)


def _fields(cls) -> dict[str, str]:
    return dict(cls.get_fields_and_field_types())


def _describe(kind) -> str:
    if kind[0] == 'msg':
        return type_name(kind[1])
    if kind[0] == 'seq':
        return f'an array of {_describe(kind[1])}'
    return kind[1]


def check_field_path(cls, path: list[str | int], text: str = '') -> str:
    """FieldPathError unless ``path`` names a field of messages of type ``cls``; returns
    the field's type ('float64', 'geometry_msgs/msg/Point', 'array of uint8' ...)."""
    kind = ('msg', cls)
    shown = text or '.'.join(map(str, path))
    for part in path:
        if isinstance(part, int):
            if kind[0] != 'seq':
                raise FieldPathError(f"--field '{shown}': [{part}] indexes {_describe(kind)}, "
                                     'which is not an array')
            kind = kind[1]
            continue
        if kind[0] != 'msg':
            raise FieldPathError(f"--field '{shown}': {_describe(kind)} has no field '{part}'")
        fields = _fields(kind[1])
        if part not in fields:
            raise FieldPathError(f"--field '{shown}': no field '{part}' in "
                                 f"{type_name(kind[1])}; it has {', '.join(fields)}")
        kind = _parse_type(fields[part])
    return _primitive(kind)


def _primitive(kind) -> str:
    if kind[0] == 'prim':
        return kind[1]
    if kind[0] == 'seq':
        return f'sequence<{_primitive(kind[1])}>'
    return type_name(kind[1])


def get_field(msg, path: list[str | int]):
    """The value at ``path`` (IndexError with a readable message if an index is out)."""
    value = msg
    for part in path:
        if isinstance(part, int):
            if not -len(value) <= part < len(value):
                raise IndexError(f'[{part}] is out of range: the array has {len(value)} items')
            value = value[part]
        else:
            value = getattr(value, part)
    return value


def is_scalar(value) -> bool:
    return not hasattr(value, 'get_fields_and_field_types') and not _is_array(value)


# -- formatting ------------------------------------------------------------------------------

def _is_array(value) -> bool:
    return isinstance(value, (list, tuple, array.array, np.ndarray, bytes, bytearray))


def _scalar(value, field_type: str = '') -> str:
    if isinstance(value, (bool, np.bool_)):
        return 'true' if value else 'false'
    if isinstance(value, (bytes, bytearray)) and len(value) == 1:  # a 'byte' element
        return str(value[0])
    if isinstance(value, (float, np.floating)):
        if field_type == 'float' or isinstance(value, np.float32):
            return str(np.float32(value))
        return repr(float(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, str):
        return _string(value)
    return str(value)


def _string(text: str) -> str:
    if _YAML_PLAIN.match(text) and text.lower() not in _YAML_WORDS and \
            not text.endswith(' ') and ': ' not in text:
        return text
    if not text.isprintable():
        return json.dumps(text)  # a YAML double-quoted scalar with escapes (newlines ...)
    return "'" + text.replace("'", "''") + "'"


def _element_type(field_type: str) -> str:
    kind = field_type
    if kind.startswith('sequence<'):
        kind = kind[len('sequence<'):-1].split(',')[0]
    return re.sub(r'\[\d*\]$', '', kind)


def _array_items(value) -> list:
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    return list(value) if not isinstance(value, np.ndarray) else value.tolist()


def _flow_array(value, field_type: str, options: Options) -> str:
    element = _element_type(field_type)
    length = len(value)
    if options.no_arr:
        return f'<array of {element or "items"}, {length} items>'
    if length == 0:
        return '[]'
    shown = value if options.full_length or length <= options.array_limit \
        else value[:options.array_limit]
    items = ', '.join(_scalar(v, element) for v in _array_items(shown))
    if len(shown) < length:
        return f'[{items}, ...]  # {length} items'
    return f'[{items}]'


def _is_point_cloud(msg) -> bool:
    return type(msg).__name__ == 'PointCloud2' and type(msg).__module__.startswith('sensor_msgs')


def _message_lines(msg, options: Options, indent: str) -> list[str]:
    if _is_point_cloud(msg):
        return _cloud_lines(msg, options, indent)
    lines = []
    for name, field_type in _fields(type(msg)).items():
        lines.extend(_field_lines(name, getattr(msg, name), field_type, options, indent))
    return lines


def _is_array_type(field_type: str) -> bool:
    return field_type.startswith('sequence<') or field_type.endswith(']')


def _field_lines(name: str, value, field_type: str, options: Options, indent: str) -> list[str]:
    if hasattr(value, 'get_fields_and_field_types'):
        nested = _message_lines(value, options, indent + '  ')
        return [f'{indent}{name}:', *nested] if nested else [f'{indent}{name}: {{}}']
    if _is_array(value) and (_is_array_type(field_type) or not isinstance(value, bytes)):
        items = _array_items(value) if not isinstance(value, np.ndarray) else value
        if len(items) and hasattr(items[0], 'get_fields_and_field_types'):
            return [f'{indent}{name}:', *_message_list(items, field_type, options, indent)]
        return [f'{indent}{name}: {_flow_array(value, field_type, options)}']
    return [f'{indent}{name}: {_scalar(value, field_type)}']


def _message_list(items, field_type: str, options: Options, indent: str) -> list[str]:
    if options.no_arr:
        return [f'{indent}  <array of {_element_type(field_type)}, {len(items)} items>']
    shown = items if options.full_length or len(items) <= options.array_limit \
        else items[:options.array_limit]
    lines = []
    for item in shown:
        body = _message_lines(item, options, indent + '  ')
        if body:
            lines.append(f'{indent}- {body[0][len(indent) + 2:]}')
            lines.extend(body[1:])
        else:
            lines.append(f'{indent}- {{}}')
    if len(shown) < len(items):
        lines.append(f'{indent}# ... {len(items) - len(shown)} more, {len(items)} items in all')
    return lines


def _cloud_lines(msg, options: Options, indent: str) -> list[str]:
    lines = _field_lines('header', msg.header, 'std_msgs/Header', options, indent)
    lines += [f'{indent}height: {msg.height}', f'{indent}width: {msg.width}']
    lines.append(f'{indent}fields:' if msg.fields else f'{indent}fields: []')
    for f in msg.fields:
        kind = _POINTFIELD_TYPES.get(f.datatype, str(f.datatype))
        lines.append(f'{indent}- {{name: {_string(f.name)}, offset: {f.offset}, '
                     f'datatype: {kind}, count: {f.count}}}')
    lines += [f'{indent}is_bigendian: {_scalar(msg.is_bigendian)}',
              f'{indent}point_step: {msg.point_step}', f'{indent}row_step: {msg.row_step}',
              f'{indent}data: <{len(msg.data)} bytes, decoded below>',
              f'{indent}is_dense: {_scalar(msg.is_dense)}']
    total = msg.width * msg.height
    try:
        from inhand_common.point_cloud import from_point_cloud2
        points = from_point_cloud2(msg)
    except ValueError as error:
        # A layout it cannot decode, refused by from_point_cloud2 or numpy (a field name
        # used twice, a field past point_step, data shorter than the points): say why
        # instead of failing.
        return [*lines, f'{indent}points: <not decoded: {error}>']
    count = total if options.full_length else min(total, options.points)
    if total == 0:
        return [*lines, f'{indent}points: []']
    lines.append(f'{indent}points:  # first {count} of {total}' if count < total
                 else f'{indent}points:  # all {total}')
    names = points.dtype.names
    for point in points.reshape(-1)[:count]:
        values = ', '.join(f'{n}: {_scalar(point[n])}' for n in names)
        lines.append(f'{indent}- {{{values}}}')
    return lines


def format_message(value, options: Options | None = None, field_type: str = '') -> str:
    """The text of a message, or of a field value picked with --field (of ``field_type``,
    as ``check_field_path`` returns it)."""
    options = options or Options()
    if hasattr(value, 'get_fields_and_field_types'):
        return '\n'.join(_message_lines(value, options, ''))
    if _is_array(value):
        items = _array_items(value) if not isinstance(value, np.ndarray) else value
        if len(items) and hasattr(items[0], 'get_fields_and_field_types'):
            return '\n'.join(_message_list(items, field_type, options, ''))
        return _flow_array(value, field_type, options)
    return _scalar(value, field_type)
