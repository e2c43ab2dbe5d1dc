"""ROS 2 node ``shape_node``: the map's surface mesh, superquadric parts and grasps on request.

Subscribes ``occupancy/occupied`` (the occupancy node's occupied cells, latched; its
``layer`` field tells the parts which cells the cell judge rescued) and
``registration/points`` (the registered fingertip positions the map is made of: where in
each occupied cell they fell places the parts' last fit to better than a cell, as the map
file's contact centroids do for ``extract_shape``; the newest :data:`KEPT_POSITIONS`
are kept, each cell's newest as many as the map's hits there, so that positions from
before an ``occupancy/reset`` drop out; a cell none of them fell in counts with its centre;
with none placed, the cells are fitted with their slack, as from a PLY). The service
``shape/extract`` (std_srvs/Trigger) runs the shape extraction (inhand_shape.shape_extraction)
on the latest map and publishes, reliable and transient-local, in the map's frame:

* ``shape/parts`` (visualization_msgs/MarkerArray): each part as a TRIANGLE_LIST (the
  graspable part orange), the grasps as a LINE_LIST between their contacts;
* ``shape/surface`` (visualization_msgs/Marker): the surface mesh, TRIANGLE_LIST.

The answer is the one-line summary (parts, graspable part, grasps, holes) and how many cells
the registered positions placed; ``success`` is
false when there is no map yet or no part explains the cells (the message says why).
Parameters: friction, max_parts, occupied_threshold (the ``shape_node`` section). The graph's
mode comes from the registration node (graph_mode.py): in static mode the object stands on a
support, and its parts may be held upright on it (docs/shape.md, "Upright on a support").
"""

from __future__ import annotations

import time

import numpy as np
from geometry_msgs.msg import Point
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import ColorRGBA
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from inhand_common.cell_lattice import infer_lattice
from inhand_common.contact_centroids import RecentPositions, centroids, position_sums
from inhand_common.node_runner import run_node
from inhand_common.point_cloud import from_point_cloud2
from inhand_common.ros_matches import logged_subscription_matches
from inhand_common.ros_parameters import declare_parameters
from inhand_mapping.cloud_layouts import unpack_registered
from inhand_mapping.graph_mode import GraphModeQuery
from inhand_mapping.qos import DATA_QOS, LATCHED_QOS
from inhand_shape.shape_display import DisplayItem, part_items, surface_item
from inhand_shape.shape_extraction import SHAPE_PARAMETERS, extract_shape, support_normal

KEPT_POSITIONS = 3_000_000   # 36 MB: 70 min of three fingers at 240 Hz
MARKER_TYPES = {'triangles': Marker.TRIANGLE_LIST, 'lines': Marker.LINE_LIST, 'points': Marker.POINTS}


def _marker(item: DisplayItem, index: int, frame_id: str, stamp) -> Marker:
    marker = Marker()
    marker.header.frame_id = frame_id
    marker.header.stamp = stamp
    marker.ns = item.name
    marker.id = index
    marker.type = MARKER_TYPES[item.kind]
    marker.action = Marker.ADD
    marker.pose.orientation.w = 1.0
    width = 0.002 if item.kind != 'triangles' else 1.0
    marker.scale.x = marker.scale.y = marker.scale.z = width
    marker.color = ColorRGBA(r=item.rgba[0], g=item.rgba[1], b=item.rgba[2], a=item.rgba[3])
    marker.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in item.points]
    return marker


class ShapeNode(Node):
    def __init__(self):
        super().__init__('shape_node')
        self.parameters = declare_parameters(self, SHAPE_PARAMETERS)
        self._cells = None
        self._frame_id = 'object'
        self._mode: str | None = None
        self._graph_mode = GraphModeQuery(self, self._on_graph_mode)
        self.create_subscription(PointCloud2, 'occupancy/occupied', self._on_map, LATCHED_QOS)
        self._positions = RecentPositions(KEPT_POSITIONS)
        self.create_subscription(
            PointCloud2, 'registration/points', self._on_points, DATA_QOS,
            event_callbacks=logged_subscription_matches(self, 'registration/points'))
        self._parts = self.create_publisher(MarkerArray, 'shape/parts', LATCHED_QOS)
        self._surface = self.create_publisher(Marker, 'shape/surface', LATCHED_QOS)
        self.create_service(Trigger, 'shape/extract', self._on_extract)
        self.get_logger().info(
            f"ready: shape/extract on the latest occupancy/occupied (friction "
            f"{self.parameters['friction']:g}, at most {self.parameters['max_parts']} parts)")

    def _on_graph_mode(self, mode: str, node: str) -> None:
        self._mode = mode
        self.get_logger().info(f'the graph is in {mode} mode (from {node})')

    def _on_map(self, msg: PointCloud2) -> None:
        self._cells = from_point_cloud2(msg)
        self._frame_id = msg.header.frame_id or 'object'

    def _on_points(self, msg: PointCloud2) -> None:
        dropped = self._positions.dropped
        self._positions.add(unpack_registered(from_point_cloud2(msg))[0])
        if self._positions.dropped and not dropped:
            self.get_logger().warning(
                f'more than {KEPT_POSITIONS} registered positions: the oldest no longer place '
                'the surface in their cells')

    def _on_extract(self, _request, response):
        cells = self._cells
        if cells is None or len(cells) == 0:
            response.success = False
            response.message = 'no map yet: nothing on occupancy/occupied (is occupancy_node running?)'
            return response
        centres = np.stack([cells['x'], cells['y'], cells['z']], axis=1).astype(np.float64)
        lattice = infer_lattice(centres) if len(centres) > 1 else None
        if lattice is None:
            response.success, response.message = False, 'the map has one occupied cell: nothing to fit'
            return response
        started = time.monotonic()
        # each cell's newest positions, as many as the map's hits there: those from before
        # an occupancy/reset are not the map's
        sums, counts = position_sums(self._positions.points(), centres, lattice, cells['hits'])
        result = extract_shape(centres, cells['intensity'], cells['hits'], cells['first_touch'],
                               resolution=lattice.resolution, origin=lattice.origin,
                               threshold=self.parameters['occupied_threshold'],
                               friction=self.parameters['friction'],
                               max_parts=self.parameters['max_parts'], frame_id=self._frame_id,
                               # none placed (the node started after the touches): the
                               # cells with their slack, not their centres as points
                               surface_points=centroids(centres, sums, counts) if counts.any() else None,
                               up=support_normal(self._mode),
                               # (a cloud from before the field: the parts take every cell)
                               layer=cells['layer'] if 'layer' in cells.dtype.names else None)
        stamp = self.get_clock().now().to_msg()
        array = MarkerArray()
        clear = Marker()
        clear.header.frame_id = self._frame_id
        clear.action = Marker.DELETEALL
        array.markers = [clear] + [_marker(item, k, self._frame_id, stamp)
                                   for k, item in enumerate(part_items(result))]
        self._parts.publish(array)
        self._surface.publish(_marker(surface_item(result), 0, self._frame_id, stamp))
        response.success = result.decomposition.reason is None
        response.message = (f'{result.summary()}; {int(np.count_nonzero(counts))} of {len(centres)} '
                            'cells placed by the registered positions')
        self.get_logger().info(f'{response.message} ({time.monotonic() - started:.1f} s)')
        return response


def main(args=None) -> int:
    return run_node('shape_node', ShapeNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
