"""Replay of a 240 Hz, 4-station, 60 s session through the graph over DDS: how fast, and
whether anything is lost.

    .venv/bin/python test/benchmarks/bench_replay.py [--bag bags/cat_moving] [--runs 3]

For each run: start registration_node and occupancy_node (config/mapping.yaml) in a DDS
domain of their own, replay the bag with ``bag_replay --fast``, and clock from the start of
the replay's first publication until the last registered points (a watch subscribed
before the replay waits until none has come for 1 s); then call occupancy/save and read the node's own count of points integrated,
outside or invalid, which must equal the bag's fingertip messages. Prints the real-time
factor (bag seconds / wall seconds), where the time went (replay publishing, registration,
integration), and exits non-zero if anything was lost.
"""

from __future__ import annotations

import argparse
import os
import random
import re
import sys
import tempfile
import time
from pathlib import Path

WORKSPACE = Path(__file__).resolve().parents[2]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--bag', type=Path, default=WORKSPACE / 'bags' / 'cat_moving')
    parser.add_argument('--runs', type=int, default=3)
    args = parser.parse_args()
    os.environ['ROS_DOMAIN_ID'] = str(random.randint(100, 200))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    from rosbags.highlevel import AnyReader
    from sensor_msgs.msg import PointCloud2

    from inhand_mapping.map_io import load_npz
    from inhand_tools.launching import ProcessGroup, TopicWatch, call_trigger, mapping_graph

    with AnyReader([args.bag]) as reader:
        counts = {c.topic.lstrip('/'): c.msgcount for c in reader.connections}
        span = (reader.end_time - reader.start_time) * 1e-9
    fingertips = sum(n for topic, n in counts.items() if topic != 'polhemus/object/pose')
    messages = sum(counts.values())
    print(f'bag {args.bag}: {messages:,} messages ({fingertips:,} fingertip poses), '
          f'{span:.1f} s of data; ROS_DOMAIN_ID {os.environ["ROS_DOMAIN_ID"]}', flush=True)
    factors, ok = [], True
    for run in range(1, args.runs + 1):
        out = Path(tempfile.mkdtemp(prefix='bench_replay_'))
        log = open(out / 'graph.log', 'w')
        with ProcessGroup(stream=log) as group, \
                TopicWatch('registration/points', PointCloud2) as watch:
            mapping_graph(group, str(WORKSPACE / 'config' / 'mapping.yaml'), str(out), 'replay')
            watch.wait_connected()  # registration -> occupancy matched before data flows
            replay = group.start('replay', ['bag_replay', str(args.bag), '--fast', '--quiet'])
            replay.wait()
            replay_done = time.monotonic()
            watch.wait_quiet(1.0)
            last = watch.last
            saved, message = call_trigger('occupancy/save')
        log.close()
        text = (out / 'graph.log').read_text()
        published = re.search(r'published (\d+) messages in ([\d.]+) s wall', text)
        waited = re.search(r'acknowledged ([\d.]+) s after the first was published', text)
        grid, _ = load_npz(out / 'replay.npz') if saved else (None, None)
        done = grid.counts.integrated + grid.counts.outside + grid.counts.invalid if grid else 0
        publish_s = float(published.group(2)) if published else float('nan')
        ack_s = float(waited.group(1)) if waited else 0.0
        # The clock starts at the replay's first publication (bag_replay says how long it
        # published and waited for the last acknowledgements; before that it only waited
        # for its subscribers to be discovered) and stops at the last registered points.
        first_publish = replay_done - max(publish_s, ack_s)
        end = max(last if last is not None else replay_done, replay_done)
        elapsed = end - first_publish
        factor = span / elapsed
        factors.append(factor)
        lost = fingertips - done
        ok &= lost == 0 and saved
        print(f'run {run}: {factor:5.1f}x real time ({elapsed:.2f} s for {span:.0f} s of data): '
              f'bag_replay published for {publish_s:.2f} s, the last registered points came '
              f'{end - replay_done:.2f} s after it ended; points in the map {done:,} of '
              f'{fingertips:,} (lost {lost})', flush=True)
    factors.sort()
    print(f'replay -> registration -> occupancy over DDS: median {factors[len(factors) // 2]:.1f}x '
          f'real time (range {factors[0]:.1f}-{factors[-1]:.1f}x), target >= 20x: '
          f'{"PASS" if factors[len(factors) // 2] >= 20 else "FAIL"}; '
          f'{"nothing lost" if ok else "SOMETHING WAS LOST"}')
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
