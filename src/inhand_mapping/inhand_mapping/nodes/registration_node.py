"""ROS 2 node ``registration_node``: fingertip poses -> points in the object (map) frame.

Subscribes ``polhemus/<finger>/pose`` for each finger name and, in tracked mode,
``polhemus/<object_name>/pose`` (geometry_msgs/PoseStamped, reliable). Publishes every
``publish_period`` the points registered since the last message on
``registration/points`` (sensor_msgs/PointCloud2, layout in cloud_layouts.py, frame ``object``),
and once, latched, the pose of the ``object`` frame in the tracker frame on
``registration/object_frame`` (geometry_msgs/PoseStamped: the object sensor's first pose;
identity in static mode).

Frames (ros_transforms.py): the object's current pose (``object`` in ``polhemus_source``,
or identity and latched in static mode) and each fingertip (``fingertip_<name>``) on
``transforms`` and, on a full ROS install, ``/tf``; names from the frame parameters.
``diagnostics`` about once a second (node_health.py): rates, counters, and the moment
fingertips are dropped or the object sensor falls silent, a warning in the log too.

Processing runs on steady-clock timers, so the node maps the same under ``use_sim_time``
whether or not anything publishes ``/clock`` (and says so when nothing does).

Poses are taken raw (``raw=True``) and decoded by pose_cdr: at 240 Hz x 4 stations,
rclpy's own deserialisation would be most of this node's time.
"""

from __future__ import annotations

import time

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from inhand_common.health import Problems
from inhand_common.node_runner import run_node
from inhand_common.point_cloud import serialize_point_cloud2
from inhand_common.ros_clock import steady_timer
from inhand_common.ros_diagnostics import NodeDiagnostics
from inhand_common.ros_matches import logged_publisher_matches, logged_subscription_matches
from inhand_common.ros_parameters import declare_parameters
from inhand_common.ros_time import stamp_from_nanoseconds, stamp_from_seconds
from inhand_common.ros_transforms import Transform, TransformPublisher
from inhand_mapping.cloud_layouts import pack_registered
from inhand_mapping.mapping_config import REGISTRATION_PARAMETERS, RegistrationConfig
from inhand_mapping.node_health import RegistrationActivity, RegistrationHealth
from inhand_mapping.pose_cdr import decode_pose_stamped_many, stamp_seconds
from inhand_mapping.qos import DATA_QOS, LATCHED_QOS

POSE_QOS = POINTS_QOS = DATA_QOS


