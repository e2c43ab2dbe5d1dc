"""The text ``topic_echo`` prints for a message: YAML-like as ``ros2 topic echo`` prints it,
or one CSV line as ``ros2 topic echo --csv`` does; and its ``--filter`` and ``--field`` tests.

YAML: nested messages are indented two spaces per level, arrays of numbers are one flow
list, arrays of messages block lists. Every array and string is printed whole unless
``truncate_length`` cuts it: an array to its first N items and ``...`` with the count in a
comment (``[0.0, 0.5, ...]  # 36 items``), a string to its first N characters and ``...``.
``no_arr`` replaces every array by its type and length and ``no_str`` every string by its
length, in ros2's words (``<sequence type: double, length: 36>``, ``<string length: <5>>``).
float32 fields are printed at float32 precision (0.1, not 0.10000000149011612), byte fields
as numbers.

Bulk data stays summarised unless ``full_length``: a ``sensor_msgs/PointCloud2`` anywhere
in a message is shown as its header, size and fields and its first ``points`` points
decoded (``inhand_common.point_cloud.from_point_cloud2``) in place of the data bytes, and
the ``data`` of a ``sensor_msgs/Image`` or ``CompressedImage`` as its size.
``full_length`` decodes every point, prints those bytes, and overrides
``truncate_length`` (as ros2's ``--full-length``).

CSV (``format_csv``): every field in message order, nested messages and arrays flattened
item by item, separated by commas (as ``rosidl_runtime_py.message_to_csv``: an empty array
is an empty value, a cut array ends in ``...``, booleans are True/False); a value holding a
comma, quote or line break is quoted as CSV quotes it.

Filter (``compile_filter``): a Python expression of ``m``, the message (or the ``--field``
value, as in ros2), with Python's builtins; a message is printed when it is true.

Field paths: ``pose.position.x``, ``fields[0].name``, ``data[-1]``; checked against the
message type before anything is received (``check_field_path``).

No rclpy import: the command checks its arguments with this module before ROS starts.
"""

from __future__ import annotations

import array
import ast
import builtins
import json
import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ['FieldPathError', 'FilterError', 'Options', 'check_field_path', 'compile_filter',
           'echo_text', 'format_csv', 'format_message', 'get_field', 'is_scalar',
           'parse_field_path', 'type_name']

_PART = re.compile(r'([A-Za-z_][A-Za-z0-9_]*)?((?:\[-?\d+\])*)$')
_INDEX = re.compile(r'\[(-?\d+)\]')
_SEQUENCE = re.compile(r'^sequence<(.+?)(?:,\s*(\d+))?>$')
_FIXED = re.compile(r'^(.+)\[(\d+)\]$')
_POINTFIELD_TYPES = {1: 'INT8', 2: 'UINT8', 3: 'INT16', 4: 'UINT16', 5: 'INT32', 6: 'UINT32',
                     7: 'FLOAT32', 8: 'FLOAT64'}
_YAML_PLAIN = re.compile(r'^[A-Za-z_/][A-Za-z0-9_./ -]*$')
_YAML_WORDS = {'true', 'false', 'yes', 'no', 'on', 'off', 'null', '~', 'y', 'n'}
# Byte fields printed as their size unless full_length: (package, message) -> field.
_BULK_FIELDS = {('sensor_msgs', 'Image'): 'data', ('sensor_msgs', 'CompressedImage'): 'data',
                ('sensor_msgs', 'PointCloud2'): 'data'}
TRUNCATED = '...'


class FieldPathError(ValueError):
    """A --field path that does not fit the message type."""


class FilterError(ValueError):
    """A --filter expression that is not Python, names something unknown, or fails on a
    message."""


@dataclass
class Options:
    truncate_length: int | None = None  # arrays and strings cut to this length; None: whole
    full_length: bool = False           # everything whole, bulk data too (overrides the above)
    no_arr: bool = False                # arrays as their type and length
    no_str: bool = False                # strings as their length
    points: int = 5                     # PointCloud2: how many points to decode
    csv: bool = False                   # one CSV line per message instead of YAML

    @property
    def limit(self) -> int | None:
        return None if self.full_length else self.truncate_length


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


# -- the filter ------------------------------------------------------------------------------

