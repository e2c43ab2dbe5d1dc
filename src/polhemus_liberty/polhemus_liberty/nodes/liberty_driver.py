"""ROS 2 node ``liberty_driver``: a thin adapter from :class:`LibertyDriver` to topics.

Publishes ``polhemus/<name>/pose`` (geometry_msgs/PoseStamped, reliable) for each station,
all stations of one tracker frame under one stamp, and ``diagnostics``
(diagnostic_msgs/DiagnosticArray) about once a second. The serial loop runs in its own
thread so a slow subscriber never stalls the port.
"""

from __future__ import annotations

from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from inhand_common.node_runner import run_node
from inhand_common.ros_diagnostics import NodeDiagnostics
from inhand_common.ros_names import station_pose_topic
from inhand_common.ros_parameters import declare_parameters
from inhand_common.ros_time import stamp_from_seconds
from polhemus_liberty.driver import LibertyDriver, PoseFrame
from polhemus_liberty.driver_config import DRIVER_PARAMETERS, DriverConfig

POSE_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


class LibertyDriverNode(Node):
    def __init__(self):
        super().__init__('liberty_driver')
        self.config = DriverConfig.from_parameters(declare_parameters(self, DRIVER_PARAMETERS))
        self._pose_publishers = {
            station: self.create_publisher(PoseStamped, station_pose_topic(name), POSE_QOS)
            for station, name in self.config.stations.items()}
        self.driver = LibertyDriver(self.config, self._publish_frame, log=self.get_logger())
        # Status named after the node, and logged the moment a fault shows (resyncs, drops).
        self.diagnostics = NodeDiagnostics(
            self, f'Polhemus Liberty on {self.config.port}', self.driver.report,
            name=f'{self.get_fully_qualified_name()}: Polhemus Liberty on {self.config.port}')
        self.driver.start()

    def _publish_frame(self, frame: PoseFrame) -> None:
        stamp = stamp_from_seconds(frame.stamp)
        frame_id = self.config.frame_id
        for station, (position, quaternion) in frame.poses.items():
            msg = PoseStamped()
            msg.header.stamp = stamp
            msg.header.frame_id = frame_id
            p, q = msg.pose.position, msg.pose.orientation
            p.x, p.y, p.z = float(position[0]), float(position[1]), float(position[2])
            q.x, q.y, q.z, q.w = (float(v) for v in quaternion)
            self._pose_publishers[station].publish(msg)

    def close(self) -> None:
        """Stop continuous output and close the port (called on Ctrl-C / SIGTERM)."""
        self.driver.stop()
        c = self.driver.counters()
        self.get_logger().info(
            f"stopped: {c['published_frames']} frames published, {c['dropped_frames']} "
            f"dropped, {c['incomplete_frames']} incomplete, {c['resyncs']} resyncs "
            f"({c['bytes_dropped']} bytes skipped), {c['resets']} resets, "
            f"{c['reconnects']} reconnects")


def main(args=None) -> int:
    return run_node('liberty_driver', LibertyDriverNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
