"""Replay of a 240 Hz, 4-station, 60 s session through the graph over DDS: how fast, and
whether anything is lost.

    .venv/bin/python test/benchmarks/bench_replay.py [--bag BAG] [--runs 3]

By default it first simulates its own session into a temporary folder (removed at the end):
the moving cat with re-grasp, 240 Hz (the Liberty's rate), 60 s, seed 2, i.e. what
``simulate_session --object cat --moving --regrasp --rate 240 --duration 60 --seed 2`` writes
(57,600 messages, 43,200 of them fingertip poses). The bundled bags are 15 Hz, 16 times
lighter a load than the device's rate; ``--bag`` replays another bag instead.

For each run: start registration_node and occupancy_node (config/mapping.yaml) in a DDS
domain of their own, replay the bag with ``bag_replay --fast``, and clock from the start of
the replay's first publication until the last registered points (a watch subscribed
before the replay waits until none has come for 1 s); then call occupancy/save and read the
node's own count of points integrated, outside or invalid, which must equal the bag's
fingertip messages. Prints the real-time factor (bag seconds / wall seconds), where the time
went (replay publishing, registration, integration), and exits non-zero if anything was lost.
"""

from __future__ import annotations

import argparse
import os
import random
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

WORKSPACE = Path(__file__).resolve().parents[2]
# The session simulated when no --bag is given (inhand_sim.session.SessionSettings).
SESSION = dict(object_name='cat', static=False, regrasp=True, rate=240.0, duration=60.0, seed=2)


def simulate_bag(folder: Path) -> Path:
    """Write the SESSION bag (no ground truth: not needed here) into ``folder``. Named
    cat_moving, it is byte for byte the bag that was bundled as bags/cat_moving before that
    became 15 Hz (the MCAP file is named after its folder), so figures stay comparable."""
    from inhand_sim.session import SessionSettings, simulate, write_bag
    started = time.monotonic()
    session = simulate(SessionSettings(**SESSION))
    bag = write_bag(session, folder / 'cat_moving')
    print(f'simulated {session.message_count:,} messages in {time.monotonic() - started:.1f} s',
          flush=True)
    return bag


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--bag', type=Path, default=None,
                        help='replay this bag instead of simulating the 240 Hz, 60 s moving '
                             'cat session (seed 2)')
    parser.add_argument('--runs', type=int, default=3)
    args = parser.parse_args()
    if args.bag is not None:
        print(f'replaying the given bag {args.bag}', flush=True)
        return bench(args.bag, args.runs)
    with tempfile.TemporaryDirectory(prefix='bench_replay_session_') as folder:
        print(f'replaying a simulated session: the moving cat with re-grasp, '
              f'{SESSION["rate"]:g} Hz, {SESSION["duration"]:g} s, seed {SESSION["seed"]} '
              f'(simulate_session --object {SESSION["object_name"]} --moving --regrasp '
              f'--rate {SESSION["rate"]:g} --duration {SESSION["duration"]:g} '
              f'--seed {SESSION["seed"]}), written to {folder}', flush=True)
        return bench(simulate_bag(Path(folder)), args.runs)


def bench(bag: Path, runs: int) -> int:
    os.environ['ROS_DOMAIN_ID'] = str(random.randint(100, 200))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    from rosbags.highlevel import AnyReader
    from sensor_msgs.msg import PointCloud2

    from inhand_mapping.map_io import load_npz
    from inhand_tools.launching import ProcessGroup, TopicWatch, call_trigger, mapping_graph

    with AnyReader([bag]) as reader:
        counts = {c.topic.lstrip('/'): c.msgcount for c in reader.connections}
        span = (reader.end_time - reader.start_time) * 1e-9
    fingertips = sum(n for topic, n in counts.items() if topic != 'polhemus/object/pose')
    messages = sum(counts.values())
    print(f'bag {bag}: {messages:,} messages ({fingertips:,} fingertip poses), '
          f'{span:.1f} s of data; ROS_DOMAIN_ID {os.environ["ROS_DOMAIN_ID"]}', flush=True)
    factors, ok = [], True
    for run in range(1, runs + 1):
        out = Path(tempfile.mkdtemp(prefix='bench_replay_'))
        log = open(out / 'graph.log', 'w')
        with ProcessGroup(stream=log) as group, \
                TopicWatch('registration/points', PointCloud2) as watch:
            mapping_graph(group, str(WORKSPACE / 'config' / 'mapping.yaml'), str(out), 'replay')
            watch.wait_connected()  # registration -> occupancy matched before data flows
            replay = group.start('replay', ['bag_replay', str(bag), '--fast', '--quiet'])
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
        shutil.rmtree(out, ignore_errors=True)     # the map and the log are read: not kept
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
