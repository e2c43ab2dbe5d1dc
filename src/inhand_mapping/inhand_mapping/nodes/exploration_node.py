"""ROS 2 node ``exploration_node``: the completed surface, its uncertainty and where to touch next.

Subscribes ``occupancy/occupied`` (the occupancy node's occupied cells, latched) and
``stereo/object`` (the stereo node's points of the object with the camera's position, when a
camera runs: the latest 4 pairs' count as surface, the space in front of them free; ``camera:
false`` leaves them out; implicit_surface.seen_cells). At most once
every ``period`` seconds, when the map has changed, it predicts the surface and ranks the next
touches (inhand_shape.touch_guidance, as ``predict_surface`` does offline) and publishes,
reliable and transient-local, in the map's frame:

* ``exploration/uncertainty`` (sensor_msgs/PointCloud2: x, y, z, ``intensity`` the standard
  deviation in m): the predicted surface's vertices, a heat map of what the map does not know;
* ``exploration/next_touch`` (geometry_msgs/PoseStamped): the best next touch, its x axis the
  approach direction (into the surface);
* ``exploration/next_touches`` (visualization_msgs/MarkerArray): every ranked touch as an
  ARROW ending on the surface, the best one larger;
* ``exploration/surface`` (visualization_msgs/Marker): the predicted surface, TRIANGLE_LIST
  coloured by its standard deviation (dark blue known, yellow a guess).

The prediction runs in a worker thread of its own, so the node keeps taking maps while it
computes, at a lower scheduling priority than the mapping nodes (nice +10), so that on a busy
machine the map's own latency does not grow.
``enabled: false`` turns it off (nothing computed or published; settable at run time). The
prior shape (a superquadric fit, most of the cost) is refitted only when the occupied cells
have grown by a quarter since the last fit. The graph's mode comes from the registration node
(graph_mode.py): in static mode the object stands on a support below its lowest cell, where
nothing is suggested, and the tracker's -z is up; in tracked mode it is held, +z up. The first
prediction waits up to 10 s for the mode; without one (no registration node) nothing is
excluded.
"""

from __future__ import annotations

import os
import threading
import time
from collections import deque
from typing import Any

import numpy as np
from geometry_msgs.msg import Point, Pose, PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from inhand_common.cell_lattice import infer_lattice
from inhand_common.node_runner import run_node
from inhand_common.point_cloud import from_point_cloud2, to_point_cloud2
from inhand_common.ros_parameters import declare_parameters
from inhand_common.rotations import matrix_to_quaternion
from inhand_mapping.cloud_layouts import seen_points
from inhand_mapping.graph_mode import GraphModeQuery
from inhand_mapping.qos import LATCHED_QOS
from inhand_shape.implicit_surface import SurfacePrior
from inhand_shape.shape_extraction import mode_orientation
from inhand_shape.touch_guidance import (
    EXPLORATION_NODE_PARAMETERS,
    Guidance,
    guide,
    std_colours,
)

NICENESS = 10           # added to the process's nice value (lower priority than the map)
MODE_WAIT = 10.0        # s: no prediction without the graph's mode before this (the support)
REFIT_GROWTH = 1.25      # the prior is refitted when the occupied cells grew by this factor
ARROW_LENGTH = 0.03      # m
SEEN_PAIRS = 4           # the latest stereo pairs whose object points count (a turned object
                         # shows other sides; older pairs of a held object are still right)