def _free_names(tree: ast.AST) -> set[str]:
    """Names an expression reads that it does not bind itself (comprehension variables,
    lambda arguments, walrus targets)."""
    read, bound = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            (read if isinstance(node.ctx, ast.Load) else bound).add(node.id)
        elif isinstance(node, ast.arg):
            bound.add(node.arg)
    return read - bound


def compile_filter(expression: str) -> Callable[[object], bool]:
    """``--filter``: a test of ``m`` (a message or field value); FilterError now if the
    expression is not Python or reads a name other than ``m`` and the builtins, and when
    called if it fails on a message."""
    shown = f"--filter '{expression}'"
    try:
        tree = ast.parse(expression.strip(), '<--filter>', mode='eval')
    except SyntaxError as error:
        raise FilterError(f'{shown}: not a Python expression ({error.msg})') from None
    unknown = sorted(_free_names(tree) - {'m'} - set(dir(builtins)))
    if unknown:
        raise FilterError(f"{shown}: unknown name {', '.join(unknown)} (the message is m, "
                          "as in m.data > 3)")
    code = compile(tree, '<--filter>', 'eval')

    def accept(m) -> bool:
        try:
            # m among the globals, so comprehensions and lambdas in the expression see it
            return bool(eval(code, {'m': m}))
        except Exception as error:  # whatever the user's expression raises
            raise FilterError(f'{shown}: {type(error).__name__}: {error}') from None

    return accept


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


def _is_message(value) -> bool:
    return hasattr(value, 'get_fields_and_field_types')


def is_scalar(value) -> bool:
    return not _is_message(value) and not _is_array(value)


def _is_array(value) -> bool:
    return isinstance(value, (list, tuple, array.array, np.ndarray, bytes, bytearray))


def _is_array_type(field_type: str) -> bool:
    return field_type.startswith('sequence<') or field_type.endswith(']')


def _is_array_value(value, field_type: str) -> bool:
    """An array, not a ``byte`` field (one-byte ``bytes``)."""
    return _is_array(value) and (_is_array_type(field_type) or not isinstance(value, bytes))


def _element_type(field_type: str) -> str:
    kind = field_type
    if kind.startswith('sequence<'):
        kind = kind[len('sequence<'):-1].split(',')[0]
    return re.sub(r'\[\d*\]$', '', kind)


def _ros_type(element: str) -> str:
    """A field type as ros2 names it: 'diagnostic_msgs/KeyValue' -> '.../msg/KeyValue'."""
    parts = element.split('/')
    return f'{parts[0]}/msg/{parts[1]}' if len(parts) == 2 else element


def _array_info(field_type: str, length: int) -> str:
    """An array left out (no_arr), in ros2's words."""
    sequence = _SEQUENCE.match(field_type)
    if sequence:
        element, bound = sequence.groups()
        bounded = f'[{bound}]' if bound else ''
        return f'<sequence type: {_ros_type(element)}{bounded}, length: {length}>'
    fixed = _FIXED.match(field_type)
    if fixed:
        return f'<array type: {_ros_type(fixed.group(1))}[{fixed.group(2)}]>'
    return f'<sequence type: {_ros_type(field_type) or "unknown"}, length: {length}>'


def _bulk_size(msg, name: str, options: Options) -> str | None:
    """'<N bytes ...>' if field ``name`` of ``msg`` is bulk data left summarised, else None."""
    cls = type(msg)
    if options.full_length or options.no_arr or \
            _BULK_FIELDS.get((cls.__module__.split('.')[0], cls.__name__)) != name:
        return None
    return f'<{len(getattr(msg, name))} bytes; --full-length shows them>'


def _cut(items, options: Options):
    """(the items shown, whether some were cut)."""
    limit = options.limit
    if limit is None or len(items) <= limit:
        return items, False
    return items[:limit], True


def _array_items(value) -> list:
    if isinstance(value, np.ndarray):
        return value.tolist()
    return list(value)


def _clip(text: str, options: Options) -> str:
    if options.no_str:
        return f'<string length: <{len(text)}>>'
    limit = options.limit
    return text if limit is None or len(text) <= limit else text[:limit] + TRUNCATED


# -- YAML ------------------------------------------------------------------------------------

def _scalar(value, field_type: str = '', options: Options | None = None) -> str:
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
        return _string(_clip(value, options) if options else value)
    return str(value)


def _string(text: str) -> str:
    if _YAML_PLAIN.match(text) and text.lower() not in _YAML_WORDS and \
            not text.endswith(' ') and ': ' not in text:
        return text
    if not text.isprintable():
        return json.dumps(text)  # a YAML double-quoted scalar with escapes (newlines ...)
    return "'" + text.replace("'", "''") + "'"