class RegistrationNode(Node):
    def __init__(self):
        super().__init__('registration_node')
        self.config = RegistrationConfig.from_parameters(
            declare_parameters(self, REGISTRATION_PARAMETERS))
        self.registrar = self.config.make_registrar()
        self.fingers = list(self.config.finger_names)
        self.frames = self.config.frames
        # Callbacks only keep the raw messages; the timer decodes them in batches
        # (pose_cdr.decode_pose_stamped_many) and registers them: at 240 Hz x 4 stations,
        # and much more in a fast replay, per-message Python work is what limits the node.
        self._raw_fingertips: list[list[bytes]] = [[] for _ in self.fingers]
        self._raw_objects: list[bytes] = []
        for topic, index in self.config.finger_topics.items():
            self.create_subscription(PoseStamped, topic, self._raw_fingertips[index].append,
                                     POSE_QOS, raw=True,
                                     event_callbacks=logged_subscription_matches(self, topic))
        if self.config.object_topic is not None:
            self.create_subscription(
                PoseStamped, self.config.object_topic, self._raw_objects.append, POSE_QOS,
                raw=True, event_callbacks=logged_subscription_matches(self,
                                                                      self.config.object_topic))
        # Points published while no reader is matched reach nobody (the topic is volatile):
        # the matches are logged and such points counted, so a loss is never silent.
        self._points = self.create_publisher(
            PointCloud2, 'registration/points', POINTS_QOS,
            event_callbacks=logged_publisher_matches(self, 'registration/points'))
        self.activity = RegistrationActivity()
        self._taken = 0        # pose messages taken in (diagnostics: is data arriving?)
        self._object_frame = self.create_publisher(PoseStamped, 'registration/object_frame',
                                                   LATCHED_QOS)
        self._frame_sent = False
        self.transforms = TransformPublisher(self)
        steady_timer(self, self.config.publish_period, self._publish)
        if not self.config.tracked:
            identity = (np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))
            self._send_object_frame(*identity)
            self.transforms.send_static([Transform(
                self.get_clock().now().to_msg(), self.frames.tracker_frame,
                self.frames.map_frame, *identity)])
        self.health = RegistrationHealth(time.monotonic(), self.config.object_topic,
                                         self.config.max_gap, self.config.max_pending)
        self.diagnostics = NodeDiagnostics(self, 'registration', self._report,
                                           data_count=lambda: self._taken)
        self.get_logger().info(
            f"registering {', '.join(self.fingers)} in {self.config.mode} mode"
            + (f' against {self.config.object_name}' if self.config.tracked
               else ' (map frame = tracker frame)'))

    def _take_received(self) -> None:
        """Decode and register what the subscriptions kept since the last call."""
        now = time.monotonic()
        latest: list[Transform] = []   # the newest pose of each sensor, as a frame
        objects, self._raw_objects[:] = list(self._raw_objects), []
        if objects:
            self._taken += len(objects)
            stamps, _, poses = decode_pose_stamped_many(objects)
            for t, pose in zip(stamp_seconds(stamps).tolist(), poses):
                self.registrar.add_object_pose(t, pose[:3], pose[3:])
            if not self._frame_sent and self.registrar.first_object_pose is not None:
                self._send_object_frame(*self.registrar.first_object_pose)
            latest.append(self._frame_of(stamps, poses, self.frames.map_frame))
        for index, buffer in enumerate(self._raw_fingertips):
            raw, buffer[:] = list(buffer), []
            if raw:
                self._taken += len(raw)
                stamps, _, poses = decode_pose_stamped_many(raw)
                self.registrar.add_fingertips(stamp_seconds(stamps), poses[:, :3], index,
                                              now=now, quaternions=poses[:, 3:])
                latest.append(self._frame_of(stamps, poses,
                                             self.frames.fingertip_frame(self.fingers[index])))
        if latest:
            self.transforms.send(latest)

    def _frame_of(self, stamps, poses, child: str) -> Transform:
        """The last of decoded poses as the frame ``child`` in the tracker frame."""
        return Transform(stamp_from_nanoseconds(stamps[-1]), self.frames.tracker_frame, child,
                         poses[-1, :3], poses[-1, 3:])

    def _send_object_frame(self, position, quaternion) -> None:
        msg = PoseStamped()
        msg.header.frame_id = self.frames.tracker_frame
        msg.header.stamp = self.get_clock().now().to_msg()
        p, q = msg.pose.position, msg.pose.orientation
        p.x, p.y, p.z = (float(v) for v in position)
        q.x, q.y, q.z, q.w = (float(v) for v in quaternion)
        self._object_frame.publish(msg)
        self._frame_sent = True

    def _publish(self) -> None:
        self._take_received()
        points, times, fingers = self.registrar.drain(now=time.monotonic())
        if len(points) == 0:
            return
        self.activity.published += len(points)
        if self._points.get_subscription_count() == 0:
            self.activity.unheard += len(points)   # diagnostics warn, and the log
        cloud = pack_registered(points, times, fingers)
        stamp = stamp_from_seconds(times[-1])
        self._points.publish(serialize_point_cloud2(cloud, self.frames.map_frame, stamp.sec,
                                                    stamp.nanosec))

    def _report(self, now: float, problems: Problems) -> tuple[str, dict[str, object]]:
        self.activity.subscribers = self._points.get_subscription_count()
        return self.health.report(now, self.registrar.stats, self.activity, problems)

    def close(self) -> None:
        if self.activity.unheard:
            self.get_logger().warning(f'{self.activity.unheard} of {self.activity.published} '
                                      'registered points were published while nothing '
                                      'subscribed')
        stats = self.registrar.stats
        self.get_logger().info(
            f'stopped: {stats.registered} of {stats.received} fingertip positions registered; '
            f'dropped {stats.dropped_gap} (object pose gap), {stats.dropped_before_object} '
            f'(before the first object pose), {stats.dropped_invalid} (invalid), '
            f'{stats.dropped_old_stream} (in flight when the time went back); '
            f'{stats.pending} pending; {stats.object_poses} object poses, '
            f'{stats.object_out_of_order} out of order, {stats.object_invalid} invalid; '
            f'{stats.restarts} new stream(s) after the time went back')
        if self.registrar.pad_normals is not None:
            self.get_logger().info(self.registrar.pad_normals.summary())


def main(args=None) -> int:
    return run_node('registration_node', RegistrationNode, args, executor_factory=EventsExecutor)


if __name__ == '__main__':
    raise SystemExit(main())
