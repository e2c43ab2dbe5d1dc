"""``calibrate_fingertips``: each finger's tip offset by pivot calibration.

    calibrate_fingertips BAG --output FILE [--config FILE ...]
    calibrate_fingertips --live SECONDS --output FILE [--config FILE ...] [--ros-args ...]
                         [--min-rotation-deg 15] [--max-residual-mm 3]
                         [--max-uncertainty-mm 1] [--figure PNG]

On the bench (docs/mapping.md, "Real fingers"): rest each finger's pad in a small dimple (or on one
fixed point of the table) and tilt the finger 30-60 degrees about it in several directions
for about ten seconds, one finger after the other, while the driver runs (recorded with
``bag_record``, or read live with ``--live``). For each finger in ``finger_names`` (from the
``--config`` files' ``registration_node`` section; default thumb, index, middle) this
finds the stretch where it pivots and solves its pad centre in the sensor's frame
(inhand_mapping/pivot_calibration.py), prints one line per finger (the offset, the
residual, how far it turned) and writes FILE::

    /**/registration_node:
      ros__parameters:
        tip_offsets: [x, y, z, ...]    # m, per finger in the order of finger_names

which the nodes take with ``--params-file`` and ``build_map`` with a further ``--config``.
A poor pivot (turned under 15 degrees, a residual over 3 mm, an offset axis uncertain by
more than 1 mm, a finger that never pivoted) is refused in one line saying what to do, and
nothing is written. Exit status: 0 written, 2 bad input or a refused pivot.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import TypeAlias

import numpy as np

from inhand_common.atomic_file import atomic_write
from inhand_common.cli_types import command_parser, number
from inhand_common.parameters import ParameterError
from inhand_common.ros_names import station_pose_topic
from inhand_mapping.bag_mapping import BagMessages
from inhand_mapping.mapping_config import load_parameters
from inhand_mapping.pivot_calibration import PivotLimits, PivotResult, pivot_window, solve_pivot
from inhand_mapping.pose_cdr import decode_pose_stamped_many, stamp_seconds
from inhand_tools.pivot_figure import write_pivot_figure

PROG = 'calibrate_fingertips'
EXIT_BAD_INPUT = 2


Pivot: TypeAlias = tuple[np.ndarray, np.ndarray, PivotResult]


def _calibrate(raw_by_finger: dict[str, list[bytes]], limits: PivotLimits) -> dict[str, Pivot]:
    """Each finger's pivot from its raw PoseStamped messages: the sensor positions and
    quaternions of the stretch where it pivots, and the solution."""
    pivots = {}
    for name, raw in raw_by_finger.items():
        poses = np.empty((0, 7))
        if raw:
            stamps, _, poses = decode_pose_stamped_many(raw)
            times = stamp_seconds(stamps)
            order = np.argsort(times, kind='stable')
            times, poses = times[order], poses[order]
            poses = poses[pivot_window(times, poses[:, 3:])]
        pivots[name] = (poses[:, :3], poses[:, 3:], solve_pivot(poses[:, :3], poses[:, 3:], limits))
    return pivots


def _read_bag(bag: Path, names: tuple[str, ...]) -> dict[str, list[bytes]]:
    topics = {station_pose_topic(name): name for name in names}
    raw: dict[str, list[bytes]] = {name: [] for name in names}
    with BagMessages(bag, set(topics)) as source:
        for topic, _, message in source:
            raw[topics[topic]].append(message)
        if source.problem:
            print(f'{PROG}: {bag}: {source.problem}; calibrating from what was read',
                  file=sys.stderr)
    return raw


def _listen(seconds: float, names: tuple[str, ...], ros_args: list[str]) -> dict[str, list[bytes]]:
    """The fingers' pose messages published during ``seconds`` (from the first one)."""
    from geometry_msgs.msg import PoseStamped

    from inhand_mapping.qos import DATA_QOS
    from inhand_tools.ros_session import RosSession, wait_until
    raw: dict[str, list[bytes]] = {name: [] for name in names}
    with RosSession(['calibrate_fingertips', '--ros-args', *ros_args]) as session:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        node = rclpy.create_node('calibrate_fingertips')
        for name in names:
            node.create_subscription(PoseStamped, station_pose_topic(name), raw[name].append,
                                     DATA_QOS, raw=True)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        print(f'{PROG}: waiting for {", ".join(station_pose_topic(n) for n in names)}')
        started: list[float] = []

        def done() -> bool:
            executor.spin_once(timeout_sec=0.05)
            if not started and any(raw.values()):
                started.append(time.monotonic())
                print(f'{PROG}: recording {seconds:g} s: pivot each finger in turn')
            return bool(started) and time.monotonic() - started[0] >= seconds
        wait_until(done, session.stop, None, period=0.0)
        node.destroy_node()
    return raw


