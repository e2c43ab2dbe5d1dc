"""``bag_replay``: publish a bag's messages on their topics, on the bag's timetable or as
fast as the subscribers take them.

    bag_replay BAG [--rate FACTOR | --fast] [--loop] [--start-offset SECONDS]
                   [--topics T [T ...]] [--wait-subscribers SECONDS] [--clock [HZ]]
                   [--quiet]
                   [--ros-args ...]

Each message goes out as the raw CDR bytes the bag holds (no deserialisation), on the
bag's topic made relative (``/polhemus/thumb/pose`` -> ``polhemus/thumb/pose``, so a
namespace or a remapping given with ``--ros-args`` applies), with the message type the bag
names (``pkg/msg/Type`` -> ``pkg.msg.Type``). The QoS is the one the bag recorded as
offered (reliable or best effort, transient-local or volatile, the depth) and otherwise
reliable/volatile depth 1000. Timing: the gaps between the bag's timestamps divided by
``--rate`` (default 1), after waiting up to 10 s (``--wait-subscribers``) until every
topic has a subscriber and every subscriber the graph shows (with a QoS that can match)
is matched: a message published before a subscriber is matched never reaches it (the
topics still short of one are named, then the replay starts). The live view's readers do
not count as a topic's subscriber (``--ignore-readers``): it reads every topic, so its
match alone would start the replay before the graph's own readers were discovered.
``--start-offset`` skips the bag's first seconds; ``--loop`` starts again at
the end until Ctrl-C. A progress line goes to stderr (redrawn on a terminal, every 10%
otherwise) and a summary to stdout at the end. A truncated MCAP bag is replayed up to
its cut (read record by record, as ``build_map`` does) and said so.

``--clock [HZ]`` publishes the bag's time on ``/clock`` (rosgraph_msgs/Clock, HZ times a
second, default 40, as ``ros2 bag play --clock``), so nodes run with ``-p
use_sim_time:=true`` live in the bag's time: it runs at ``--rate`` from the first message,
follows the messages in ``--fast``, and holds before and after them.

``--fast``: as fast as the subscribers keep up, with nothing lost. How:

1. Before the first message it waits until every replayed topic has a matched
   subscriber, up to 10 s (``--wait-subscribers S``), then names those without one and
   starts anyway.
   Messages published before a reader is matched would never reach it.
2. Every topic is published reliable. Volatile topics use KEEP_ALL history: the writer
   keeps each message until every matched reliable reader has acknowledged it, and a
   reader acknowledges only what it has room for in its own history. A KEEP_ALL
   subscriber therefore pushes back: once its queue and ours are full (about 5000
   messages each with Fast DDS's default resource limits), ``publish()`` blocks, and
   after Fast DDS's max_blocking_time (100 ms) it fails with "cannot publish data";
   bag_replay then publishes the same message again, so the replay runs at the pace
   of the slowest subscriber and the summary says how long it was held back.
   Transient-local topics keep their recorded depth (KEEP_ALL would hand late joiners
   the whole history) and are paced by acknowledgements instead: when as many messages
   as the depth are unacknowledged, it waits until they are acknowledged.
3. At the end it waits until every message is acknowledged before destroying the
   publishers: a writer destroyed earlier takes its unacknowledged messages with it.
   Acknowledgements follow heartbeats, which Fast DDS sends every 3 s by default; this
   process asks for one every 20 ms (a default data-writer profile written to a
   temporary file, only when FASTRTPS_DEFAULT_PROFILES_FILE is not set already), so
   acknowledgements come within milliseconds.

The limits, stated plainly: DDS acknowledges a message when it is in the reader's
history, not when the subscriber's callback has taken it. A subscriber with KEEP_LAST
history of depth D (the mapping nodes use D = 1000) that falls more than D messages
behind loses the oldest in its own queue whatever the publisher does; a best-effort
subscriber never acknowledges anything. Subscribe with KEEP_ALL (or a depth above the
bag's message count) to be fed without loss at any speed; bag_replay warns about
best-effort subscribers (the history of a remote reader is not visible in discovery).
Measured here (2 cores, 60 s of 240 Hz poses from 4 stations, 57,600 messages): a raw
KEEP_ALL subscriber on the EventsExecutor takes 50,000-80,000 messages/s and gets all of
them; one on the SingleThreadedExecutor takes about 4,000/s and gets all of them (the
replay is held back to its pace); the same with KEEP_LAST 1000 got 9,281 of 57,600.

Exit status: 0 done (or stopped with Ctrl-C), 1 the bag is truncated or damaged (what
could be read was replayed), 2 refused arguments or bag.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from inhand_common.bag_source import BagError, BagSource
from inhand_common.cli_types import command_parser, non_negative_float, positive_float
from inhand_tools.bag_replayer import ReplayOptions, plan_streams, replay_bag, replay_summary, start_stamp

EXIT_DAMAGED = 1
EXIT_REFUSED = 2
DEFAULT_CLOCK_HZ = 40.0   # Hz, as ros2 bag play --clock


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = command_parser('bag_replay', __doc__, epilog_from=2)
    parser.add_argument('bag', type=Path, help='bag folder, or .mcap / .db3 file')
    pace = parser.add_mutually_exclusive_group()
    pace.add_argument('--rate', type=positive_float, default=1.0, metavar='FACTOR',
                      help='time scale: 2 plays twice as fast, 0.5 half as fast (default 1)')
    pace.add_argument('--fast', action='store_true',
                      help='as fast as the subscribers take the messages, none lost')
    parser.add_argument('--loop', action='store_true', help='start again at the end')
    parser.add_argument('--start-offset', type=non_negative_float, default=0.0,
                        metavar='SECONDS', help="skip the bag's first SECONDS")
    parser.add_argument('--topics', nargs='+', metavar='T',
                        help='replay only these topics (default: all)')
    parser.add_argument('--wait-subscribers', type=non_negative_float, metavar='SECONDS',
                        help='before starting, wait up to SECONDS for a subscriber on every '
                        'topic and for every subscriber the graph shows to match, so their '
                        'first messages are not lost (default 10; then the topics short of '
                        'one are named and the replay starts; 0: at once)')
    parser.add_argument('--ignore-readers', nargs='*', default=list(ReplayOptions.ignored_readers),
                        metavar='NODE', help="nodes whose readers do not count as a topic's "
                        'subscriber in that wait (they are still waited for once seen; '
                        f'default: {" ".join(ReplayOptions.ignored_readers)}, which reads '
                        'every topic; none given: every reader counts)')
    parser.add_argument('--clock', type=positive_float, nargs='?', const=DEFAULT_CLOCK_HZ,
                        metavar='HZ', help="publish the bag's time on /clock, HZ times a "
                        f'second (default {DEFAULT_CLOCK_HZ:g}), for nodes with use_sim_time')
    parser.add_argument('--quiet', action='store_true', help='no progress line')
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    from rclpy.utilities import remove_ros_args
    full = list(sys.argv if argv is None else ['bag_replay', *argv])
    args = parse_args(remove_ros_args(full)[1:])
    options = ReplayOptions(rate=args.rate, fast=args.fast, loop=args.loop,
                            wait_subscribers=args.wait_subscribers, quiet=args.quiet,
                            clock_hz=args.clock, ignored_readers=tuple(args.ignore_readers))
    try:
        with BagSource(args.bag) as source:
            streams = plan_streams(source, args.topics)
            start_ns = start_stamp(source, args.start_offset)
            if source.problem:
                print(f'bag_replay: {args.bag} is truncated or damaged: {source.problem}',
                      file=sys.stderr, flush=True)
            try:
                stats = replay_bag(full, source, streams, options, start_ns)
            except KeyboardInterrupt:  # a second Ctrl-C while stopping
                return 0
            print(replay_summary(stats, streams, options), flush=True)
            if source.problem:
                print(f'bag_replay: the bag is truncated or damaged: {source.problem}. Replayed '
                      f'the {stats.messages} messages that could be read.', file=sys.stderr)
                return EXIT_DAMAGED
            return 0
    except BagError as error:
        print(f'bag_replay: {error}', file=sys.stderr)
        return EXIT_REFUSED


if __name__ == '__main__':
    raise SystemExit(main())
