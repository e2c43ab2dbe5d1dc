"""camera_info YAML files, as ROS's camera_calibration writes them, <-> :class:`CameraModel`.

The format is the one of ``camera_calibration_parsers`` (and of the ``left.yaml`` /
``right.yaml`` that camera_calibration saves): ``image_width``, ``image_height``,
``camera_name``, ``camera_matrix``, ``distortion_model``, ``distortion_coefficients``,
``rectification_matrix``, ``projection_matrix``, each matrix as ``{rows, cols, data}`` with
``data`` row-major. Reading is as lenient as ``camera_calibration_parsers`` (``camera_name``
and ``distortion_model`` may be missing: '' and plumb_bob; integers where floats are meant),
and stricter where it only asserts: a ``rows x cols`` that does not match the data or the
field's shape is refused with the file name and the field, not read past. Files are written
atomically, with every number at full precision so a round trip is exact.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike

from inhand_common.atomic_file import atomic_write
from inhand_common.yaml_errors import describe_yaml_error
from inhand_stereo.camera_model import CameraModel, CameraModelError

__all__ = ['CameraInfoYamlError', 'camera_info_yaml_text', 'format_float', 'read_camera_info_yaml',
           'write_camera_info_yaml']

# Field name -> (rows, cols) it must have; None: any number of columns (the distortion).
_MATRICES: dict[str, tuple[int, int | None]] = {
    'camera_matrix': (3, 3),
    'distortion_coefficients': (1, None),
    'rectification_matrix': (3, 3),
    'projection_matrix': (3, 4),
}
# A camera name that YAML reads back as the same plain string (no quoting needed).
_PLAIN_NAME = re.compile(r'[A-Za-z_][A-Za-z0-9_./-]*')


class CameraInfoYamlError(ValueError):
    """A camera_info YAML file that cannot be used; the message names the file and the
    problem."""


def read_camera_info_yaml(path: str | os.PathLike[str]) -> CameraModel:
    """The checked :class:`CameraModel` of a camera_info YAML file.

    Raises :class:`CameraInfoYamlError` for a missing or unreadable file, a file that is not
    YAML or not a mapping, a missing field, a matrix whose ``rows``/``cols`` disagree with its
    data or its shape, a non-numeric entry, and everything :meth:`CameraModel.check` refuses.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding='utf-8')
    except FileNotFoundError:
        raise CameraInfoYamlError(f'{path}: no such file') from None
    except (OSError, UnicodeDecodeError) as error:
        raise CameraInfoYamlError(f'{path}: cannot read it ({error})') from None
    try:
        document = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise CameraInfoYamlError(f'{path}: {describe_yaml_error(error)}') from None
    try:
        return camera_model_from_document(document)
    except (CameraInfoYamlError, CameraModelError) as error:
        raise CameraInfoYamlError(f'{path}: {error}') from None


def camera_model_from_document(document: Any) -> CameraModel:
    """The :class:`CameraModel` of a parsed camera_info YAML document (messages without the
    file name: the caller adds it)."""
    if not isinstance(document, Mapping):
        raise CameraInfoYamlError('not a camera_info file (the top level is not a mapping of '
                                  'image_width, image_height, camera_matrix, ...)')
    width = _integer(document, 'image_width')
    height = _integer(document, 'image_height')
    name = document.get('camera_name')
    name = '' if name is None else str(name)
    model_name = document.get('distortion_model')
    if model_name is None:
        model_name = 'plumb_bob'
    elif not isinstance(model_name, str):
        raise CameraInfoYamlError(f'distortion_model must be a name such as plumb_bob, not '
                                  f'{model_name!r}')
    matrices = {field: _matrix(document, field, rows, cols)
                for field, (rows, cols) in _MATRICES.items()}
    try:
        return CameraModel.from_fields(
            width, height, matrices['camera_matrix'], matrices['distortion_coefficients'],
            matrices['rectification_matrix'], matrices['projection_matrix'],
            distortion_model=model_name, name=name)
    except CameraModelError as error:
        raise CameraInfoYamlError(str(error)) from None


def _integer(document: Mapping[str, Any], field: str) -> int:
    if field not in document:
        raise CameraInfoYamlError(f'{field} is missing')
    value = document[field]
    if isinstance(value, bool) or not isinstance(value, int):
        raise CameraInfoYamlError(f'{field} must be a whole number of pixels, not {value!r}')
    return value


