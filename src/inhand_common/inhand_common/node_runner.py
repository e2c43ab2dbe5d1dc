"""Start, spin and stop a node the same way in every executable.

Jazzy has no ``with rclpy.init()``: the pattern is try / spin / except (KeyboardInterrupt,
ExternalShutdownException) / finally destroy and ``try_shutdown``. Nodes that hold
hardware or threads define ``close()``, called before the node is destroyed, so Ctrl-C
(SIGINT) or SIGTERM always stops the device cleanly. A refused parameter ends the process
with exit code 2 and the list of problems on stderr.
"""

from __future__ import annotations

import sys
from typing import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from inhand_common.parameters import ParameterError

__all__ = ['run_node', 'EXIT_BAD_PARAMETERS']

EXIT_BAD_PARAMETERS = 2


def run_node(name: str, make_node: Callable[[], Node], args: Sequence[str] | None = None,
             executor_factory: Callable[[], object] = SingleThreadedExecutor) -> int:
    """Create the node with ``make_node`` and spin it until shutdown; returns an exit code.

    ``name`` prefixes the message printed when parameters are refused.
    """
    rclpy.init(args=list(args) if args is not None else sys.argv)
    node = None
    try:
        node = make_node()
        executor = executor_factory()
        executor.add_node(node)
        executor.spin()
        return 0
    except ParameterError as error:
        print(f'{name}: {error}', file=sys.stderr)
        return EXIT_BAD_PARAMETERS
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    finally:
        if node is not None:
            close = getattr(node, 'close', None)
            if callable(close):
                close()
            node.destroy_node()
        rclpy.try_shutdown()
