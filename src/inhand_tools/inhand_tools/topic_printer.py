"""Subscribe to a topic and print its messages as text: the library behind the
``topic_echo`` command (the text itself is :mod:`inhand_tools.echo_format`).

``echo_topic`` runs a ROS session of its own: it resolves the topic name, waits for a
publisher of it, takes the message type from the graph (or checks the one given against
it), subscribes with the QoS the publishers offer (or the one asked for) and prints until
stopped or ``count`` messages are printed.

No rclpy import at module level, so the command checks its arguments before the ROS
runtime loads.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from inhand_tools.echo_format import FilterError, Options, check_field_path, echo_text, get_field, type_name
from inhand_tools.message_types import UnknownMessageType, message_class

__all__ = ['EchoRequest', 'Printer', 'echo_topic', 'topic_class', 'wait_for_publishers']

SEPARATOR = '---'
WAIT_NOTICE = 0.5   # s: say we are waiting for a publisher after this long


@dataclass
class EchoRequest:
    """What to print (the command's arguments)."""

    topic: str                            # relative names resolve in the node's namespace
    msg_class: object = None              # None: the graph's type; else checked against it
    field_path: list = field(default_factory=list)  # parse_field_path(field_text)
    field_text: str = ''                  # as given with --field
    count: int | None = None              # stop after printing this many; None: until stopped
    accept: Callable[[object], bool] | None = None  # --filter (compile_filter); None: all
    reliability: str | None = None        # 'reliable' / 'best_effort'; None: as offered
    durability: str | None = None         # 'transient_local' / 'volatile'; None: as offered
    depth: int = 100                      # the subscription's history depth
    text: Options = field(default_factory=Options)


class Printer:
    """The subscription callback: writes each message (or its field) that passes the
    filter to stdout. A filter that fails stops the session and is kept in ``error``."""

    def __init__(self, request: EchoRequest, field_type: str, stop):
        self.request, self.field_type, self.stop = request, field_type, stop
        self.printed = 0
        self.closed = False
        self.error: FilterError | None = None

    def __call__(self, msg) -> None:
        count = self.request.count
        if self.closed or self.error or (count and self.printed >= count):
            return
        try:
            shown = self._text(msg)
        except FilterError as error:
            self.error = error
            self.stop.set()
            return
        if shown is None:
            return
        text, single = shown
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

    def _text(self, msg) -> tuple[str, bool] | None:
        """The text to print and whether it is a line of its own (no separator); None if
        the filter leaves the message out."""
        request = self.request
        try:
            value = get_field(msg, request.field_path)
        except IndexError as error:
            return f'<{request.field_text}: {error}>', False
        if request.accept is not None and not request.accept(value):
            return None
        return echo_text(value, request.text, self.field_type)


def wait_for_publishers(node, topic: str, stop) -> list:
    """The publishers of ``topic`` (``node.get_publishers_info_by_topic``), waiting for one
    to appear; [] if stopped first."""
    told = False
    began = time.monotonic()
    while not stop.is_set():
        infos = node.get_publishers_info_by_topic(topic)
        if infos:
            return infos
        if not told and time.monotonic() - began > WAIT_NOTICE:
            print(f'topic_echo: waiting for a publisher on {topic}', file=sys.stderr, flush=True)
            told = True
        stop.wait(0.05)
    return []


def topic_class(topic: str, graph_types: list[str], given=None):
    """The message class to subscribe with: the publishers' type, or ``given`` (a class)
    if they publish it. UnknownMessageType if they publish several types and none is
    given, another type than the one given, or one without a Python class here."""
    types = sorted(set(graph_types))
    if given is not None:
        if type_name(given) in types:
            return given
        raise UnknownMessageType(f'{topic} is published as {" and ".join(types)}, '
                                 f'not {type_name(given)}')
    if len(types) > 1:
        raise UnknownMessageType(f'{topic} is published with several types: '
                                 f'{", ".join(types)}; name one as MESSAGE_TYPE')
    return message_class(types[0])


def echo_topic(ros_args: list[str], request: EchoRequest) -> int:
    """Print the topic's messages in a ROS session started with ``ros_args`` (the full
    command line, for ``--ros-args``) until SIGINT/SIGTERM or ``request.count``; the
    number printed.

    InvalidTopicName, UnknownMessageType (the graph's type, or one that differs from the
    type asked for) or FieldPathError (the field does not fit the graph's type) before
    anything is printed; FilterError if the filter fails on a message; KeyboardInterrupt
    on a second signal.
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
            publishers = wait_for_publishers(node, topic, session.stop)
            if not publishers:
                return 0
            cls = topic_class(topic, [p.topic_type for p in publishers], request.msg_class)
            field_type = check_field_path(cls, request.field_path, request.field_text) \
                if request.field_path else ''
            durability = None if request.durability is None else \
                request.durability == 'transient_local'
            qos = matching_qos([p for p in publishers if p.topic_type == type_name(cls)],
                               request.reliability, durability, depth=request.depth)
            print(f'topic_echo: {topic} ({type_name(cls)}; {describe_qos(qos)})',
                  file=sys.stderr, flush=True)
            printer = Printer(request, field_type, session.stop)
            node.create_subscription(cls, topic, printer, qos)
            executor = SingleThreadedExecutor(context=node.context)
            executor.add_node(node)
            while not session.stop.is_set():
                executor.spin_once(timeout_sec=0.05)
            if printer.error is not None:
                raise printer.error
            return printer.printed
        finally:
            if executor is not None:
                executor.shutdown()
            node.destroy_node()
