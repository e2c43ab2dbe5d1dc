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
import os
import sys
import time

from inhand_tools.bag_io import UnknownMessageType, message_class
from inhand_tools.echo_format import (FieldPathError, Options, check_field_path,
                                      format_message, get_field, is_scalar, parse_field_path,
                                      type_name)

EXIT_REFUSED = 2
SEPARATOR = '---'


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"'{text}' must be at least 1")
    return value


def parse_args(argv: list[str]) -> argparse.Namespace:
    parts = __doc__.split('\n\n')
    parser = argparse.ArgumentParser(
        prog='topic_echo', description=parts[0].replace('\n', ' ').replace('``', ''),
        epilog='\n\n'.join(parts[2:]), formatter_class=argparse.RawDescriptionHelpFormatter)
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


class Printer:
    def __init__(self, args, path, field_type: str, stop):
        self.args, self.path, self.field_type, self.stop = args, path, field_type, stop
        self.options = Options(full_length=args.full_length, no_arr=args.no_arr,
                               points=args.points)
        self.printed = 0
        self.closed = False

    def __call__(self, msg) -> None:
        if self.closed or (self.args.count and self.printed >= self.args.count):
            return
        if self.path:
            try:
                value = get_field(msg, self.path)
            except IndexError as error:
                text = f'<{self.args.field}: {error}>'
                value = None
            else:
                text = value if isinstance(value, str) else \
                    format_message(value, self.options, self.field_type)
            single = value is not None and is_scalar(value)
        else:
            text, single = format_message(msg, self.options), False
        try:
            sys.stdout.write(text + '\n' if single else f'{text}\n{SEPARATOR}\n')
            sys.stdout.flush()
        except BrokenPipeError:  # topic_echo ... | head
            self.closed = True
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            self.stop.set()
            return
        self.printed += 1
        if self.args.count and self.printed >= self.args.count:
            self.stop.set()


def resolve_type(node, topic: str, session) -> str | None:
    """The topic's type from the graph, waiting for it to appear (None if stopped)."""
    from inhand_tools.bag_ros import graph_types
    told = False
    began = time.monotonic()
    while not session.stop.is_set():
        types = graph_types(node).get(topic)
        if types:
            if len(set(types)) > 1:
                raise UnknownMessageType(f'{topic} has several types on the graph: '
                                         f'{", ".join(sorted(set(types)))}; choose with --type')
            return types[0]
        if not told and time.monotonic() - began > 0.5:
            print(f'topic_echo: waiting for {topic} to appear', file=sys.stderr, flush=True)
            told = True
        session.stop.wait(0.05)
    return None


def echo(args, full_argv, cls, path) -> int:
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from inhand_tools.bag_ros import RosSession, describe_qos, matching_qos
    try:
        with RosSession(full_argv) as session:
            node = Node('topic_echo', enable_rosout=False, start_parameter_services=False)
            executor = None
            try:
                try:
                    topic = node.resolve_topic_name(args.topic)
                except Exception as error:  # rclpy's InvalidTopicNameException
                    print(f'topic_echo: {error}', file=sys.stderr)
                    return EXIT_REFUSED
                try:
                    if cls is None:
                        msgtype = resolve_type(node, topic, session)
                        if msgtype is None:
                            return 0
                        cls = message_class(msgtype)
                    field_type = check_field_path(cls, path, args.field) if path else ''
                except (UnknownMessageType, FieldPathError) as error:
                    print(f'topic_echo: {error}', file=sys.stderr)
                    return EXIT_REFUSED
                qos = matching_qos(node.get_publishers_info_by_topic(topic), args.qos,
                                   True if args.transient_local else None, depth=100)
                print(f'topic_echo: {topic} ({type_name(cls)}; {describe_qos(qos)})',
                      file=sys.stderr, flush=True)
                printer = Printer(args, path, field_type, session.stop)
                node.create_subscription(cls, topic, printer, qos)
                executor = SingleThreadedExecutor(context=node.context)
                executor.add_node(node)
                while not session.stop.is_set():
                    executor.spin_once(timeout_sec=0.05)
            finally:
                if executor is not None:
                    executor.shutdown()
                node.destroy_node()
    except KeyboardInterrupt:  # a second Ctrl-C
        pass
    return 0


def main(argv: list[str] | None = None) -> int:
    from rclpy.utilities import remove_ros_args
    full = list(sys.argv if argv is None else ['topic_echo', *argv])
    args = parse_args(remove_ros_args(full)[1:])
    try:
        path = parse_field_path(args.field) if args.field else []
        cls = message_class(args.type) if args.type else None
        if cls is not None and path:
            check_field_path(cls, path, args.field)
    except (UnknownMessageType, FieldPathError) as error:
        print(f'topic_echo: {error}', file=sys.stderr)
        return EXIT_REFUSED
    return echo(args, full, cls, path)


if __name__ == '__main__':
    raise SystemExit(main())
