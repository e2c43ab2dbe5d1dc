"""ROS 2 node ``occupancy_node``: registered points -> probabilistic voxel map.

Subscribes ``registration/points`` (PointCloud2, layout in cloud_layouts.py). Publishes, at
``publish_rate`` when the map changed, reliable and transient-local (a late subscriber
gets the latest map):

* ``occupancy/cloud``: every touched cell; ``occupancy/occupied``: cells above
  ``occupied_threshold`` (PointCloud2, frame ``object``; fields x y z intensity hits
  first_touch);
* ``occupancy/center_of_mass`` (PointStamped, frame ``object``): origin of the
  ``object_centric`` frame.

``occupancy/updates`` (PointCloud2, reliable, volatile), ``update_rate`` times a second
when anything changed: the cells whose probability changed and the cells the fingertips
are in now, flagged provisional (map_updates.py), for live views.

Services (std_srvs/Trigger): ``occupancy/reset`` clears the map; ``occupancy/save``
writes ``<output_dir>/<map_name>.npz`` (whole grid) and ``.ply`` (occupied cells)
atomically and answers with the paths.

With ``fusion`` (product or entropy) the node also subscribes ``vision/cloud`` (the stereo
node's vision local map, latched): ``occupancy/cloud``, ``occupancy/occupied``, the centre
of mass and the saved files are then the global map fused from the touch map and the
latest vision map (fusion.py, global_map.py), ``occupancy/touch/cloud`` carries the touch
local map, and the NPZ keeps both local maps. ``occupancy/reset`` clears the touch map;
the vision map stays (it is the stereo node's, from a picture taken once).

Subscribes ``occupancy/textured`` too (the stereo node's colours of the occupied cells,
latched): a save colours the occupied cells with the latest of it (``red green blue
textured`` in the PLYs, ``rgb``/``textured`` in the NPZ); cells occupied since it came are
saved untextured.

Frames (ros_transforms.py): ``object_centric`` in ``object`` (origin at the centre of mass)
with each map publication, on ``transforms`` and, on a full ROS install, ``/tf``.
``diagnostics`` about once a second (node_health.py): state, rates, counters, cells, and
points falling outside the workspace, a warning in the log too. The map is published on
a steady-clock timer, so ``use_sim_time`` changes the stamps, not the mapping.

The map holds each finger's newest samples back until the samples after them show how
fast the finger was moving (touch_paths.py, dwell.py). A save, and the map published once
no points have come for two publish periods (the end of a replay, a pause), are made from
a copy with them applied (GlobalMap.settled): the live map goes on holding them, so saves
and pauses leave the map the stream gives unchanged (build_map's of the same poses).
"""

from __future__ import annotations

import time

import numpy as np
from geometry_msgs.msg import PointStamped
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from inhand_common.health import Problems
from inhand_common.node_runner import run_node
from inhand_common.packed_rgb import colours_of_rgb
from inhand_common.parameters import ParameterError
from inhand_common.point_cloud import from_point_cloud2, serialize_point_cloud2
from inhand_common.ros_clock import steady_timer
from inhand_common.ros_diagnostics import NodeDiagnostics
from inhand_common.ros_matches import logged_subscription_matches
from inhand_common.ros_parameters import declare_parameters
from inhand_common.ros_transforms import Transform, TransformPublisher
from inhand_mapping.cloud_layouts import unpack_registered, vision_log_odds
from inhand_mapping.global_map import GlobalMap
from inhand_mapping.graph_mode import GraphModeQuery
from inhand_mapping.map_io import GridColours
from inhand_mapping.map_products import MapProducts, resume_from, save_map
from inhand_mapping.map_updates import MapUpdates
from inhand_mapping.mapping_config import OCCUPANCY_PARAMETERS, OccupancyConfig
from inhand_mapping.node_health import OccupancyActivity, OccupancyHealth
from inhand_mapping.occupancy import warm_up
from inhand_mapping.qos import DATA_QOS, LATCHED_QOS, UPDATES_QOS

