"""ROS adapter for :mod:`inhand_common.parameters`: declare a spec table on an rclpy node.

Values given with ``--ros-args -p`` or ``--params-file`` are checked against the table
*before* they are declared, so a bad value is refused with the parameter's name and the
allowed range (rclpy alone would raise a bare ``InvalidParameterValueException``), and an
integer written where a number is expected (``sigma: 2`` in YAML) is accepted as 2.0.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter

from inhand_common.parameters import ParameterError, ParamSpec, unknown_parameter, validate

__all__ = ['command_line_overrides', 'declare_parameters']

_INT64_MIN, _INT64_MAX = -2**63, 2**63 - 1


def _descriptor(spec: ParamSpec) -> ParameterDescriptor:
    descriptor = ParameterDescriptor(
        name=spec.name,
        description=spec.description,
        additional_constraints=f'allowed: {spec.allowed()}',
        read_only=spec.read_only,
    )
    if not spec.is_list and spec.choices is None and (
            spec.minimum is not None or spec.maximum is not None):
        if spec.element_type is float:
            descriptor.floating_point_range = [FloatingPointRange(
                from_value=float(spec.minimum if spec.minimum is not None else -math.inf),
                to_value=float(spec.maximum if spec.maximum is not None else math.inf),
                step=0.0)]
        elif spec.element_type is int:
            descriptor.integer_range = [IntegerRange(
                from_value=int(spec.minimum if spec.minimum is not None else _INT64_MIN),
                to_value=int(spec.maximum if spec.maximum is not None else _INT64_MAX),
                step=0)]
    return descriptor


def command_line_overrides(node: Node) -> dict[str, Parameter]:
    """The values given to ``node`` with ``--ros-args -p`` / ``--params-file``, by name.

    rclpy has no public call for these: it keeps them in ``Node._parameter_overrides`` until
    the parameters are declared. They must be read before declaring, to refuse a bad value
    with its range instead of rclpy's bare exception and to name parameters the node does not
    have. If a future rclpy moves them, this fails loudly here (and
    ``test_parameters.py::test_command_line_overrides_reach_declare_parameters`` fails)
    instead of every node silently running on its defaults.
    """
    overrides = getattr(node, '_parameter_overrides', None)
    if not isinstance(overrides, dict):
        raise RuntimeError('this rclpy keeps no Node._parameter_overrides dict: '
                           'inhand_common.ros_parameters cannot read --ros-args values')
    return overrides


def _rclpy_own(name: str) -> bool:
    """Parameters every rclpy node takes itself (sim time, QoS overrides, ...)."""
    return name in ('use_sim_time', 'start_type_description_service') or \
        name.startswith('qos_overrides.')


def declare_parameters(node: Node, specs: Iterable[ParamSpec]) -> dict[str, Any]:
    """Declare every spec on ``node`` and return the validated values by name.

    Raises :class:`~inhand_common.parameters.ParameterError` listing every refused value.
    """
    specs = list(specs)
    overrides = command_line_overrides(node)
    given = {spec.name: overrides[spec.name].value for spec in specs if spec.name in overrides}
    problems = []
    try:
        values = validate(specs, given)
    except ParameterError as error:
        problems.extend(error.problems)
        values = {}
    known = {s.name for s in specs}
    problems.extend(unknown_parameter(name, known) for name in sorted(overrides)
                    if name not in known and not _rclpy_own(name))
    if problems:
        raise ParameterError(problems)
    for spec in specs:
        if spec.name in overrides:
            # Write back the coerced value so that rclpy sees the declared type.
            overrides[spec.name] = Parameter(spec.name, value=values[spec.name])
        node.declare_parameter(spec.name, values[spec.name], _descriptor(spec))
    return values