class ExplorationNode(Node):
    def __init__(self):
        super().__init__('exploration_node')
        self.parameters = declare_parameters(self, EXPLORATION_NODE_PARAMETERS)
        self._lock = threading.Lock()
        self._cells: Any = None
        self._frame_id = 'object'
        self._version = 0            # maps received
        self._done = 0               # the version last predicted
        self._prior: SurfacePrior | None = None
        self._prior_cells = 0
        self.predictions = 0
        self._mode: str | None = None
        self._started = time.monotonic()
        self._graph_mode = GraphModeQuery(self, self._on_graph_mode)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.create_subscription(PointCloud2, 'occupancy/occupied', self._on_map, LATCHED_QOS)
        self._seen: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=SEEN_PAIRS)
        self.create_subscription(PointCloud2, 'stereo/object', self._on_seen, LATCHED_QOS)
        self._uncertainty = self.create_publisher(PointCloud2, 'exploration/uncertainty', LATCHED_QOS)
        self._next_touch = self.create_publisher(PoseStamped, 'exploration/next_touch', LATCHED_QOS)
        self._touches = self.create_publisher(MarkerArray, 'exploration/next_touches', LATCHED_QOS)
        self._surface = self.create_publisher(Marker, 'exploration/surface', LATCHED_QOS)
        self.create_timer(self.parameters['period'], self._wake.set)
        self._worker = threading.Thread(target=self._work_loop, name='exploration', daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"ready: the predicted surface and {self.parameters['suggestions']} next touches of "
            f"occupancy/occupied at most every {self.parameters['period']:g} s"
            + ('' if self.parameters['enabled'] else ' (disabled: enabled is false)'))

    def _on_graph_mode(self, mode: str, node: str) -> None:
        with self._lock:
            self._mode = mode
            self._version += 1           # predict again with the support known
        self.get_logger().info(f'the graph is in {mode} mode (from {node})')

    def _on_map(self, msg: PointCloud2) -> None:
        cells = from_point_cloud2(msg)
        with self._lock:
            self._cells = cells
            self._frame_id = msg.header.frame_id or 'object'
            self._version += 1

    def _on_seen(self, msg: PointCloud2) -> None:
        points = seen_points(from_point_cloud2(msg))
        with self._lock:
            self._seen.append(points)
            if self.get_parameter('camera').value:
                self._version += 1

    def _work_loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait()
            self._wake.clear()
            if self._stop.is_set():
                return
            if self.get_parameter('enabled').value:
                try:
                    self._predict()
                except Exception as error:   # a bad map must not kill the node: say it
                    self.get_logger().error(f'prediction failed: {error!r}')

    def _predict(self) -> None:
        with self._lock:
            cells, frame_id, version, mode = self._cells, self._frame_id, self._version, self._mode
            seen = list(self._seen) if self.get_parameter('camera').value else []
        if cells is None or version == self._done or len(cells) < 2:
            return
        if mode is None and time.monotonic() - self._started < MODE_WAIT:
            return      # the registration node answers within a second in a running graph
        self._done = version
        centres = np.stack([cells['x'], cells['y'], cells['z']], axis=1).astype(np.float64)
        lattice = infer_lattice(centres)
        if lattice is None:
            return
        occupied = int(np.count_nonzero(cells['intensity'] >= self.parameters['occupied_threshold']))
        if self._prior is not None and occupied > REFIT_GROWTH * self._prior_cells:
            self._prior = None
        up, on_support = mode_orientation(mode)
        started = time.monotonic()
        guidance = guide(centres, cells['intensity'], lattice.resolution, self.parameters,
                         up=up, on_support=on_support, frame_id=frame_id, prior=self._prior,
                         seen=np.concatenate([p for p, _ in seen]) if seen else None,
                         seen_from=np.concatenate([v for _, v in seen]) if seen else None)
        if self._prior is None and not guidance.surface.empty:
            self._prior, self._prior_cells = guidance.surface.prior, occupied
        self._publish(guidance)
        self.predictions += 1
        self.get_logger().debug(f'{guidance.summary()} ({time.monotonic() - started:.2f} s)')

    def _publish(self, guidance: Guidance) -> None:
        stamp = self.get_clock().now().to_msg()
        frame_id = guidance.frame_id
        surface = guidance.surface
        cloud = np.zeros(len(surface.vertices), dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                                                       ('intensity', '<f4')])
        for k, axis in enumerate('xyz'):
            cloud[axis] = surface.vertices[:, k]
        cloud['intensity'] = surface.vertex_std
        self._uncertainty.publish(to_point_cloud2(cloud, frame_id, stamp))
        mesh = Marker()
        mesh.header.frame_id, mesh.header.stamp = frame_id, stamp
        mesh.ns, mesh.id, mesh.type, mesh.action = 'predicted surface', 0, Marker.TRIANGLE_LIST, Marker.ADD
        mesh.pose.orientation.w = 1.0
        mesh.scale.x = mesh.scale.y = mesh.scale.z = 1.0
        mesh.color = ColorRGBA(r=1.0, g=1.0, b=1.0, a=0.9)
        corners = surface.faces.ravel()
        mesh.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in surface.vertices[corners]]
        mesh.colors = [ColorRGBA(r=float(r), g=float(g), b=float(b), a=0.9)
                       for r, g, b in std_colours(surface.vertex_std[corners], surface.settings.signal_std)]
        self._surface.publish(mesh)
        array = MarkerArray()
        clear = Marker()
        clear.header.frame_id = frame_id
        clear.action = Marker.DELETEALL
        array.markers = [clear]
        for rank, touch in enumerate(guidance.suggestions):
            pose = _pose(touch.position - ARROW_LENGTH * touch.approach, touch.approach)
            arrow = Marker()
            arrow.header.frame_id, arrow.header.stamp = frame_id, stamp
            arrow.ns, arrow.id, arrow.type, arrow.action = 'next touches', rank, Marker.ARROW, Marker.ADD
            arrow.pose = pose
            width = 0.004 if rank == 0 else 0.0025
            arrow.scale.x, arrow.scale.y, arrow.scale.z = ARROW_LENGTH, width, width
            arrow.color = ColorRGBA(r=0.9, g=0.15, b=0.15, a=1.0 if rank == 0 else 0.6)
            array.markers.append(arrow)
        self._touches.publish(array)
        if guidance.suggestions:
            best = guidance.suggestions[0]
            message = PoseStamped()
            message.header.frame_id, message.header.stamp = frame_id, stamp
            message.pose = _pose(best.position, best.approach)
            self._next_touch.publish(message)

    def destroy_node(self) -> bool:
        self._stop.set()
        self._wake.set()
        self._worker.join(timeout=5.0)
        return super().destroy_node()


def _pose(position: np.ndarray, approach: np.ndarray) -> Pose:
    """A geometry_msgs/Pose at ``position`` whose x axis is ``approach`` (unit)."""
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in position)
    helper = np.array([0.0, 0.0, 1.0]) if abs(approach[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    side = np.cross(helper, approach)
    side /= np.linalg.norm(side)
    x, y, z, w = matrix_to_quaternion(np.stack([approach, side, np.cross(approach, side)], axis=1))
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = \
        float(x), float(y), float(z), float(w)
    return pose


def main(args=None) -> int:
    # The map comes first: on a busy machine this node's predictions wait for the mapping
    # nodes (a lower scheduling priority), so the map's own latency does not grow.
    os.nice(NICENESS)
    return run_node('exploration_node', ExplorationNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