def _flow_array(value, field_type: str, options: Options) -> str:
    if options.no_arr:
        return _string(_array_info(field_type, len(value)))
    element = _element_type(field_type)
    items = _array_items(value)
    shown, cut = _cut(items, options)
    text = ', '.join([_scalar(v, element, options) for v in shown] + ([TRUNCATED] if cut else []))
    return f'[{text}]  # {len(items)} items' if cut else f'[{text}]'


def _is_point_cloud(msg) -> bool:
    return type(msg).__name__ == 'PointCloud2' and type(msg).__module__.startswith('sensor_msgs')


def _message_lines(msg, options: Options, indent: str) -> list[str]:
    if _is_point_cloud(msg):
        return _cloud_lines(msg, options, indent)
    lines = []
    for name, field_type in _fields(type(msg)).items():
        size = _bulk_size(msg, name, options)
        if size is not None:
            lines.append(f'{indent}{name}: {size}')
        else:
            lines.extend(_field_lines(name, getattr(msg, name), field_type, options, indent))
    return lines


def _field_lines(name: str, value, field_type: str, options: Options, indent: str) -> list[str]:
    if _is_message(value):
        nested = _message_lines(value, options, indent + '  ')
        return [f'{indent}{name}:', *nested] if nested else [f'{indent}{name}: {{}}']
    if _is_array_value(value, field_type):
        if len(value) and not options.no_arr and _is_message(value[0]):
            return [f'{indent}{name}:', *_message_list(value, options, indent)]
        return [f'{indent}{name}: {_flow_array(value, field_type, options)}']
    return [f'{indent}{name}: {_scalar(value, field_type, options)}']


def _message_list(items, options: Options, indent: str) -> list[str]:
    shown, cut = _cut(items, options)
    lines = []
    for item in shown:
        body = _message_lines(item, options, indent + '  ')
        if body:
            lines.append(f'{indent}- {body[0][len(indent) + 2:]}')
            lines.extend(body[1:])
        else:
            lines.append(f'{indent}- {{}}')
    if cut:
        lines.append(f'{indent}- {TRUNCATED}  # {len(items)} items')
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
    """The YAML-like text of a message, or of a field value picked with --field (of
    ``field_type``, as ``check_field_path`` returns it)."""
    options = options or Options()
    if _is_message(value):
        return '\n'.join(_message_lines(value, options, ''))
    if _is_array_value(value, field_type):
        if len(value) and not options.no_arr and _is_message(value[0]):
            return '\n'.join(_message_list(value, options, ''))
        return _flow_array(value, field_type, options)
    return _scalar(value, field_type, options)


# -- CSV -------------------------------------------------------------------------------------

def _csv_quote(text: str) -> str:
    if any(c in text for c in ',"\n\r'):
        return '"' + text.replace('"', '""') + '"'
    return text


def _csv_scalar(value, field_type: str, options: Options) -> str:
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, str):
        return _csv_quote(_clip(value, options))
    return _scalar(value, field_type)


def format_csv(value, options: Options | None = None, field_type: str = '') -> str:
    """A message (or a --field value of ``field_type``) as one line of comma-separated
    values: its fields in order, nested messages and arrays flattened."""
    options = options or Options()
    if _is_message(value):
        return ','.join(
            size if (size := _bulk_size(value, name, options)) is not None
            else format_csv(getattr(value, name), options, kind)
            for name, kind in _fields(type(value)).items())
    if _is_array_value(value, field_type):
        if options.no_arr:
            return _csv_quote(_array_info(field_type, len(value)))
        shown, cut = _cut(_array_items(value), options)
        element = _element_type(field_type)
        return ','.join([format_csv(v, options, element) for v in shown] +
                        ([TRUNCATED] if cut else []))
    return _csv_scalar(value, field_type, options)


def echo_text(value, options: Options, field_type: str = '') -> tuple[str, bool]:
    """What ``topic_echo`` prints for a message or --field value, and whether it is a line
    of its own (CSV, or a single value) rather than a document ended by ``---``."""
    if options.csv:
        return format_csv(value, options, field_type), True
    if isinstance(value, str):
        return _clip(value, options), True
    return format_message(value, options, field_type), is_scalar(value)
