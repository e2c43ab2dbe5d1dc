"""The graph on the Foxglove WebSocket protocol, with foxglove-sdk (no rclpy here).

A :class:`FoxgloveLink` runs foxglove-sdk's WebSocket server (Foxglove, and Lichtblick
versions that speak its ``foxglove.sdk.v1`` subprotocol, connect to
``ws://host:port``). The node tells it what to serve:

* every ROS topic as a channel of the same name: encoding ``cdr``, schema the type's
  complete ``ros2msg`` definition (:mod:`inhand_view.ros2msg_schemas`), messages the
  serialized bytes as they came off DDS, logged with their receive time. A client that
  subscribes to a latched topic (transient-local: the maps) gets its latest message again
  (:meth:`FoxgloveLink.resend_latched`), as a late ROS subscriber would;
* the frames as ``foxglove.FrameTransforms`` (foxglove's own schema) on one channel;
* ROS services as Foxglove services whose handler takes the request's CDR and returns the
  response's (the node makes the ROS call).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable

import foxglove
from foxglove.channels import FrameTransformsChannel
from foxglove.messages import FrameTransform, FrameTransforms, Quaternion, Timestamp, Vector3
from foxglove.websocket import Capability, ChannelView, Client

from inhand_view.frame_tree import Transform
from inhand_view.ros2msg_schemas import MessageDefinitions

__all__ = ['FRAMES_CHANNEL', 'FoxgloveLink', 'PortInUse', 'frame_transforms']

FRAMES_CHANNEL = '/frame_transforms'
MESSAGE_ENCODING = 'cdr'
SCHEMA_ENCODING = 'ros2msg'


class PortInUse(OSError):
    """The WebSocket server could not bind its port."""


def frame_transforms(transforms: Iterable[Transform]) -> FrameTransforms:
    """foxglove.FrameTransforms of transforms (stamps in seconds)."""
    out = []
    for transform in transforms:
        seconds, nanoseconds = divmod(round(transform.stamp * 1e9), 1_000_000_000)
        out.append(FrameTransform(
            timestamp=Timestamp(sec=int(seconds), nsec=int(nanoseconds)),
            parent_frame_id=transform.parent, child_frame_id=transform.child,
            translation=Vector3(x=transform.translation[0], y=transform.translation[1],
                                z=transform.translation[2]),
            rotation=Quaternion(x=transform.rotation[0], y=transform.rotation[1],
                                z=transform.rotation[2], w=transform.rotation[3])))
    return FrameTransforms(transforms=out)


class _Listener:
    """foxglove-sdk calls this from its own threads: it only notes who subscribed."""

    def __init__(self, link: FoxgloveLink):
        self.link = link

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        with self.link.lock:
            self.link.subscribed.add(channel.id)


class FoxgloveLink:
    def __init__(self, host: str, port: int, name: str, definitions: MessageDefinitions):
        self.definitions = definitions
        self.lock = threading.Lock()
        self.subscribed: set[int] = set()        # channel ids subscribed since the last resend
        self.context = foxglove.Context()
        self.channels: dict[str, foxglove.Channel] = {}
        self.latest: dict[str, tuple[bytes, int]] = {}   # latched topics: last message, time
        self.services: list[str] = []
        try:
            self.server = foxglove.start_server(
                name=name, host=host, port=port, capabilities=[Capability.Services],
                supported_encodings=[MESSAGE_ENCODING], server_listener=_Listener(self),
                context=self.context)
        except RuntimeError as error:
            if 'bind' in str(error).lower():
                raise PortInUse(str(error)) from None
            raise
        self.port = self.server.port
        self.frames = FrameTransformsChannel(FRAMES_CHANNEL, context=self.context)
        self._frame_table: dict[str, Transform] = {}

    # ------------------------------------------------------------------ topics
    def advertise(self, topic: str, type_name: str, latched: bool) -> None:
        """A channel for ``topic``; DefinitionNotFound when the type has no .msg file."""
        schema = foxglove.Schema(name=type_name, encoding=SCHEMA_ENCODING,
                                 data=self.definitions.message(type_name).encode('utf-8'))
        self.channels[topic] = foxglove.Channel(topic, schema=schema,
                                                message_encoding=MESSAGE_ENCODING,
                                                context=self.context)
        if latched:
            self.latest.setdefault(topic, (b'', 0))

    def remove(self, topic: str) -> None:
        channel = self.channels.pop(topic, None)
        self.latest.pop(topic, None)
        if channel is not None:
            channel.close()

    def forward(self, topic: str, data: bytes, log_time: int) -> None:
        """One serialized message, unchanged; ``log_time`` in ns since the epoch."""
        channel = self.channels.get(topic)
        if channel is None:
            return
        if topic in self.latest:
            self.latest[topic] = (data, log_time)
        channel.log(data, log_time=log_time)

    # ------------------------------------------------------------------ frames
    def publish_transforms(self, transforms: list[Transform], log_time: int) -> None:
        for transform in transforms:
            self._frame_table[transform.child] = transform
        self.frames.log(frame_transforms(transforms), log_time=log_time)

    def resend_latched(self, log_time: int) -> None:
        """The latest message of each latched topic and every frame's latest transform
        again, for the clients that subscribed since the last call."""
        with self.lock:
            subscribed, self.subscribed = self.subscribed, set()
        if not subscribed:
            return
        for topic, (data, stamp) in list(self.latest.items()):
            channel = self.channels.get(topic)
            if data and channel is not None and channel.id() in subscribed:
                channel.log(data, log_time=stamp)
        if self.frames.id() in subscribed and self._frame_table:
            self.frames.log(frame_transforms(self._frame_table.values()), log_time=log_time)

    # ------------------------------------------------------------------ services
    def add_service(self, name: str, type_name: str, call: Callable[[bytes], bytes]) -> None:
        """A ROS service offered to the clients: ``call`` takes the request's CDR and returns
        the response's (an exception becomes the client's call failure)."""
        request, response = self.definitions.service(type_name)
        schema = foxglove.ServiceSchema(
            type_name,
            request=foxglove.MessageSchema(encoding=MESSAGE_ENCODING, schema=foxglove.Schema(
                name=f'{type_name}_Request', encoding=SCHEMA_ENCODING,
                data=request.encode('utf-8'))),
            response=foxglove.MessageSchema(encoding=MESSAGE_ENCODING, schema=foxglove.Schema(
                name=f'{type_name}_Response', encoding=SCHEMA_ENCODING,
                data=response.encode('utf-8'))))
        self.server.add_services([foxglove.Service(name, schema=schema,
                                                   handler=lambda request: call(request.payload))])
        self.services.append(name)

    def close(self) -> None:
        self.server.stop()
