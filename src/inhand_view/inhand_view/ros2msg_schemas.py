"""Complete ROS 2 message definitions in the ``ros2msg`` schema encoding (plain Python, no ROS).

Foxglove (and Lichtblick) decode a channel's CDR with the schema the server advertises. For
ROS 2 types that schema is the ``ros2msg`` text rosbag2 writes into MCAP files: the type's
``.msg`` file as it is, then every type it uses, depth first, each once, each after a
two-line delimiter (a line of 80 ``=`` and ``MSG: <type as the .msg names it>``)::

    std_msgs/Header header
    ...
    ================================================================================
    MSG: std_msgs/Header
    builtin_interfaces/Time stamp
    string frame_id
    ================================================================================
    MSG: builtin_interfaces/Time
    ...

The ``.msg`` and ``.srv`` files come from ``share/<package>/msg|srv/`` of every prefix on
``AMENT_PREFIX_PATH`` (a full ROS install, a colcon workspace) and of this Python's prefix
(the pip wheels install them under ``.venv/share/``).
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path

__all__ = ['DELIMITER', 'DefinitionNotFound', 'MessageDefinitions', 'default_search_paths',
           'field_types', 'split_type_name']

DELIMITER = '=' * 80
PRIMITIVE_TYPES = frozenset({
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
    'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring'})
_ARRAY_SUFFIX = re.compile(r'\[[^\]]*\]$')
_SERVICE_SEPARATOR = re.compile(r'^---\s*$', re.M)


class DefinitionNotFound(LookupError):
    """No ``.msg`` / ``.srv`` file for a type (or for a type it uses)."""


def default_search_paths() -> list[Path]:
    """The prefixes whose ``share/`` folders hold interface files: AMENT_PREFIX_PATH's, then
    this Python's (the pip ROS wheels), without repeats."""
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    seen: list[Path] = []
    for prefix in prefixes:
        path = Path(prefix)
        if path not in seen:
            seen.append(path)
    return seen


def split_type_name(type_name: str, kind: str = 'msg') -> tuple[str, str, str]:
    """(package, kind, name) of ``pkg/msg/Type`` or ``pkg/Type`` (``kind`` assumed)."""
    parts = type_name.split('/')
    if len(parts) == 2:
        parts = [parts[0], kind, parts[1]]
    if len(parts) != 3 or not all(parts):
        raise DefinitionNotFound(f"'{type_name}' is not a type name (expected pkg/{kind}/Type)")
    return parts[0], parts[1], parts[2]


def field_types(text: str, package: str) -> list[str]:
    """The message types the fields of a ``.msg`` text use, as ``pkg/Type``, in order of
    first use (primitive types, constants and comments left out; a type without a package
    is of ``package``)."""
    found: list[str] = []
    for line in text.splitlines():
        line = line.split('#', 1)[0].strip()
        if not line:
            continue
        base = _ARRAY_SUFFIX.sub('', line.split()[0]).split('<=', 1)[0]
        if base in PRIMITIVE_TYPES:
            continue
        if base == 'Header':                        # the ROS 1 shorthand some files keep
            base = 'std_msgs/Header'
        elif '/' not in base:
            base = f'{package}/{base}'
        elif base.count('/') == 2:                  # pkg/msg/Type
            pkg, _, name = base.split('/')
            base = f'{pkg}/{name}'
        if base not in found:
            found.append(base)
    return found


class MessageDefinitions:
    """Reads interface files once and builds complete definitions from them."""

    def __init__(self, search_paths: Iterable[Path | str] | None = None):
        self.search_paths = [Path(p) for p in (search_paths if search_paths is not None
                                               else default_search_paths())]
        self._texts: dict[tuple[str, str, str], str] = {}

    def _file_text(self, package: str, kind: str, name: str) -> str:
        key = (package, kind, name)
        if key not in self._texts:
            for prefix in self.search_paths:
                path = prefix / 'share' / package / kind / f'{name}.{kind}'
                if path.is_file():
                    self._texts[key] = path.read_text(encoding='utf-8')
                    break
            else:
                where = ', '.join(str(p / 'share') for p in self.search_paths)
                raise DefinitionNotFound(f'no {package}/{kind}/{name}.{kind} under {where}')
        return self._texts[key]

    def _complete(self, text: str, package: str, seen: set[str]) -> str:
        """``text`` followed by the definitions of the types it uses not in ``seen``."""
        parts = [text]
        for dependency in field_types(text, package):
            if dependency in seen:
                continue
            seen.add(dependency)
            dep_package, _, dep_name = split_type_name(dependency)
            dep_text = self._file_text(dep_package, 'msg', dep_name)
            parts.append(f'\n{DELIMITER}\nMSG: {dependency}\n')
            parts.append(self._complete(dep_text, dep_package, seen))
        return ''.join(parts)

    def message(self, type_name: str) -> str:
        """The complete ``ros2msg`` definition of a message type (``pkg/msg/Type``)."""
        package, kind, name = split_type_name(type_name)
        if kind != 'msg':
            raise DefinitionNotFound(f"'{type_name}' is not a message type")
        return self._complete(self._file_text(package, 'msg', name), package, set())

    def service(self, type_name: str) -> tuple[str, str]:
        """The complete ``ros2msg`` definitions of a service's request and response
        (``pkg/srv/Type``)."""
        package, kind, name = split_type_name(type_name, 'srv')
        if kind != 'srv':
            raise DefinitionNotFound(f"'{type_name}' is not a service type")
        halves: Sequence[str] = _SERVICE_SEPARATOR.split(
            self._file_text(package, 'srv', name), maxsplit=1)
        if len(halves) != 2:
            raise DefinitionNotFound(f"{type_name}: no '---' between request and response")
        request, response = (half.strip('\n') for half in halves)
        return (self._complete(request, package, set()),
                self._complete(response, package, set()))
