"""``bag_record``: record topics into an MCAP bag (rosbag2 format, written with rosbags).

    bag_record -o OUTPUT [TOPIC ...] [--all] [--duration SECONDS] [--force]
               [--ros-args ...]

Subscribes to each TOPIC (relative names resolve in the node's namespace) as soon as the
graph shows it with a publisher, with the type the graph reports, and writes every message
as the raw CDR bytes received (``raw=True``: no deserialisation), stamped with the time
of receipt, into the bag folder OUTPUT (``OUTPUT/OUTPUT.mcap`` and ``metadata.yaml``).
``--all`` records every topic with a publisher, including ones that appear later
(``rosout`` and ``parameter_events`` only when named). Message definitions come from
rosbags' ROS 2 Jazzy type store, so any rosbag2 tool can read the bag.

QoS: the subscription matches the publishers (reliable when they all are, so a reliable
publisher gets acknowledgements; transient-local when they all offer it, so the latest
message of a latched topic such as a map, published before the recorder started, is
recorded too) with KEEP_ALL history: a message stays in the DDS queue until it is
written, and a publisher faster than the recorder is held back rather than overwriting
what was not written yet. The publishers' offered QoS is stored with each topic, so
``bag_replay`` offers the same again.

Stopping: Ctrl-C (SIGINT), SIGTERM or the end of ``--duration`` (counted from the first
subscription) ends the loop; the recorder then takes every message already in its
queues (until it finds them empty, at most 2 s), and closes the bag (chunk index,
summary, metadata.yaml). Nothing received is lost. A recorder killed outright
(SIGKILL, power loss) leaves an MCAP without its summary: ``bag_replay`` and
``build_map`` still read it up to the last complete chunk (1 MiB).

OUTPUT must not exist; ``--force`` replaces an existing bag folder (a folder holding only
metadata.yaml, .mcap and .db3 files), never anything else.
Exit status: 0 recorded, 2 refused arguments, unknown message type.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from inhand_common.cli_types import command_parser, positive_float
from inhand_tools.bag_recorder import RecordRequest, prepare_output, record_topics, recording_summary

EXIT_REFUSED = 2


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = command_parser('bag_record', __doc__, epilog_from=2)
    parser.add_argument('-o', '--output', type=Path, required=True,
                        help='bag folder to create')
    parser.add_argument('topics', nargs='*', metavar='TOPIC', help='topics to record')
    parser.add_argument('--all', action='store_true', help='record every topic with a publisher')
    parser.add_argument('--duration', type=positive_float, metavar='SECONDS',
                        help='stop after SECONDS of recording')
    parser.add_argument('--force', action='store_true', help='replace an existing bag folder')
    args = parser.parse_args(argv)
    if not args.topics and not args.all:
        parser.error('name the topics to record, or --all')
    return args


def main(argv: list[str] | None = None) -> int:
    from rclpy.utilities import remove_ros_args
    full = list(sys.argv if argv is None else ['bag_record', *argv])
    args = parse_args(remove_ros_args(full)[1:])
    try:
        prepare_output(args.output, args.force)
    except (ValueError, OSError) as error:
        print(f'bag_record: {error}', file=sys.stderr)
        return EXIT_REFUSED
    from inhand_tools.ros_session import InvalidTopicName  # loads rclpy.node: after the checks
    began = time.monotonic()
    try:
        recorder = record_topics(full, RecordRequest(args.output, args.topics, args.all,
                                                     args.duration))
    except InvalidTopicName as error:
        print(f'bag_record: {error}', file=sys.stderr)
        return EXIT_REFUSED
    if recorder is None:
        return EXIT_REFUSED
    for error in recorder.errors:
        print(f'bag_record: {error}', file=sys.stderr)
    print(recording_summary(recorder, args.output, time.monotonic() - began), flush=True)
    return EXIT_REFUSED if recorder.errors else 0


if __name__ == '__main__':
    raise SystemExit(main())