def _yaml(results: dict[str, PivotResult], source: str) -> str:
    lines = [f'# written by {PROG} from {source}']
    lines += [f'# {result.summary(name)}' for name, result in results.items()]
    values = ', '.join(f'{v:.6f}' for result in results.values() for v in result.offset)
    lines += ['/**/registration_node:', '  ros__parameters:',
              f'    # pad centre in each sensor\'s frame (m), x, y, z per finger: '
              f'{", ".join(results)}',
              f'    tip_offsets: [{values}]', '']
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args: list[str] = []
    if '--ros-args' in argv:
        ros_args = argv[argv.index('--ros-args') + 1:]
        argv = argv[:argv.index('--ros-args')]
    parser = command_parser(PROG, __doc__)
    parser.add_argument('bag', type=Path, nargs='?', metavar='BAG')
    parser.add_argument('--live', type=number(above=0.0), metavar='SECONDS',
                        help='read the driver\'s topics for SECONDS instead of a bag')
    parser.add_argument('--output', type=Path, required=True, help='parameter file to write')
    parser.add_argument('--config', action='append', default=[],
                        help='ROS parameter files giving finger_names; repeatable')
    parser.add_argument('--min-rotation-deg', type=number(above=0.0), default=15.0)
    parser.add_argument('--max-residual-mm', type=number(above=0.0), default=3.0)
    parser.add_argument('--max-uncertainty-mm', type=number(above=0.0), default=1.0)
    parser.add_argument('--figure', type=Path, metavar='PNG',
                        help='also draw the geometry and each finger\'s pivot (written even '
                             'when a finger is refused: it shows why)')
    args = parser.parse_args(argv)
    if (args.bag is None) == (args.live is None):
        parser.error('give a BAG or --live SECONDS (one of the two)')
    limits = PivotLimits(min_rotation_deg=args.min_rotation_deg,
                         max_residual=args.max_residual_mm / 1000.0,
                         max_uncertainty=args.max_uncertainty_mm / 1000.0)
    try:
        registration, _ = load_parameters(args.config, {})
        names = registration.finger_names
        if args.bag is not None:
            if not args.bag.exists():
                raise ValueError(f'{args.bag}: no such bag')
            raw = _read_bag(args.bag, names)
            source = str(args.bag)
        else:
            raw = _listen(args.live, names, ros_args)
            source = f'{args.live:g} s of live poses'
        pivots = _calibrate(raw, limits)
        if args.figure is not None:
            write_pivot_figure(args.figure, pivots, source)
            print(f'wrote {args.figure}')
    except (ParameterError, ValueError, OSError) as error:
        print(f'{PROG}: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    results = {name: pivot[2] for name, pivot in pivots.items()}
    for name, result in results.items():
        print(result.summary(name), file=sys.stdout if result.accepted else sys.stderr)
    refused = [name for name, result in results.items() if not result.accepted]
    if refused:
        print(f'{PROG}: {", ".join(refused)} refused: nothing written (pivot '
              f'{"that finger" if len(refused) == 1 else "those fingers"} again)', file=sys.stderr)
        return EXIT_BAD_INPUT
    with atomic_write(args.output) as stream:
        stream.write(_yaml(results, source).encode('utf-8'))
    print(f'wrote {args.output}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
