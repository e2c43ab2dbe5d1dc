"""Message classes by type name: ``message_class('geometry_msgs/msg/PoseStamped')``.

The bag tools know a topic's type only as a name (from a bag, the graph or ``--type``);
this imports the ROS message package and returns its class, or raises
``UnknownMessageType`` with a message for the user. No rclpy import here, so argument and
bag checks run before the ROS runtime loads.
"""

from __future__ import annotations

import importlib

__all__ = ['UnknownMessageType', 'message_class']


class UnknownMessageType(ValueError):
    """A message type this ROS installation has no Python class for."""


def message_class(msgtype: str):
    """The rclpy message class of 'pkg/msg/Type' (also 'pkg/Type'): imports ``pkg.msg``."""
    parts = msgtype.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or not all(parts) or parts[1] not in ('msg', 'srv', 'action'):
        raise UnknownMessageType(f"'{msgtype}' is not a message type (expected pkg/msg/Type)")
    package, kind, name = parts
    module_name = f'{package}.{kind}'
    try:
        module = importlib.import_module(module_name)
    except ImportError:
        raise UnknownMessageType(f"unknown message type '{msgtype}': this ROS installation has "
                                 f"no Python module {module_name}") from None
    cls = getattr(module, name, None)
    if cls is None or not hasattr(cls, 'get_fields_and_field_types'):
        raise UnknownMessageType(f"unknown message type '{msgtype}': module {module_name} has "
                                 f'no message {name}')
    return cls
