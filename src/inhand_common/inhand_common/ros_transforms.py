"""Publishing the graph's frames so that visualisers place the map, the fingertips, the
object and the camera together.

A full ROS 2 install has tf2_msgs: the frames go on ``/tf`` and ``/tf_static``
(tf2_msgs/TFMessage) as tf2's broadcasters send them. The pip runtime has no tf2_msgs
wheel, so every transform also goes out as one geometry_msgs/TransformStamped on the
relative topics ``transforms`` (changing frames) and ``transforms_static`` (latched),
which ``live_view`` turns into Foxglove FrameTransforms and ``topic_echo`` prints.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

try:   # a full ROS 2 install
    from tf2_msgs.msg import TFMessage
except ImportError:   # the pip runtime
    TFMessage = None

__all__ = ['HAS_TF2_MSGS', 'TRANSFORMS_STATIC_TOPIC', 'TRANSFORMS_TOPIC', 'Transform',
           'TransformPublisher']

HAS_TF2_MSGS = TFMessage is not None
TRANSFORMS_TOPIC = 'transforms'
TRANSFORMS_STATIC_TOPIC = 'transforms_static'

# As tf2's broadcasters: /tf reliable volatile depth 100; /tf_static latched.
DYNAMIC_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
STATIC_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)


class Transform(NamedTuple):
    """``child`` in ``parent`` at ``stamp`` (builtin_interfaces/Time): translation (m) and
    quaternion x, y, z, w."""

    stamp: object
    parent: str
    child: str
    translation: Sequence[float]
    rotation: Sequence[float]


def _message(transform: Transform) -> TransformStamped:
    msg = TransformStamped()
    msg.header.stamp = transform.stamp
    msg.header.frame_id = transform.parent
    msg.child_frame_id = transform.child
    t, q = msg.transform.translation, msg.transform.rotation
    t.x, t.y, t.z = (float(v) for v in transform.translation)
    q.x, q.y, q.z, q.w = (float(v) for v in transform.rotation)
    return msg


class TransformPublisher:
    """A node's frames: ``send`` for those that move, ``send_static`` for fixed ones (kept
    and latched, so a viewer started later still gets them)."""

    def __init__(self, node: Node):
        self._dynamic = node.create_publisher(TransformStamped, TRANSFORMS_TOPIC, DYNAMIC_QOS)
        self._static = node.create_publisher(TransformStamped, TRANSFORMS_STATIC_TOPIC,
                                             STATIC_QOS)
        self._tf = self._tf_static = None
        self._static_frames: dict[str, TransformStamped] = {}
        if HAS_TF2_MSGS:
            self._tf = node.create_publisher(TFMessage, '/tf', DYNAMIC_QOS)
            self._tf_static = node.create_publisher(TFMessage, '/tf_static', STATIC_QOS)

    def send(self, transforms: Sequence[Transform]) -> None:
        messages = [_message(t) for t in transforms]
        for msg in messages:
            self._dynamic.publish(msg)
        if self._tf is not None and messages:
            self._tf.publish(TFMessage(transforms=messages))

    def send_static(self, transforms: Sequence[Transform]) -> None:
        for transform in transforms:
            msg = _message(transform)
            self._static_frames[msg.child_frame_id] = msg
            self._static.publish(msg)
        if self._tf_static is not None and transforms:
            # tf2's static broadcaster sends every static frame it holds each time.
            self._tf_static.publish(TFMessage(transforms=list(self._static_frames.values())))
