"""Live mode without hardware: emulated Liberty -> driver -> registration -> occupancy.

    .venv/bin/python launch_scripts/live_emulator.py [--duration S] [--motion SOURCE]
        [--format binary|ascii] [--output DIR] [--view [--http-port P] [--foxglove-port P]]

liberty_emulator streams on a pty (built-in motion by default: fingertips stroking a
sphere on a swaying object; or a text recording or a bag), liberty_driver publishes
polhemus/<name>/pose, registration_node and occupancy_node build the map. Ctrl-C (or the
end of --duration, SIGTERM, or the terminal closing) stops the emulator and the driver
first, waits until the graph has passed on what they sent, saves the map to --output and
stops every process cleanly; a second Ctrl-C does not cut the save short. The occupancy
node also saves every --autosave seconds and when it is stopped. --view also
starts live_view: the page at http://127.0.0.1:8080/, Foxglove at ws://127.0.0.1:8765.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from inhand_tools.launching import (
    ProcessGroup,
    TopicWatch,
    add_view_arguments,
    driver_command,
    mapping_graph,
    save_when_drained,
    start_view,
)

WORKSPACE = Path(__file__).resolve().parents[1]
AUTOSAVE = 30.0   # s: the live session's map is saved this often
QUIET = 1.0       # s without registered points after the driver stopped: the graph drained
SOURCES = ('driver', 'emulator')   # stopped first (the driver stops the device's stream), so
#                                   that what they sent is in the map


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, help='seconds (default: until Ctrl-C)')
    parser.add_argument('--motion', default='builtin')
    parser.add_argument('--format', choices=('binary', 'ascii'), default='binary')
    parser.add_argument('--output', type=Path, default=WORKSPACE / 'output' / 'live')
    parser.add_argument('--autosave', type=float, default=AUTOSAVE, metavar='SECONDS',
                        help='the occupancy node saves a changed map this often (default '
                        f'{AUTOSAVE:g} s; 0: off): a crash loses at most that much')
    add_view_arguments(parser)
    args = parser.parse_args(argv)
    port = f'/tmp/liberty-live-{os.getpid()}'
    args.output.mkdir(parents=True, exist_ok=True)
    from sensor_msgs.msg import PointCloud2
    with ProcessGroup() as group, TopicWatch('registration/points', PointCloud2) as watch:
        mapping_graph(group, str(WORKSPACE / 'config' / 'mapping.yaml'), str(args.output),
                      'live', autosave=args.autosave, shape=True, exploration=True)
        # The map's reader in place before the first pose: the occupancy node can take
        # seconds to start (its kernels), and what registration sent before was lost.
        if not watch.wait_reader('occupancy_node', timeout=60.0):
            print('[launch] occupancy_node did not subscribe to registration/points within '
                  '60 s; stopping', flush=True)
            return 1
        group.start('emulator', ['liberty_emulator', '--port', port, '--motion', args.motion])
        group.start('driver', driver_command(str(WORKSPACE / 'config' / 'liberty_emulator.yaml'),
                                             port, f'output_format:={args.format}'))
        url = start_view(group, args)
        print(f'[launch] live graph on {port}; Ctrl-C to stop', flush=True)
        if url:
            print(f'[launch] live view at {url}', flush=True)
        try:
            deadline = time.monotonic() + args.duration if args.duration else None
            while deadline is None or time.monotonic() < deadline:
                if any(p.poll() is not None for _, p in group.processes):
                    print('[launch] a process ended early; stopping', flush=True)
                    return 1
                time.sleep(0.2)
        except KeyboardInterrupt:
            pass
        group.say('[launch] stopping the driver and the emulator; saving once the graph '
                  'has drained')
        ok, _ = save_when_drained(group, watch, QUIET, SOURCES, timeout=10.0)
    return 0 if ok else 1


if __name__ == '__main__':
    raise SystemExit(main())
