"""Start, spin and stop a node the same way in every executable.

Ctrl-C (SIGINT) and SIGTERM end the spin loop through our own handlers rather than
rclpy's, so that the node's ``close()`` runs while its context is still valid: nodes that
hold hardware or threads stop the device cleanly and can still log and publish a last
word. A refused parameter ends the process with exit code 2 and the list of problems on
stderr. (Jazzy has no ``with rclpy.init()``; this is the try / spin / finally pattern.)
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from inhand_common.blas_threads import single_threaded_blas
from inhand_common.dds_profile import shipped_profile
from inhand_common.heap_reuse import reuse_freed_memory
from inhand_common.parameters import ParameterError, read_parameter_file
from inhand_common.stop_flag import StopFlag

__all__ = ['EXIT_BAD_PARAMETERS', 'run_node']

EXIT_BAD_PARAMETERS = 2
SPIN_SLICE = 0.1  # s: how often the spin loop looks at the stop flag


def _parameter_files(argv: Sequence[str]) -> list[str]:
    """The paths given to ``--params-file`` after ``--ros-args``."""
    files = []
    in_ros_args = False
    for k, arg in enumerate(argv):
        if arg == '--ros-args':
            in_ros_args = True
        elif arg == '--':
            in_ros_args = False
        elif in_ros_args and arg == '--params-file' and k + 1 < len(argv):
            files.append(argv[k + 1])
    return files


def run_node(name: str, make_node: Callable[[], Node], args: Sequence[str] | None = None,
             executor_factory: Callable[[], object] = SingleThreadedExecutor,
             asynchronous_publishing: bool = False) -> int:
    """Create the node with ``make_node`` and spin it until shutdown; returns an exit code.

    ``name`` prefixes the message printed when parameters are refused;
    ``asynchronous_publishing`` for a node whose messages are large and latched
    (dds_profile.py).
    """
    single_threaded_blas()
    reuse_freed_memory()
    argv = list(args) if args is not None else list(sys.argv)
    try:
        for path in _parameter_files(argv):    # rcl would say it in a 60-line traceback
            read_parameter_file(path)
    except ParameterError as error:
        print(f'{name}: {error.problems[0]}', file=sys.stderr)
        return EXIT_BAD_PARAMETERS
    # large images arrive, also best effort (dds_profile.py)
    with shipped_profile(asynchronous=asynchronous_publishing):
        return _spin(name, make_node, argv, executor_factory)


def _spin(name: str, make_node: Callable[[], Node], argv: list[str],
          executor_factory: Callable[[], object]) -> int:
    stop = StopFlag()   # not a threading.Event (stop_flag.py)
    previous = {sig: signal.signal(sig, stop.set)
                for sig in (signal.SIGINT, signal.SIGTERM)}
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        node = make_node()
        executor = executor_factory()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=SPIN_SLICE)
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
        for sig, handler in previous.items():
            signal.signal(sig, handler)
