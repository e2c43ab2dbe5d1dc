"""What the bag tools add to :mod:`inhand_common.bag_source`: message classes by type name.

No rclpy import here, so argument and bag checks run before the ROS runtime loads. The bag
reading itself (``BagSource``, ``Progress``) is shared with ``build_map`` and re-exported.
"""

from __future__ import annotations

import importlib

from inhand_common.bag_source import (BagError, BagSource, BagTopic,  # noqa: F401 (re-exported)
                                      Progress, relative_name)
from inhand_common.cli_types import non_negative_float, positive_float  # re-exported

__all__ = ['BagError', 'BagSource', 'BagTopic', 'Progress', 'UnknownMessageType',
           'message_class', 'non_negative_float', 'positive_float', 'relative_name']


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