def _number(value: Any, field: str, index: int) -> float:
    """An entry of a matrix: YAML int or float, or a string such as '1e-05' that PyYAML
    leaves unresolved (yaml-cpp, which ROS uses, reads those as numbers)."""
    if isinstance(value, bool) or value is None:
        raise CameraInfoYamlError(f'{field}: data[{index}] is {value!r}, not a number')
    if isinstance(value, (int, float)):
        return float(value)
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            pass
    raise CameraInfoYamlError(f'{field}: data[{index}] is {value!r}, not a number')


def _matrix(document: Mapping[str, Any], field: str, rows: int, cols: int | None
            ) -> list[float]:
    if field not in document:
        raise CameraInfoYamlError(f'{field} is missing')
    node = document[field]
    if not isinstance(node, Mapping) or not {'rows', 'cols', 'data'} <= set(node):
        raise CameraInfoYamlError(f'{field} must be a mapping with rows, cols and data')
    got_rows, got_cols, data = node['rows'], node['cols'], node['data']
    if not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0
               for n in (got_rows, got_cols)):
        raise CameraInfoYamlError(f'{field}: rows and cols must be whole numbers, got rows '
                                  f'{got_rows!r}, cols {got_cols!r}')
    shape = f'{rows}x{cols}' if cols is not None else f'{rows}xN'
    if got_rows != rows and not (cols is None and got_rows * got_cols == 0):
        raise CameraInfoYamlError(f'{field}: rows is {got_rows}, a {shape} matrix was expected')
    if cols is not None and got_cols != cols:
        raise CameraInfoYamlError(f'{field}: cols is {got_cols}, a {shape} matrix was expected')
    if data is None:
        data = []
    if not isinstance(data, Sequence) or isinstance(data, str):
        raise CameraInfoYamlError(f'{field}: data must be a list of numbers, not {data!r}')
    if len(data) != got_rows * got_cols:
        raise CameraInfoYamlError(f'{field}: data holds {len(data)} numbers but rows x cols '
                                  f'is {got_rows}x{got_cols} = {got_rows * got_cols}')
    return [_number(value, field, i) for i, value in enumerate(data)]


def format_float(value: float) -> str:
    """The shortest text that reads back as exactly ``value``, always with a decimal point
    (YAML 1.1 readers such as PyYAML read ``1e-05`` as a string and ROS's parameter parser
    reads ``0`` as an integer, so ``1.0e-05`` and ``0.0``)."""
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f'{value} cannot be written as a YAML number')
    text = repr(value)
    if 'e' in text and '.' not in text:
        mantissa, exponent = text.split('e')
        text = f'{mantissa}.0e{exponent}'
    elif '.' not in text and 'e' not in text:
        text += '.0'
    return text


def _flow(values: ArrayLike, columns: int = 0) -> str:
    """A YAML flow list, one matrix row per line (as camera_calibration lays them out) when
    ``columns`` is given."""
    numbers = [format_float(v) for v in np.asarray(values, dtype=float).ravel()]
    if not columns:
        return '[' + ', '.join(numbers) + ']'
    rows = [', '.join(numbers[i:i + columns]) for i in range(0, len(numbers), columns)]
    return '[' + ',\n         '.join(rows) + ']'


def _name_text(name: str) -> str:
    if _PLAIN_NAME.fullmatch(name) and yaml.safe_load(name) == name:
        return name
    return json.dumps(name)  # a JSON string is a double-quoted YAML scalar


def camera_info_yaml_text(model: CameraModel) -> str:
    """The file's text: camera_calibration's layout, numbers at full precision."""
    model.check()
    d = np.asarray(model.D, dtype=float).ravel()
    lines = [
        f'image_width: {model.width}',
        f'image_height: {model.height}',
        f'camera_name: {_name_text(model.name)}',
        'camera_matrix:',
        '  rows: 3',
        '  cols: 3',
        f'  data: {_flow(model.K, 3)}',
        f'distortion_model: {model.distortion_model}',
        'distortion_coefficients:',
        '  rows: 1',
        f'  cols: {d.size}',
        f'  data: {_flow(d)}',
        'rectification_matrix:',
        '  rows: 3',
        '  cols: 3',
        f'  data: {_flow(model.R, 3)}',
        'projection_matrix:',
        '  rows: 3',
        '  cols: 4',
        f'  data: {_flow(model.P, 4)}',
    ]
    return '\n'.join(lines) + '\n'


def write_camera_info_yaml(path: str | os.PathLike[str], model: CameraModel) -> Path:
    """Write ``model`` to ``path`` atomically (readers see the old file or the new one,
    never half of it); returns the path."""
    path = Path(path)
    text = camera_info_yaml_text(model)
    with atomic_write(path) as stream:
        stream.write(text.encode('utf-8'))
    return path
