"""Subscribe to a topic and print its messages as text: the library behind the
``topic_echo`` command (the text itself is :mod:`inhand_tools.echo_format`).

``echo_topic`` runs a ROS session of its own: it resolves the topic name, takes the
message type from the graph unless one is given, subscribes with the QoS the publishers
offer (or the one asked for) and prints until stopped or ``count`` messages are printed.

No rclpy import at module level, so the command checks its arguments before the ROS
runtime loads.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass, field

from inhand_tools.echo_format import (
    Options,
    check_field_path,
    format_message,
    get_field,
    is_scalar,
    type_name,
)
from inhand_tools.message_types import UnknownMessageType, message_class

__all__ = ['EchoRequest', 'Printer', 'echo_topic', 'wait_for_topic_type']

SEPARATOR = '---'
TYPE_WAIT_NOTICE = 0.5   # s: say we are waiting for the topic after this long


@dataclass
class EchoRequest:
    """What to print (the command's arguments)."""

    topic: str                            # relative names resolve in the node's namespace
    msg_class: object = None              # None: the type the graph shows for the topic
    field_path: list = field(default_factory=list)  # parse_field_path(field_text)
    field_text: str = ''                  # as given with --field
    count: int | None = None              # stop after this many; None: until stopped
    reliability: str | None = None        # 'reliable' / 'best_effort'; None: as offered
    transient_local: bool = False         # ask for it; False: as offered
    text: Options = field(default_factory=Options)


class Printer:
    """The subscription callback: writes each message (or its field) to stdout."""

    def __init__(self, request: EchoRequest, field_type: str, stop):
        self.request, self.field_type, self.stop = request, field_type, stop
        self.printed = 0
        self.closed = False

    def __call__(self, msg) -> None:
        count = self.request.count
        if self.closed or (count and self.printed >= count):
            return
        text, single = self._text(msg)
        try:
            sys.stdout.write(text + '\n' if single else f'{text}\n{SEPARATOR}\n')
            sys.stdout.flush()
        except BrokenPipeError:  # topic_echo ... | head
            self.closed = True
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            self.stop.set()
            return
        self.printed += 1
        if count and self.printed >= count:
            self.stop.set()

    def _text(self, msg) -> tuple[str, bool]:
        """The text to print and whether it is a single value (one line, no separator)."""
        request = self.request
        if not request.field_path:
            return format_message(msg, request.text), False
        try:
            value = get_field(msg, request.field_path)
        except IndexError as error:
            return f'<{request.field_text}: {error}>', False
        text = value if isinstance(value, str) else \
            format_message(value, request.text, self.field_type)
        return text, value is not None and is_scalar(value)


def wait_for_topic_type(node, topic: str, stop) -> str | None:
    """The topic's type from the graph, waiting for it to appear (None if stopped)."""
    from inhand_tools.ros_session import graph_types
    told = False
    began = time.monotonic()
    while not stop.is_set():
        types = graph_types(node).get(topic)
        if types:
            if len(set(types)) > 1:
                raise UnknownMessageType(f'{topic} has several types on the graph: '
                                         f'{", ".join(sorted(set(types)))}; choose with --type')
            return types[0]
        if not told and time.monotonic() - began > TYPE_WAIT_NOTICE:
            print(f'topic_echo: waiting for {topic} to appear', file=sys.stderr, flush=True)
            told = True
        stop.wait(0.05)
    return None


def echo_topic(ros_args: list[str], request: EchoRequest) -> int:
    """Print the topic's messages in a ROS session started with ``ros_args`` (the full
    command line, for ``--ros-args``) until SIGINT/SIGTERM or ``request.count``; the
    number printed.

    InvalidTopicName, UnknownMessageType (the graph's type) or FieldPathError (the field
    does not fit the graph's type) before anything is printed; KeyboardInterrupt on a
    second signal.
    """
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from inhand_tools.qos_profiles import describe_qos, matching_qos
    from inhand_tools.ros_session import RosSession, resolve_topic
    with RosSession(ros_args) as session:
        node = Node('topic_echo', enable_rosout=False, start_parameter_services=False)
        executor = None
        try:
            topic = resolve_topic(node, request.topic)
            cls = request.msg_class
            if cls is None:
                msgtype = wait_for_topic_type(node, topic, session.stop)
                if msgtype is None:
                    return 0
                cls = message_class(msgtype)
            field_type = check_field_path(cls, request.field_path, request.field_text) \
                if request.field_path else ''
            qos = matching_qos(node.get_publishers_info_by_topic(topic), request.reliability,
                               True if request.transient_local else None, depth=100)
            print(f'topic_echo: {topic} ({type_name(cls)}; {describe_qos(qos)})',
                  file=sys.stderr, flush=True)
            printer = Printer(request, field_type, session.stop)
            node.create_subscription(cls, topic, printer, qos)
            executor = SingleThreadedExecutor(context=node.context)
            executor.add_node(node)
            while not session.stop.is_set():
                executor.spin_once(timeout_sec=0.05)
            return printer.printed
        finally:
            if executor is not None:
                executor.shutdown()
            node.destroy_node()
