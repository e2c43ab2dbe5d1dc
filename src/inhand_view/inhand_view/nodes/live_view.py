"""ROS 2 node ``live_view``: the graph served to Foxglove / Lichtblick and to a web page.

Every ``scan_period`` the node looks at the graph (``get_topic_names_and_types``) and
subscribes, raw (the serialized CDR, never decoded for forwarding), to every topic that
has a publisher, with a QoS that matches the publishers (transient-local where they all
are, so the latched maps arrive); a topic whose publishers are gone is dropped. Each
message goes, unchanged and stamped with its receive time, to the Foxglove WebSocket
server (``ws://host:foxglove_port``; foxglove_link.py), and the ones the page shows are
decoded into the page's state (view_state.py):

* ``occupancy/cloud``, ``occupancy/occupied``, ``occupancy/textured``: the map, its
  occupied cells, the camera's colours; ``occupancy/updates`` (20 Hz: the changed cells
  and the provisional ones under the fingertips) merged into the map between whole maps;
* ``registration/points``: the fingertips and their trails;
* ``transforms`` and ``transforms_static`` (geometry_msgs/TransformStamped, one transform
  per message), ``/tf`` and ``/tf_static`` where tf2_msgs is installed (a full ROS
  install): the frames, also served to Foxglove as ``foxglove.FrameTransforms`` on
  ``/frame_transforms``;
* ``diagnostics``: the latest status of each node that reports one.

* ``shape/parts`` (visualization_msgs/MarkerArray, the shape node's): the superquadric
  parts and the grasps, drawn over the map.
* ``exploration/uncertainty`` (PointCloud2, the exploration node's predicted surface with
  its standard deviation) and ``exploration/next_touches`` (MarkerArray of ARROWs): the
  heat map of what the map does not know and where to touch next.

The page (``http://host:http_port/``, page_server.py) runs in threads of its own. Its reset,
save and shape buttons, and Foxglove's service calls of ``occupancy/reset``,
``occupancy/save`` and ``shape/extract`` (std_srvs/Trigger, offered under their names in
this node's namespace), call the graph's services of those names and pass the answer back.
A port that is taken stops the node at start with one line naming the parameter and the
port, exit code 2.
"""

from __future__ import annotations

import time
from functools import partial

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TransformStamped
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from inhand_common.node_runner import run_node
from inhand_common.parameters import ParameterError
from inhand_common.point_cloud import decode_point_cloud2
from inhand_common.ros_clock import steady_timer
from inhand_common.ros_parameters import declare_parameters
from inhand_common.rotations import rotate_vectors
from inhand_mapping.cloud_layouts import unpack_registered
from inhand_tools.message_types import UnknownMessageType, message_class
from inhand_tools.qos_profiles import matching_qos
from inhand_view.foxglove_link import FRAMES_CHANNEL, FoxgloveLink, PortInUse
from inhand_view.frame_tree import Transform
from inhand_view.page_server import PageServer
from inhand_view.ros2msg_schemas import DefinitionNotFound, MessageDefinitions
from inhand_view.view_config import VIEW_PARAMETERS, ViewConfig
from inhand_view.view_state import ViewState

try:   # tf2_msgs has no pip wheel: /tf and /tf_static only on a full ROS install
    from tf2_msgs.msg import TFMessage
except ImportError:
    TFMessage = None

SUBSCRIPTION_DEPTH = 100
TICK = 0.2          # s: latched messages for new Foxglove subscribers, service availability
# the page's buttons and Foxglove's service calls -> the graph's services
SERVICES = {'reset': 'occupancy/reset', 'save': 'occupancy/save', 'shape': 'shape/extract'}
MARKER_KINDS = {Marker.TRIANGLE_LIST: 'triangles', Marker.LINE_LIST: 'lines'}


