"""``topic_echo``: print a topic's messages readably, like ``ros2 topic echo``.

    topic_echo TOPIC [MESSAGE_TYPE] [--field a.b[0].c] [-n COUNT | --once] [--csv]
               [--filter EXPR] [-l N] [-f] [--no-arr] [--no-str] [--points N]
               [--qos-reliability reliable|best_effort]
               [--qos-durability transient_local|volatile] [--qos-depth N] [--ros-args ...]

It waits for a publisher of TOPIC and takes the message type from the graph; MESSAGE_TYPE
(pkg/msg/Type or pkg/Type, also --type) is checked against the publishers' type, and an
unknown one is refused before anything starts. Messages are printed YAML-like, separated
by ``---``: nested fields indented, arrays and strings whole; ``-l N``
(``--truncate-length``) cuts arrays to N items and strings to N characters (ros2 cuts
at 128 by default; ``-l 128`` prints as it does), ``--no-arr`` and ``--no-str``
print only their type and length. A sensor_msgs/PointCloud2 is shown as its header, size
and fields and its first ``--points`` points decoded, the data of an Image or
CompressedImage as its size; ``-f`` (``--full-length``) decodes every point, prints those
bytes and ignores ``-l``. ``--csv`` prints each message on one line, every field
flattened in order, comma-separated. ``--field`` prints only the value at a dotted path
with [i] indexing (``pose.position.x``, ``fields[0].name``), one line per message when it
is a single value.

``--filter EXPR`` prints only the messages for which the Python expression is true, with
``m`` the message (the ``--field`` value when there is one, as in ros2), e.g.
``--filter 'm.pose.position.x > 0.1'``. ``-n COUNT`` exits after COUNT messages are
printed; ``--once`` is ``-n 1``.

QoS: by default what the publishers offer (reliable if they all are, transient-local if
they all are, so a latched map is printed at once), depth 100; ``--qos-reliability``,
``--qos-durability`` and ``--qos-depth`` choose instead.
Exit status: 0 (also on Ctrl-C), 2 refused (unknown or mismatched type, bad field path or
filter, a filter that fails on a message).
"""

from __future__ import annotations

import argparse
import sys

from inhand_common.cli_types import command_parser
from inhand_tools.echo_format import (
    FieldPathError,
    FilterError,
    Options,
    check_field_path,
    compile_filter,
    parse_field_path,
)
from inhand_tools.message_types import UnknownMessageType, message_class
from inhand_tools.topic_printer import EchoRequest, echo_topic

EXIT_REFUSED = 2


def whole_number(at_least: int):
    """An argparse type for whole numbers >= ``at_least``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
        if value < at_least:
            raise argparse.ArgumentTypeError(f"'{text}' must be at least {at_least}")
        return value

    parse.__name__ = 'whole number'
    return parse


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = command_parser('topic_echo', __doc__, epilog_from=2)
    parser.add_argument('topic', help='topic name (relative names resolve in the namespace)')
    parser.add_argument('message_type', nargs='?', metavar='MESSAGE_TYPE',
                        help='pkg/msg/Type, checked against the graph (default: from the graph)')
    parser.add_argument('--type', metavar='pkg/msg/Type', help='the same as MESSAGE_TYPE')
    parser.add_argument('--field', metavar='PATH', help='print only this field')
    count = parser.add_mutually_exclusive_group()
    count.add_argument('-n', '--count', type=whole_number(1), metavar='COUNT',
                       help='exit after printing COUNT messages')
    count.add_argument('--once', action='store_true', help='exit after printing one message')
    parser.add_argument('--csv', action='store_true',
                        help='one line per message: every field, comma-separated')
    parser.add_argument('--filter', metavar='EXPR',
                        help="print only messages for which EXPR is true (m: the message)")
    parser.add_argument('-l', '--truncate-length', type=whole_number(0), metavar='N',
                        help='cut arrays to N items and strings to N characters')
    parser.add_argument('-f', '--full-length', action='store_true',
                        help='print everything whole: image bytes, every point, no -l')
    parser.add_argument('--no-arr', action='store_true', help="don't print array contents")
    parser.add_argument('--no-str', action='store_true', help="don't print string contents")
    parser.add_argument('--points', type=whole_number(1), default=5, metavar='N',
                        help='PointCloud2: how many points to decode (default 5)')
    parser.add_argument('--qos-reliability', choices=('reliable', 'best_effort'),
                        help='default: what the publishers offer')
    parser.add_argument('--qos-durability', choices=('transient_local', 'volatile'),
                        help='default: what the publishers offer')
    parser.add_argument('--qos-depth', type=whole_number(1), default=100, metavar='N',
                        help='history depth (default 100)')
    args = parser.parse_intermixed_args(argv)  # MESSAGE_TYPE may follow options
    if args.message_type and args.type and args.message_type != args.type:
        parser.error(f'MESSAGE_TYPE {args.message_type} and --type {args.type} differ')
    args.message_type = args.message_type or args.type
    if args.once:
        args.count = 1
    return args


def request_of(args: argparse.Namespace) -> EchoRequest:
    """The request the arguments make; UnknownMessageType, FieldPathError or FilterError if
    the type, ``--field`` or ``--filter`` is wrong (checked here, before ROS starts; the
    field against the type when the type is given)."""
    path = parse_field_path(args.field) if args.field else []
    cls = message_class(args.message_type) if args.message_type else None
    if cls is not None and path:
        check_field_path(cls, path, args.field)
    return EchoRequest(
        topic=args.topic, msg_class=cls, field_path=path, field_text=args.field or '',
        count=args.count, accept=compile_filter(args.filter) if args.filter else None,
        reliability=args.qos_reliability, durability=args.qos_durability, depth=args.qos_depth,
        text=Options(truncate_length=args.truncate_length, full_length=args.full_length,
                     no_arr=args.no_arr, no_str=args.no_str, points=args.points, csv=args.csv))


def main(argv: list[str] | None = None) -> int:
    from rclpy.utilities import remove_ros_args
    full = list(sys.argv if argv is None else ['topic_echo', *argv])
    args = parse_args(remove_ros_args(full)[1:])
    try:
        request = request_of(args)
    except (UnknownMessageType, FieldPathError, FilterError) as error:
        print(f'topic_echo: {error}', file=sys.stderr)
        return EXIT_REFUSED
    from inhand_tools.ros_session import InvalidTopicName  # loads rclpy.node: after the checks
    try:
        echo_topic(full, request)
    except (InvalidTopicName, UnknownMessageType, FieldPathError, FilterError) as error:
        print(f'topic_echo: {error}', file=sys.stderr)
        return EXIT_REFUSED
    except KeyboardInterrupt:  # a second Ctrl-C
        pass
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
