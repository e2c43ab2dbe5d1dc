"""``topic_echo``: print a topic's messages readably, like ``ros2 topic echo``.

    topic_echo TOPIC [--type pkg/msg/Type] [--field a.b[0].c] [-n COUNT | --once]
               [--no-arr] [--full-length] [--points N]
               [--qos reliable|best_effort] [--transient-local] [--ros-args ...]

The message type comes from the graph (waiting for the topic to appear) unless ``--type``
names it. Messages are printed YAML-like, separated by ``---``: nested fields indented,
arrays cut to their first 16 items with the count (``--full-length`` prints them whole,
``--no-arr`` only their type and length). ``--field`` prints only the value at a dotted
path with [i] indexing (``pose.position.x``, ``fields[0].name``), one line per message when
it is a single value. A sensor_msgs/PointCloud2 is shown as its header, size and fields
and its first ``--points`` points decoded, instead of the raw data bytes.

QoS: by default what the publishers offer (reliable if they all are, transient-local if
they all are, so a latched map is printed at once); ``--qos`` and ``--transient-local``
choose instead. ``-n COUNT`` exits after COUNT messages; ``--once`` is ``-n 1``.
Exit status: 0 (also on Ctrl-C), 2 refused arguments (unknown type, bad field path).
"""

from __future__ import annotations

import argparse
import sys

from inhand_common.cli_types import command_parser
from inhand_tools.echo_format import FieldPathError, Options, check_field_path, parse_field_path
from inhand_tools.message_types import UnknownMessageType, message_class
from inhand_tools.topic_printer import EchoRequest, echo_topic

EXIT_REFUSED = 2


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"'{text}' must be at least 1")
    return value


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = command_parser('topic_echo', __doc__, epilog_from=2)
    parser.add_argument('topic', help='topic name (relative names resolve in the namespace)')
    parser.add_argument('--type', metavar='pkg/msg/Type',
                        help='message type (default: from the graph)')
    parser.add_argument('--field', metavar='PATH', help='print only this field')
    count = parser.add_mutually_exclusive_group()
    count.add_argument('-n', '--count', type=positive_int, metavar='COUNT',
                       help='exit after COUNT messages')
    count.add_argument('--once', action='store_true', help='exit after one message')
    parser.add_argument('--no-arr', action='store_true', help="don't print array contents")
    parser.add_argument('--full-length', action='store_true', help='print arrays whole')
    parser.add_argument('--points', type=positive_int, default=5, metavar='N',
                        help='PointCloud2: how many points to decode (default 5)')
    parser.add_argument('--qos', choices=('reliable', 'best_effort'),
                        help='reliability (default: what the publishers offer)')
    parser.add_argument('--transient-local', action='store_true',
                        help='ask for transient-local durability (latched topics)')
    args = parser.parse_args(argv)
    if args.once:
        args.count = 1
    return args


def request_of(args: argparse.Namespace) -> EchoRequest:
    """The request the arguments make; UnknownMessageType or FieldPathError if ``--type``
    or ``--field`` is wrong (checked here, before ROS starts, when both are given)."""
    path = parse_field_path(args.field) if args.field else []
    cls = message_class(args.type) if args.type else None
    if cls is not None and path:
        check_field_path(cls, path, args.field)
    return EchoRequest(topic=args.topic, msg_class=cls, field_path=path,
                       field_text=args.field or '', count=args.count, reliability=args.qos,
                       transient_local=args.transient_local,
                       text=Options(full_length=args.full_length, no_arr=args.no_arr,
                                    points=args.points))


def main(argv: list[str] | None = None) -> int:
    from rclpy.utilities import remove_ros_args
    full = list(sys.argv if argv is None else ['topic_echo', *argv])
    args = parse_args(remove_ros_args(full)[1:])
    try:
        request = request_of(args)
    except (UnknownMessageType, FieldPathError) as error:
        print(f'topic_echo: {error}', file=sys.stderr)
        return EXIT_REFUSED
    from inhand_tools.ros_session import InvalidTopicName  # loads rclpy.node: after the checks
    try:
        echo_topic(full, request)
    except (InvalidTopicName, UnknownMessageType, FieldPathError) as error:
        print(f'topic_echo: {error}', file=sys.stderr)
        return EXIT_REFUSED
    except KeyboardInterrupt:  # a second Ctrl-C
        pass
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
