"""Declarative node parameters: one table per node says name, default, meaning and range.

The same table serves three purposes, so they never drift apart:

* the ROS adapter (:mod:`inhand_common.ros_parameters`) declares each parameter with its
  description and range, so ``ros2 param describe`` shows them;
* :func:`validate` refuses bad values at start-up with the parameter's name, the value
  given and what is allowed;
* tools without ROS (batch map building, benchmarks) validate the same YAML the same way.

No rclpy here: this module is tested directly.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = ['ParamSpec', 'ParameterError', 'load_yaml_parameters', 'unknown_parameter', 'validate']


class ParameterError(ValueError):
    """One or more parameters were refused; ``problems`` lists one sentence each."""

    def __init__(self, problems: Sequence[str]):
        self.problems = list(problems)
        super().__init__('invalid parameters:\n' + '\n'.join(f'  - {p}' for p in self.problems))


def _number(value: float) -> str:
    """A bound as written, never rounded (1048576, not 1.04858e+06)."""
    return repr(value) if isinstance(value, float) and value != int(value) else \
        str(int(value))


@dataclass(frozen=True)
class ParamSpec:
    """A node parameter: its default fixes its type (bool, int, float, str or a list of one).

    ``minimum``/``maximum`` bound numbers (inclusive) and, for lists, every element;
    ``choices`` lists the allowed values; ``length`` fixes a list's length and
    ``min_length`` bounds it from below.
    """

    name: str
    default: Any
    description: str
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[Any, ...] | None = None
    length: int | None = None
    min_length: int | None = None
    read_only: bool = True

    def __post_init__(self) -> None:
        if self.is_list and not self.default:
            raise TypeError(f'{self.name}: a list default must not be empty (it fixes the type)')

    @property
    def is_list(self) -> bool:
        return isinstance(self.default, (list, tuple))

    @property
    def element_type(self) -> type:
        """The Python type of the value (of each element for lists)."""
        if self.is_list:
            return type(self.default[0])
        return type(self.default)

    def allowed(self) -> str:
        """What is allowed, as a phrase for messages and for the ROS descriptor."""
        kind = {bool: 'true or false', int: 'an integer', float: 'a number', str: 'a string'}[
            self.element_type]
        if self.choices is not None:
            what = 'one of ' + ', '.join(repr(c) for c in self.choices)
        elif self.minimum is not None and self.maximum is not None:
            what = f'{kind} in [{_number(self.minimum)}, {_number(self.maximum)}]'
        elif self.minimum is not None:
            what = f'{kind} >= {_number(self.minimum)}'
        elif self.maximum is not None:
            what = f'{kind} <= {_number(self.maximum)}'
        else:
            what = kind
        if not self.is_list:
            return what
        if self.length is not None:
            count = f'exactly {self.length}'
        elif self.min_length is not None:
            count = f'at least {self.min_length}'
        else:
            count = 'any number of'
        return f'a list of {count} elements, each {what}'

    def coerce(self, value: Any) -> Any:
        """Value converted to this parameter's type where that loses nothing (1 -> 1.0)."""
        if self.is_list:
            if isinstance(value, (list, tuple)):
                return [self._coerce_scalar(v) for v in value]
            return value
        return self._coerce_scalar(value)

    def _coerce_scalar(self, value: Any) -> Any:
        if self.element_type is float and isinstance(value, int) and not isinstance(value, bool):
            try:
                return float(value)
            except OverflowError:
                return value  # an integer beyond any float: refused as not a number in range
        return value

    def problem(self, value: Any) -> str | None:
        """Why ``value`` is refused, or None when it is fine."""
        value = self.coerce(value)
        if self.is_list:
            if not isinstance(value, (list, tuple)):
                return self._refusal(value)
            if self.length is not None and len(value) != self.length:
                return self._refusal(value)
            if self.min_length is not None and len(value) < self.min_length:
                return self._refusal(value)
            for element in value:
                if not self._scalar_ok(element):
                    return self._refusal(value)
            return None
        return None if self._scalar_ok(value) else self._refusal(value)

    def _scalar_ok(self, value: Any) -> bool:
        if not _exactly(value, self.element_type):  # bool is an int subclass: compare exactly
            return False
        wanted = self.element_type
        if wanted is float and not math.isfinite(value):
            return False
        if self.choices is not None and value not in self.choices:
            return False
        if self.minimum is not None and value < self.minimum:
            return False
        if self.maximum is not None and value > self.maximum:
            return False
        return True

    def _refusal(self, value: Any) -> str:
        # An empty list reaches a node as no value at all: show what the user typed.
        shown = '[]' if self.is_list and value in (None, [], ()) else repr(value)
        return f"parameter '{self.name}' = {shown} is refused: allowed is {self.allowed()}"


def validate(specs: Iterable[ParamSpec], values: Mapping[str, Any]) -> dict[str, Any]:
    """Every spec's value (the default where ``values`` has none), checked and coerced.

    Raises :class:`ParameterError` listing every refused value and every unknown name, so
    a user fixing a YAML file sees all problems at once.
    """
    specs = list(specs)
    known = {s.name for s in specs}
    problems = [unknown_parameter(name, known) for name in values if name not in known]
    result: dict[str, Any] = {}
    for spec in specs:
        value = spec.coerce(values.get(spec.name, spec.default))
        problem = spec.problem(value)
        if problem:
            problems.append(problem)
        result[spec.name] = list(value) if spec.is_list and isinstance(value, tuple) else value
    if problems:
        raise ParameterError(problems)
    return result


def unknown_parameter(name: str, known: Iterable[str]) -> str:
    """The refusal of a parameter name the node does not have, with the closest valid one."""
    known = sorted(known)
    closest = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
    hint = f"did you mean '{closest[0]}'?" if closest else f"known: {', '.join(known)}"
    return f"unknown parameter '{name}' ({hint})"


def read_parameter_file(path: str) -> dict[str, Any]:
    """A ROS parameter file as a mapping; ParameterError in one line naming the file when
    it cannot be read, is not YAML, or is not a mapping."""
    import yaml  # PyYAML comes with the ROS wheels; imported lazily for speed

    from inhand_common.yaml_errors import describe_yaml_error
    try:
        with open(path, encoding='utf-8') as stream:
            document = yaml.safe_load(stream) or {}
    except OSError as error:
        raise ParameterError([f'{path}: cannot read the parameter file '
                              f'({error.strerror or error})']) from None
    except yaml.YAMLError as error:
        raise ParameterError([f'{path}: {describe_yaml_error(error)}']) from None
    if not isinstance(document, dict):
        raise ParameterError([f'{path}: not a ROS parameter file (top level is not a mapping)'])
    return document


def load_yaml_parameters(path: str, node_name: str) -> dict[str, Any]:
    """The ``ros__parameters`` of ``node_name`` (or of ``/**``) in a ROS parameter file.

    Lets tools without ROS read the same ``config/*.yaml`` the nodes use. Wildcard
    sections apply first so a node's own section overrides them, as in ROS.
    """
    document = read_parameter_file(path)
    merged: dict[str, Any] = {}
    # As rcl matches them: every node, then this node in any namespace, then by its name.
    for key in ('/**', '**', '/**/' + node_name, node_name, '/' + node_name):
        section = document.get(key)
        if isinstance(section, dict):
            merged.update(section.get('ros__parameters', {}) or {})
    return merged


def _exactly(value: Any, wanted: type) -> bool:
    """``type(value) is wanted``, apart so that type checkers do not narrow ``value``."""
    return type(value) is wanted
