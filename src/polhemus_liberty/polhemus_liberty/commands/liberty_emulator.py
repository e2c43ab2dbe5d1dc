"""``liberty_emulator``: an emulated Polhemus Liberty on a pseudo-terminal.

Examples::

    liberty_emulator --port /tmp/liberty0                       # built-in motion
    liberty_emulator --port /tmp/liberty0 --motion rec.txt      # a text recording
    liberty_emulator --port /tmp/liberty0 --motion bags/cat     # a recorded bag
    liberty_emulator --fault garbage:200@5 --fault disconnect:2@10

While it runs, type commands on stdin: ``garbage N``, ``drop N``, ``skip N``,
``pause S``, ``stall``, ``disconnect S``, ``status``, ``quit``. It needs no ROS: it is a
device, not a node.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time

from inhand_common.cli_types import command_parser, positive_float
from inhand_common.stop_flag import StopFlag
from polhemus_liberty.emulator import LibertyEmulator
from polhemus_liberty.motion import open_motion_source

FAULTS = {
    'garbage': ('inject_garbage', int),
    'drop': ('drop_bytes', int),
    'skip': ('skip_frames', int),
    'pause': ('pause', float),
    'stall': ('stall', None),
    'disconnect': ('disconnect', float),
}


def parse_fault(text: str) -> tuple[float, str, str | None]:
    """``KIND[:ARG]@SECONDS`` -> (seconds, kind, arg); raises argparse errors on bad input."""
    what, at, when = text.partition('@')
    kind, _, arg = what.partition(':')
    if kind not in FAULTS or not at:
        raise argparse.ArgumentTypeError(
            f'fault {text!r}: expected KIND[:ARG]@SECONDS with KIND one of {", ".join(FAULTS)}')
    try:
        seconds = float(when)
        if FAULTS[kind][1] is not None:
            FAULTS[kind][1](arg)
    except ValueError:
        raise argparse.ArgumentTypeError(f'fault {text!r}: bad number') from None
    return seconds, kind, arg or None


def apply_fault(emulator: LibertyEmulator, kind: str, arg: str | None) -> str:
    method, convert = FAULTS[kind]
    if convert is None:
        getattr(emulator, method)()
        return kind
    getattr(emulator, method)(convert(arg))
    return f'{kind} {arg}'


def _station_list(text: str) -> list[int]:
    try:
        stations = [int(s) for s in text.split(',') if s]
    except ValueError:
        raise argparse.ArgumentTypeError(f'stations {text!r}: expected e.g. 1,2,3,4') from None
    if not stations or any(not 1 <= s <= 16 for s in stations):
        raise argparse.ArgumentTypeError(f'stations {text!r}: each must be 1..16')
    return stations


def build_parser() -> argparse.ArgumentParser:
    parser = command_parser('liberty_emulator', __doc__)
    parser.add_argument('--port', default='/tmp/liberty0',
                        help='symlink to create for the pty (what the driver opens)')
    parser.add_argument('--motion', default='builtin',
                        help='"builtin", a text recording (.txt) or a bag (default builtin)')
    parser.add_argument('--stations', type=_station_list, default=[1, 2, 3, 4],
                        help='active station numbers (default 1,2,3,4)')
    parser.add_argument('--station-names', default='thumb,index,middle,object',
                        help='names of the stations, for bags: polhemus/<name>/pose')
    parser.add_argument('--rate', type=positive_float, default=None,
                        help='stream at this rate instead of the device\'s 120/240 Hz')
    parser.add_argument('--duration', type=positive_float, default=None,
                        help='stop after this many seconds (default: run until Ctrl-C)')
    parser.add_argument('--fault', type=parse_fault, action='append', default=[],
                        metavar='KIND[:ARG]@SECONDS', help='schedule a fault (repeatable)')
    parser.add_argument('--status-every', type=float, default=5.0,
                        help='seconds between status lines (0 = none)')
    return parser


def _console(emulator: LibertyEmulator, done: StopFlag) -> None:
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        if words[0] in ('quit', 'exit'):
            done.set()
            return
        if words[0] == 'status':
            print(emulator.status(), flush=True)
            continue
        try:
            print('fault:', apply_fault(emulator, words[0], words[1] if len(words) > 1 else None),
                  flush=True)
        except (KeyError, TypeError, ValueError):
            print(f'unknown command {line.strip()!r}; try: ' + ', '.join(FAULTS) +
                  ', status, quit', flush=True)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    names = [n for n in args.station_names.split(',') if n]
    try:
        motion = open_motion_source(args.motion, dict(zip(names, args.stations)), args.stations)
    except (OSError, ValueError) as error:
        print(f'liberty_emulator: {error}', file=sys.stderr)
        return 2
    emulator = LibertyEmulator(motion, args.port, stations=tuple(args.stations),
                               rate_override=args.rate)
    done = StopFlag()   # not a threading.Event (stop_flag.py)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, done.set)
    emulator.start()
    print(f'liberty_emulator: Liberty on {emulator.port} -> {emulator.link.slave_name}, '
          f'stations {args.stations}, motion {args.motion}', flush=True)
    threading.Thread(target=_console, args=(emulator, done), daemon=True).start()
    start = time.monotonic()
    schedule = sorted(args.fault)
    next_status = start + args.status_every
    try:
        while not done.is_set():
            now = time.monotonic()
            while schedule and now - start >= schedule[0][0]:
                _, kind, arg = schedule.pop(0)
                print(f'fault at {now - start:.1f} s:', apply_fault(emulator, kind, arg),
                      flush=True)
            if args.status_every and now >= next_status:
                print(emulator.status(), flush=True)
                next_status += args.status_every
            if args.duration is not None and now - start >= args.duration:
                break
            done.wait(0.05)
    finally:
        emulator.stop()
        print(f'liberty_emulator: stopped; {emulator.status()}', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