MAP_QOS = LATCHED_QOS
POINTS_QOS = DATA_QOS
# The map's clouds (8.2 MB for a full 70^3 grid) are handed to Fast DDS's own thread, so a
# publication with a subscriber costs the node 2 ms instead of 4 (dds_profile.py).
ASYNCHRONOUS_PUBLISHING = True


class OccupancyNode(Node):
    def __init__(self):
        super().__init__('occupancy_node')
        self.config = OccupancyConfig.from_parameters(
            declare_parameters(self, OCCUPANCY_PARAMETERS))
        self.grid = self.config.make_grid()
        config = self.config
        resumed = None
        if config.initial_map is not None:
            try:
                resumed = resume_from(self.grid, config.initial_map)
            except (OSError, ValueError) as error:
                raise ParameterError([f"parameter 'initial_map': {error}"]) from None
        self.map = GlobalMap.for_config(self.grid, config)
        self._products: dict[int, MapProducts] = {}   # by grid: touch, fused
        self._changed = False
        self._unsaved = False   # points integrated since the last save (autosave, shutdown)
        self._idle_ticks = 0   # publish periods since points last came
        self._settled_shown = False   # the map with what it holds back applied is shown
        self._latest_stamp = None
        self._colours: GridColours | None = None   # the latest occupancy/textured, by cell
        # the graph's mode (the registration node's), recorded in the saved maps: the tools
        # then know a static object stands on a support in the tracker frame
        self.registration_mode: str | None = None
        self._graph_mode = GraphModeQuery(self, self._on_graph_mode)
        self.frames = config.frames
        self.activity = OccupancyActivity()
        self._points_sub = self.create_subscription(
            PointCloud2, 'registration/points', self._on_points, POINTS_QOS,
            event_callbacks=logged_subscription_matches(self, 'registration/points'))
        self.create_subscription(PointCloud2, 'occupancy/textured', self._on_textured, MAP_QOS)
        self._touch_cloud = None
        if config.fusion != 'none':
            self.create_subscription(PointCloud2, 'vision/cloud', self._on_vision, MAP_QOS)
            self._touch_cloud = self.create_publisher(PointCloud2, 'occupancy/touch/cloud',
                                                      MAP_QOS)
        self._cloud = self.create_publisher(PointCloud2, 'occupancy/cloud', MAP_QOS)
        self._occupied = self.create_publisher(PointCloud2, 'occupancy/occupied', MAP_QOS)
        self._com = self.create_publisher(PointStamped, 'occupancy/center_of_mass', MAP_QOS)
        self.create_service(Trigger, 'occupancy/reset', self._on_reset)
        self.create_service(Trigger, 'occupancy/save', self._on_save)
        self.transforms = TransformPublisher(self)
        steady_timer(self, 1.0 / self.config.publish_rate, self._publish)
        if config.autosave_period > 0:
            steady_timer(self, config.autosave_period, self._autosave)
        if resumed is not None:   # not yet saved as this node's map
            self.map.touch_changed()
            self._changed = self._unsaved = True
            self.get_logger().info(f'resumed: {resumed}')
        self._updates = None
        if config.update_rate > 0:
            self._updates = MapUpdates(config.grid, config.model)
            self._updates_pub = self.create_publisher(PointCloud2, 'occupancy/updates',
                                                      UPDATES_QOS)
            steady_timer(self, 1.0 / config.update_rate, self._publish_updates)
        spec, model = self.grid.spec, self.grid.model
        self.health = OccupancyHealth(
            time.monotonic(), f'{spec.size:g} m cube centred at {list(spec.centre)}')
        self.diagnostics = NodeDiagnostics(self, 'occupancy map', self._report,
                                           data_count=lambda: self.activity.messages)
        started = time.monotonic()
        warm_up(model, spec.resolution)   # not on the first touch (occupancy.warm_up)
        self.get_logger().info(
            f'kernels ready in {time.monotonic() - started:.2f} s; '
            f'map: {spec.cells_per_axis}^3 cells of {spec.resolution * 1000:g} mm, '
            f'{spec.size:g} m cube centred at {list(spec.centre)} in {self.frames.map_frame}; '
            f'{model.touch_model} touch model, P(Z|not O) {model.p_z_given_not_occupied:g}, '
            f'visit gap {model.visit_gap:g} s; fusion {config.fusion}')

    def products(self, grid) -> MapProducts:
        """The clouds and object frame of ``grid`` (buffers made once per grid)."""
        if id(grid) not in self._products:
            self._products[id(grid)] = MapProducts(grid, self.config.occupied_threshold)
        return self._products[id(grid)]

    def _products_of_copy(self, grid) -> MapProducts:
        """The products of a settled copy, made for it alone (products() keeps its buffers
        for the grids that last)."""
        return MapProducts(grid, self.config.occupied_threshold)

    def _on_points(self, msg: PointCloud2) -> None:
        points, times, fingers = unpack_registered(from_point_cloud2(msg))
        self.activity.received += len(points)
        self.activity.messages += 1
        self._idle_ticks = 0
        self._settled_shown = False
        if len(points):
            self.grid.integrate(points, times, fingers)
            self.map.touch_changed()
            self._changed = True
            self._unsaved = True
        if len(times):
            self._latest_stamp = msg.header.stamp

    def _on_textured(self, msg: PointCloud2) -> None:
        cloud = from_point_cloud2(msg)
        centres = np.stack([cloud['x'], cloud['y'], cloud['z']], axis=1).astype(np.float64)
        inside = self.grid.spec.contains(centres)
        if not inside.all():
            self.get_logger().warning(
                f'occupancy/textured: {int((~inside).sum())} of {len(centres)} cells outside '
                'this map (another grid?); they are not saved')
        self.activity.textured = True
        self._colours = GridColours.from_cells(
            self.grid.spec, centres[inside], colours_of_rgb(cloud['rgb'][inside]),
            cloud['textured'][inside].astype(bool))

    def _on_vision(self, msg: PointCloud2) -> None:
        log_odds, outside = vision_log_odds(from_point_cloud2(msg), self.grid.spec)
        if outside:
            self.get_logger().warning(
                f'vision/cloud: {outside} of {msg.width} cells outside this map (another '
                'grid? the stereo node must share workspace_size, workspace_centre and '
                'resolution); they are not fused')
        first = self.map.vision is None
        self.map.set_vision(log_odds)
        self.activity.vision_cells = int(msg.width)
        self._changed = True
        if first:
            self.get_logger().info(f'vision map: {msg.width} cells; publishing the '
                                   f'{self.config.fusion} fusion of touch and vision')

    def _publish(self) -> None:
        self._idle_ticks += 1
        # Points stopped for two periods (a pause, the end of a replay): show the map with
        # what it holds back applied, on a copy.
        settle = self._idle_ticks >= 2 and self.grid.pending > 0
        if not (self._changed or (settle and not self._settled_shown)):
            return
        self._changed = False
        shown, products_of = self.map, self.products
        if settle:
            self._settled_shown = True
            shown = self.map.settled()
            products_of = self._products_of_copy
        stamp = self._latest_stamp or self.get_clock().now().to_msg()
        grid = shown.grid()
        products = products_of(grid)
        map_frame = self.frames.map_frame
        if self._touch_cloud is not None:
            touch, _ = products_of(shown.touch).cells()
            self._touch_cloud.publish(serialize_point_cloud2(touch, map_frame, stamp.sec,
                                                             stamp.nanosec))
        touched, occupied = products.cells()
        # Serialized here and published as bytes: a full map is 8 MB (see point_cloud.py).
        self._cloud.publish(serialize_point_cloud2(touched, map_frame, stamp.sec, stamp.nanosec))
        self._occupied.publish(serialize_point_cloud2(occupied, map_frame, stamp.sec,
                                                      stamp.nanosec))
        self.activity.publications += 1
        self.activity.touched_cells, self.activity.occupied_cells = len(touched), len(occupied)
        self.activity.occupied_on_faces = products.occupied_on_faces(occupied)
        frame = products.object_frame()
        if frame is not None:
            msg = PointStamped()
            msg.header.frame_id = map_frame
            msg.header.stamp = stamp
            msg.point.x, msg.point.y, msg.point.z = (float(v) for v in frame.centre_of_mass)
            self._com.publish(msg)
            self.transforms.send([Transform(stamp, map_frame, self.frames.object_centric_frame,
                                            frame.centre_of_mass, (0.0, 0.0, 0.0, 1.0))])

    def _publish_updates(self) -> None:
        if self._updates_pub.get_subscription_count() == 0:
            return   # nobody watches: the comparison over the grid is not worth it
        grid = self.map.grid()
        cells = self._updates.changes(grid.log_odds, grid.hits, self.grid.held_points())
        if len(cells):
            stamp = self._latest_stamp or self.get_clock().now().to_msg()
            self._updates_pub.publish(serialize_point_cloud2(cells, self.frames.map_frame,
                                                             stamp.sec, stamp.nanosec))

    def _on_reset(self, _request, response):
        self.grid.reset()
        self.map.touch_changed()
        self._colours = None
        self._changed = True
        response.success = True
        response.message = 'map cleared'
        self.get_logger().info('map cleared')
        return response

    def _on_save(self, _request, response):
        response.success, response.message = self.save()
        return response

    def _autosave(self) -> None:
        if self._unsaved:
            ok, message = self.save()
            if ok:
                self.get_logger().info(f'autosaved {message}')

    def _on_graph_mode(self, mode: str, node: str) -> None:
        self.registration_mode = mode

    def save(self) -> tuple[bool, str]:
        """Write the map set (map_products.save_map); (success, paths or the reason)."""
        saved = self.map.settled()   # the live map goes on holding back (see the top)
        grid = saved.grid()
        colours = textured = None
        if self._colours is not None:
            centres = grid.cells(threshold=self.config.occupied_threshold)[0]
            colours, textured = self._colours.at(grid.spec, centres)
        try:
            paths = save_map(grid, self.config.output_dir, self.config.map_name,
                             self.config.occupied_threshold, self.frames.map_frame,
                             extra={'node': self.get_fully_qualified_name(),
                                    'fusion': self.config.fusion if self.map.fusing
                                    else 'none',
                                    **({'registration_mode': self.registration_mode}
                                       if self.registration_mode else {})},
                             colours=colours, textured=textured,
                             local_maps=saved.local_maps())
        except OSError as error:
            message = f'could not save the map: {error}'
            self.get_logger().error(message)
            return False, message
        self._unsaved = False
        message = ' '.join(str(p) for p in paths)
        self.get_logger().info(f'saved {message}')
        return True, message

    def _report(self, now: float, problems: Problems) -> tuple[str, dict[str, object]]:
        self.activity.pending = self.grid.pending
        self.activity.publishers = self._points_sub.get_publisher_count()
        return self.health.report(now, self.grid.counts, self.activity, problems)

    def close(self) -> None:
        """At Ctrl-C or SIGTERM: what was mapped since the last save is saved."""
        if self._unsaved:
            ok, message = self.save()
            self.get_logger().info(f'saved at shutdown: {message}' if ok else
                                   f'could not save at shutdown: {message}')
        counts = self.grid.counts
        self.get_logger().info(
            f'stopped: received {self.activity.received} points in {self.activity.messages} '
            'messages; '
            f'{counts.integrated} points integrated, {counts.outside} outside the workspace, '
            f'{counts.invalid} invalid, {self.grid.pending} held back for their speeds (a '
            'save applies them)')


def main(args=None) -> int:
    return run_node('occupancy_node', OccupancyNode, args, executor_factory=EventsExecutor,
                    asynchronous_publishing=ASYNCHRONOUS_PUBLISHING)


if __name__ == '__main__':
    raise SystemExit(main())