def arrow_ends(marker: Marker) -> tuple[np.ndarray, np.ndarray]:
    """(tail, tip) m of an ARROW marker given by its pose: from the position along the
    pose's x axis, scale.x long."""
    q = marker.pose.orientation
    tail = np.array([marker.pose.position.x, marker.pose.position.y, marker.pose.position.z])
    return tail, tail + marker.scale.x * rotate_vectors(np.array([q.x, q.y, q.z, q.w]),
                                                        np.array([1.0, 0.0, 0.0]))


class PortBusy(ParameterError):
    """A port parameter whose port is taken: said in one line."""

    def __str__(self) -> str:
        return self.problems[0]


def port_busy(parameter: str, host: str, port: int, error: Exception) -> PortBusy:
    return PortBusy([f"parameter '{parameter}' = {port} is refused: {host}:{port} is in use "
                     f'({getattr(error, "strerror", None) or error}); choose another port'])


def transform_of(msg, static: bool) -> Transform:
    """A geometry_msgs/TransformStamped as a Transform."""
    t, q = msg.transform.translation, msg.transform.rotation
    return Transform(msg.header.frame_id, msg.child_frame_id,
                     msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9,
                     (t.x, t.y, t.z), (q.x, q.y, q.z, q.w), static)


class LiveView(Node):
    def __init__(self) -> None:
        super().__init__('live_view')
        self.config = config = ViewConfig.from_parameters(declare_parameters(self,
                                                                             VIEW_PARAMETERS))
        self.state = ViewState(config.settings)
        self._triggers = {name: self.create_client(Trigger, service)
                          for name, service in SERVICES.items()}
        self._service_names = {name: self.resolve_service_name(service)
                               for name, service in SERVICES.items()}
        try:
            self.page = PageServer(config.host, config.http_port, self.state.snapshot,
                                   {name: partial(self.call_trigger, name) for name in SERVICES})
        except OSError as error:
            raise port_busy('http_port', config.host, config.http_port, error) from None
        try:
            self.link = FoxgloveLink(config.host, config.foxglove_port,
                                     self.get_fully_qualified_name(), MessageDefinitions())
        except PortInUse as error:
            self.page.close()
            raise port_busy('foxglove_port', config.host, config.foxglove_port, error) from None
        for name in SERVICES:
            self.link.add_service(self._service_names[name], 'std_srvs/srv/Trigger',
                                  partial(self._foxglove_trigger, name))
        self.page.start()
        self._decoders = {self.resolve_topic_name(name): decoder for name, decoder in (
            ('occupancy/cloud', self._on_map), ('occupancy/updates', self._on_updates),
            ('occupancy/occupied', self._on_occupied),
            ('occupancy/textured', self._on_textured), ('registration/points', self._on_points),
            ('shape/parts', self._on_shape),
            ('exploration/uncertainty', self._on_uncertainty),
            ('exploration/next_touches', self._on_next_touches),
            ('transforms', partial(self._on_transform, static=False)),
            ('transforms_static', partial(self._on_transform, static=True)),
            ('diagnostics', self._on_diagnostics))}
        if TFMessage is not None:
            self._decoders['/tf'] = partial(self._on_tf, static=False)
            self._decoders['/tf_static'] = partial(self._on_tf, static=True)
        self._forwarded: dict[str, tuple[object, str, tuple]] = {}   # topic: sub, type, QoS
        self._refused: set[str] = set()      # topics said once not to be forwardable
        self._failed: set[str] = set()       # topics said once not to decode
        self._refused_frames: set[tuple[str, str]] = set()   # transforms said once unusable
        steady_timer(self, config.scan_period, self._scan)   # whatever /clock does
        steady_timer(self, TICK, self._tick)
        self._scan()
        self.get_logger().info(
            f'page at {self.page.url}; Foxglove WebSocket at ws://{config.host}:{self.link.port} '
            f'(frames on {FRAMES_CHANNEL}; services {", ".join(self.link.services)})')

    # ------------------------------------------------------------------ the graph
    def _scan(self) -> None:
        graph = dict(self.get_topic_names_and_types())
        for topic in list(self._forwarded):
            if topic not in graph or self.count_publishers(topic) == 0:
                self._drop(topic)
        for topic, types in graph.items():
            publishers = self.get_publishers_info_by_topic(topic)
            if not types or not publishers or topic in self._refused:
                continue
            qos = matching_qos(publishers, depth=SUBSCRIPTION_DEPTH)
            key = (qos.reliability, qos.durability)
            known = self._forwarded.get(topic)
            if known is not None and known[1] == types[0] and known[2] == key:
                continue
            if known is not None:
                self._drop(topic)
            self._subscribe(topic, types[0], qos, key)
        self.state.set_topics(len(self._forwarded),
                              {'port': self.link.port, 'frames': FRAMES_CHANNEL,
                               'services': list(self.link.services)})

    def _subscribe(self, topic: str, type_name: str, qos, key: tuple) -> None:
        try:
            msg_type = message_class(type_name)
            self.link.advertise(topic, type_name,
                                latched=qos.durability == DurabilityPolicy.TRANSIENT_LOCAL)
        except (UnknownMessageType, DefinitionNotFound) as error:
            self._refused.add(topic)
            self.get_logger().warning(f'{topic} is not forwarded: {error}')
            return
        # No QoS event handlers (rclpy adds two per subscription by default, to log an
        # incompatible QoS): the default executor rebuilds its wait set in Python for every
        # message, and at 960 poses/s those handlers were most of this node's CPU time.
        subscription = self.create_subscription(
            msg_type, topic, partial(self._on_message, topic), qos, raw=True,
            event_callbacks=SubscriptionEventCallbacks(use_default_callbacks=False))
        self._forwarded[topic] = (subscription, type_name, key)

    def _drop(self, topic: str) -> None:
        subscription, _, _ = self._forwarded.pop(topic)
        self.destroy_subscription(subscription)
        self.link.remove(topic)

    def _tick(self) -> None:
        self.link.resend_latched(time.time_ns())
        for error in self.page.take_errors():
            self.get_logger().error(f'page: {error}')
        self.state.set_services({name: client.service_is_ready()
                                 for name, client in self._triggers.items()})

    # ------------------------------------------------------------------ messages
    def _on_message(self, topic: str, data: bytes) -> None:
        self.link.forward(topic, data, time.time_ns())
        self.state.message_arrived(topic)
        decoder = self._decoders.get(topic)
        if decoder is None:
            return
        try:
            decoder(data)
        except Exception as error:   # one bad message must not stop the view
            if topic not in self._failed:
                self._failed.add(topic)
                self.get_logger().warning(f'{topic}: cannot show this message on the page '
                                          f'({type(error).__name__}: {error})')

    def _on_map(self, data: bytes) -> None:
        cloud = decode_point_cloud2(data)
        self.state.set_map(cloud.points, cloud.frame_id)

    def _on_updates(self, data: bytes) -> None:
        cloud = decode_point_cloud2(data)
        self.state.apply_updates(cloud.points, cloud.frame_id)

    def _on_occupied(self, data: bytes) -> None:
        self.state.set_occupied(len(decode_point_cloud2(data).points))

    def _on_textured(self, data: bytes) -> None:
        self.state.set_textured(decode_point_cloud2(data).points)

    def _on_shape(self, data: bytes) -> None:
        markers = deserialize_message(data, MarkerArray).markers
        drawn = [m for m in markers if m.action == Marker.ADD and m.type in MARKER_KINDS]
        self.state.set_shape(
            [(m.ns, MARKER_KINDS[m.type], np.array([[p.x, p.y, p.z] for p in m.points]).reshape(-1, 3),
              (m.color.r, m.color.g, m.color.b, m.color.a)) for m in drawn],
            drawn[0].header.frame_id if drawn else 'object')

    def _on_uncertainty(self, data: bytes) -> None:
        cloud = decode_point_cloud2(data)
        points = cloud.points
        self.state.set_uncertainty(np.stack([points['x'], points['y'], points['z']], axis=1),
                                   points['intensity'], cloud.frame_id)

    def _on_next_touches(self, data: bytes) -> None:
        markers = [m for m in deserialize_message(data, MarkerArray).markers
                   if m.action == Marker.ADD and m.type == Marker.ARROW]
        self.state.set_next_touches([arrow_ends(m) for m in sorted(markers, key=lambda m: m.id)],
                                    markers[0].header.frame_id if markers else 'object')

    def _on_points(self, data: bytes) -> None:
        points, times, fingers = unpack_registered(decode_point_cloud2(data).points)
        if len(points):
            self.state.add_registered(points, fingers, times)

    def _on_transform(self, data: bytes, static: bool) -> None:
        self._add_transforms([transform_of(deserialize_message(data, TransformStamped), static)])

    def _on_tf(self, data: bytes, static: bool) -> None:
        message = deserialize_message(data, TFMessage)
        self._add_transforms([transform_of(t, static) for t in message.transforms])

    def _add_transforms(self, transforms: list[Transform]) -> None:
        usable = []
        for transform in transforms:
            if self.state.add_transform(transform):
                usable.append(transform)
            elif (transform.parent, transform.child) not in self._refused_frames:
                self._refused_frames.add((transform.parent, transform.child))
                self.get_logger().warning(
                    f'a transform of {transform.child!r} in {transform.parent!r} is not usable '
                    f'(translation {transform.translation}, rotation {transform.rotation}); '
                    'left out')
        if usable:
            self.link.publish_transforms(usable, time.time_ns())

    def _on_diagnostics(self, data: bytes) -> None:
        message = deserialize_message(data, DiagnosticArray)
        self.state.set_diagnostics([
            {'name': s.name, 'level': s.level[0] if isinstance(s.level, bytes) else int(s.level),
             'message': s.message, 'hardware_id': s.hardware_id,
             'values': [[kv.key, kv.value] for kv in s.values]} for s in message.status])

    # ------------------------------------------------------------------ services
    def call_trigger(self, name: str) -> tuple[bool, str]:
        """Call the graph's service behind ``name`` (SERVICES; from the page's or Foxglove's
        threads: the executor answers); (success, message)."""
        client, service = self._triggers[name], self._service_names[name]
        if not client.service_is_ready():
            success, message = False, f'{service} is not offered (is its node running?)'
        else:
            future = client.call_async(Trigger.Request())
            deadline = time.monotonic() + self.config.service_timeout
            while not future.done() and time.monotonic() < deadline:
                time.sleep(0.01)
            if future.done():
                result = future.result()
                success, message = bool(result.success), result.message
            else:
                success, message = False, (f'{service} did not answer within '
                                           f'{self.config.service_timeout:g} s')
        self.state.record_call(name, success, message)
        self.get_logger().info(f'{service}: {"done" if success else "failed"}: {message}')
        return success, message

    def _foxglove_trigger(self, name: str, _request: bytes) -> bytes:
        success, message = self.call_trigger(name)
        return serialize_message(Trigger.Response(success=success, message=message))

    def close(self) -> None:
        self.page.close()
        self.link.close()
        counts = self.state.snapshot(since=self.state.map_version)['counts']
        self.get_logger().info(f'stopped: forwarded {counts["topics"]} topics; last map '
                               f'{counts["cells"]} cells, {counts["fingertip_points"]} '
                               f'fingertip points')


def main(args=None) -> int:
    # Not the events executor of the mapping nodes: this node subscribes as topics appear,
    # and Jazzy's EventsExecutor did not deliver a subscription made after spinning began
    # (the page's test saw no registration/points).
    return run_node('live_view', LiveView, args)


if __name__ == '__main__':
    raise SystemExit(main())
