"""ROS 2 node ``stereo_node``: a stereo pair -> disparity, 3D points and the texture of the map.

Subscribes (best-effort, so camera drivers and reliable bag replays both match)
``stereo/left/image_raw``, ``stereo/right/image_raw`` (sensor_msgs/Image: mono8, rgb8, bgr8)
and ``stereo/left/camera_info``, ``stereo/right/camera_info``; unless in static mode, the
object sensor's ``polhemus/<object_name>/pose`` (reliable); and the latched
``occupancy/occupied``. The mode is the registration node's (asked over its
``get_parameters``), unless the ``mode`` parameter fixes one.
Left and right images pair by exact stamp, with the newest camera_info of each side.

Publishes, reliable and transient-local (a late subscriber gets the latest):
``stereo/disparity`` (stereo_msgs/DisparityImage, frame ``stereo_left_optical``),
``stereo/points`` (PointCloud2 ``x y z rgb`` in the map frame ``object``) and
``occupancy/textured`` (every occupied cell with ``x y z intensity rgb textured``), the
last re-coloured from the last pair on every map update, and ``vision/cloud``: the vision
local map (paper eqs. 5-7, vision_model.py) on the occupancy grid, every pair's object
pixels (scene_segmentation.py) integrated once, for the occupancy node's fusion; and
``stereo/object``: those object pixels' points with the camera's position (``x y z vp_x
vp_y vp_z``, cloud_layouts.py), for the exploration node's completed surface.

A pair that cannot be used (sizes that differ, an unsupported encoding, a camera_info
inconsistent with the image or with a zero focal length, a right P without a baseline) gets
one log line naming the problem; nothing is published from it and the node keeps running. A
pair that comes before its camera_infos waits for them (with one warning). The callbacks
only pair the images; one worker thread does a pair's work, the newest pair first, and a
pair replaced while it was busy is counted as skipped (pair_flow.py): ``diagnostics`` about
once a second give pairs received, processed, skipped and refused. The work is in
stereo_pipeline.py; this file only translates messages.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from stereo_msgs.msg import DisparityImage

from inhand_common.health import WARN, IntervalCounts, Problems
from inhand_common.node_runner import run_node
from inhand_common.packed_rgb import rgb_of_colours
from inhand_common.point_cloud import from_point_cloud2, serialize_point_cloud2
from inhand_common.ros_diagnostics import NodeDiagnostics
from inhand_common.ros_names import station_pose_topic
from inhand_common.ros_parameters import declare_parameters
from inhand_common.ros_time import stamp_from_seconds
from inhand_common.ros_transforms import Transform, TransformPublisher
from inhand_mapping.cloud_layouts import seen_cloud, textured_cells, vision_cells
from inhand_mapping.graph_mode import GraphModeQuery
from inhand_mapping.pose_cdr import decode_pose_stamped_many, stamp_seconds
from inhand_mapping.qos import LATCHED_QOS
from inhand_mapping.registration import Registrar
from inhand_stereo.pair_flow import NewestPair, flow_report
from inhand_stereo.scene_segmentation import warm_up as warm_up_segmentation
from inhand_stereo.shot_placement import PlacedShot, ShotPlacer, UnplacedShot, waiting_advice
from inhand_stereo.stereo_config import FOLLOW_REGISTRATION, STEREO_PARAMETERS, StereoConfig
from inhand_stereo.stereo_inputs import StereoInputs, StereoPair, shot_from_messages
from inhand_stereo.stereo_pipeline import StereoPipeline, StereoShot
from inhand_stereo.texture import warm_up as warm_up_texture
from inhand_stereo.vision_model import VisionMap, warm_up

IMAGE_QOS = qos_profile_sensor_data          # best-effort, depth 5
# A best-effort reader matches every camera driver and bag replay. A publisher without the
# graph's Fast DDS profile (dds_profile.py) sends a 640x480 rgb8 image (921,600 bytes) over
# UDP in fragments, and a best-effort reader loses about half of them (411 of 900 in
# benchmark.sh stereo-node). So each image topic is also read reliably: a reliable publisher
# (a bag replay, most drivers) delivers to both readers, and the copy that comes second is
# recognised by its stamp and dropped. The camera_infos likewise (a fast replay's burst
# loses them on a best-effort reader).
RELIABLE_IMAGE_QOS = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
POSE_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
POINT_FIELDS = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('rgb', '<f4')])
MAX_OBJECT_POINTS = 20_000   # stereo/object's points per pair at most (evenly thinned beyond)


class StereoNode(Node):
    def __init__(self) -> None:
        super().__init__('stereo_node')
        self.config = StereoConfig.from_parameters(declare_parameters(self, STEREO_PARAMETERS))
        config = self.config
        self.pipeline = StereoPipeline(config.disparity, point_step=config.point_step)
        self.inputs: StereoInputs[Image, CameraInfo] = StereoInputs()
        self.placer = ShotPlacer(None)        # until the graph's mode is known
        self.placed: PlacedShot | None = None
        self.vision = VisionMap(config.grid, config.vision, config.clamp)
        started = time.monotonic()
        warm_up(config.vision, config.grid.resolution)   # not on the first pair
        warm_up_segmentation(config.grid, config.segmentation)
        warm_up_texture()
        self.get_logger().info(f'kernels ready in {time.monotonic() - started:.2f} s')
        self.cells: np.ndarray | None = None         # the latest occupied cloud's points
        self.counts = {'processed': 0, 'refused': 0, 'no_object_pose': 0}
        self.images = 0
        # The worker's state (the placer, the vision map, the last shot, the map's cells)
        # is shared with the object pose and map callbacks: one lock.
        self._state = threading.Lock()
        self.pending: NewestPair[StereoPair[Image, CameraInfo]] = NewestPair()
        self._interval = IntervalCounts(time.monotonic())
        for side in ('left', 'right'):
            for qos in (IMAGE_QOS, RELIABLE_IMAGE_QOS):
                self.create_subscription(Image, f'stereo/{side}/image_raw',
                                         lambda msg, side=side: self._on_image(side, msg), qos)
                # camera_info too: a best-effort reader loses it in a fast replay's burst
                self.create_subscription(CameraInfo, f'stereo/{side}/camera_info',
                                         lambda msg, side=side: self._on_info(side, msg), qos)
        # The graph's mode is the registration node's (mode 'follow', the default): asked
        # from whichever node publishes registration/object_frame. Until it is known the
        # pairs wait, and after WAIT_WARNING s the node says why and what to do.
        self.object_topic = station_pose_topic(config.object_name)
        self._held_since: float | None = None    # monotonic: since when a pair waits
        self._own_mode = 'its mode parameter' if config.mode != FOLLOW_REGISTRATION else None
        if self._own_mode:
            self._use_mode(config.mode, self._own_mode)
        self._graph_mode = GraphModeQuery(self, self._on_graph_mode)
        if config.mode != 'static':
            # from the start: a fast replay sends every pose before the mode is known (the
            # placer keeps them until it is; in static mode it ignores them)
            self.create_subscription(PoseStamped, self.object_topic, self._on_object_pose,
                                     POSE_QOS, raw=True)
        self.create_subscription(PointCloud2, 'occupancy/occupied', self._on_map, LATCHED_QOS)
        self._disparity = self.create_publisher(DisparityImage, 'stereo/disparity', LATCHED_QOS)
        self._points = self.create_publisher(PointCloud2, 'stereo/points', LATCHED_QOS)
        self._textured = self.create_publisher(PointCloud2, 'occupancy/textured', LATCHED_QOS)
        self._vision = self.create_publisher(PointCloud2, 'vision/cloud', LATCHED_QOS)
        self._object = self.create_publisher(PointCloud2, 'stereo/object', LATCHED_QOS)
        # The camera on the tracker (camera_pose, from calibrate_camera_tracker), latched.
        self.frames = config.frames
        self.transforms = TransformPublisher(self)
        self.transforms.send_static([Transform(
            self.get_clock().now().to_msg(), self.frames.tracker_frame, self.frames.camera_frame,
            config.camera_pose[:3], config.camera_pose[3:])])
        self.diagnostics = NodeDiagnostics(self, 'stereo', self._report,
                                           data_count=lambda: self.images)
        self._worker = threading.Thread(target=self._work_loop, name='stereo_work', daemon=True)
        self._worker.start()
        matcher = self.pipeline.matcher.config
        self.get_logger().info(
            f"stereo: {'semi-global' if matcher.stereo_algorithm else 'block'} matching, "
            f'disparities {matcher.min_disparity}..{matcher.max_search} px; mode '
            f'{config.mode}; camera_pose {np.round(config.camera_pose, 4).tolist()}')

    # ------------------------------------------------------------------ the graph's mode
    def _on_graph_mode(self, mode: str, node: str) -> None:
        if self.placer.mode is None:
            self._use_mode(mode, f'from {node}')
        elif self.placer.mode != mode:
            self.get_logger().warning(
                f'this node places the pairs in {self.placer.mode} mode (its mode parameter) '
                f'but {node} registers in {mode} mode: the images and the touch map will not '
                f"line up; leave this node's mode unset (follow) so the graph has one mode")

    @property
    def mode_source(self) -> str:
        """Where the mode the pairs are placed in came from, or why it is not known yet."""
        return self._own_mode or self._graph_mode.source

    def _use_mode(self, mode: str, source: str) -> None:
        with self._state:
            self._decided(self.placer.use(Registrar(mode, self.config.max_gap)))
        self.get_logger().info(f'placing the stereo pairs in {mode} mode ({source})')

    def _waiting(self) -> tuple[str, str] | None:
        """Why pairs wait to be placed, once one has waited WAIT_WARNING s (diagnostics
        warn, and log it when it starts, when its cause changes and every 10 s)."""
        with self._state:
            since, mode, poses = self._held_since, self.placer.mode, self.placer.object_poses
        waited = 0.0 if since is None else time.monotonic() - since
        if waited < WAIT_WARNING:
            return None
        return waiting_advice(mode, waited, poses, self.object_topic, self.mode_source)

    # ------------------------------------------------------------------ inputs
    def _on_image(self, side: str, msg: Image) -> None:
        self.images += 1
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        held = self.inputs.held
        pair = self.inputs.add_image(side, stamp_ns, msg)
        if held is None and self.inputs.held is not None:
            # Held until the camera_info comes; a newer pair replaces it, and the node says so
            # once (a camera without calibration publishes none).
            missing = self.inputs.missing_infos()
            self.get_logger().warning(
                f'stereo pair at {stamp_ns * 1e-9:.3f} s waits: no camera_info for the '
                f'{" and ".join(missing)} camera yet (stereo/{missing[0]}/camera_info)')
        self._process(pair)

    def _on_info(self, side: str, msg: CameraInfo) -> None:
        self._process(self.inputs.add_info(side, msg))

    def _on_object_pose(self, raw: bytes) -> None:
        stamps, _, poses = decode_pose_stamped_many([raw])
        with self._state:
            self._decided(self.placer.add_object_pose(float(stamp_seconds(stamps)[0]),
                                                      poses[0, :3], poses[0, 3:]))

    def _on_map(self, msg: PointCloud2) -> None:
        cells = np.array(from_point_cloud2(msg))
        with self._state:
            self.cells = cells
            self._publish_texture()

    # ------------------------------------------------------------------ work
    def _process(self, pair: StereoPair[Image, CameraInfo] | None) -> None:
        if pair is not None:
            self.pending.offer(pair)        # the worker takes the newest (pair_flow.py)

    def _work_loop(self) -> None:
        while not self.pending.closed:
            pair = self.pending.take(timeout=0.2)
            if pair is not None:
                with self._state:
                    self._work(pair)

    def _work(self, pair: StereoPair[Image, CameraInfo]) -> None:
        try:
            shot = shot_from_messages(self.pipeline, pair)
        except ValueError as error:
            self.counts['refused'] += 1
            self.get_logger().error(f'stereo pair at {pair.stamp_ns * 1e-9:.3f} s not used: '
                                    f'{error}')
            return
        self.counts['processed'] += 1
        self._publish_disparity(shot, pair.left.header)
        self._decided(self.placer.add_shot(shot))

    def _decided(self, outcomes: list[PlacedShot | UnplacedShot]) -> None:
        """Publish the shots placed on the object; say why the others cannot be. (Called
        after every change of the placer: notes since when a pair waits.)"""
        if not self.placer.held:
            self._held_since = None
        elif self._held_since is None:
            self._held_since = time.monotonic()
        for outcome in outcomes:
            if isinstance(outcome, UnplacedShot):
                self.counts['no_object_pose'] += 1
                self.get_logger().error(
                    f'stereo pair at {outcome.shot.stamp_ns * 1e-9:.3f} s not used: '
                    f'{outcome.reason}; the images cannot be placed on the object')
                continue
            self.placed = outcome
            shot = outcome.shot
            points = outcome.points_in_map(self.config.camera_pose)
            cloud = np.empty(len(points), dtype=POINT_FIELDS)
            for axis, name in enumerate('xyz'):
                cloud[name] = points[:, axis]
            cloud['rgb'] = rgb_of_colours(shot.colours)
            stamp = stamp_from_seconds(shot.stamp_ns * 1e-9)
            self._points.publish(serialize_point_cloud2(cloud, self.frames.map_frame, stamp.sec,
                                                        stamp.nanosec))
            self._publish_texture()
            self._publish_vision(outcome, stamp)

    # ------------------------------------------------------------------ outputs
    def _publish_disparity(self, shot: StereoShot, header: Any) -> None:
        result, rectifier = shot.disparity, shot.rectifier
        msg = DisparityImage()
        msg.header.stamp = header.stamp
        msg.header.frame_id = self.frames.camera_frame
        height, width = result.disparity.shape
        msg.image.header = msg.header
        msg.image.height, msg.image.width = height, width
        msg.image.encoding = '32FC1'
        msg.image.step = 4 * width
        msg.image.data = result.disparity.astype('<f4').tobytes()
        msg.f, msg.t = float(rectifier.focal), float(rectifier.baseline)
        x, y, w, h = result.valid_window
        msg.valid_window.x_offset, msg.valid_window.y_offset = int(x), int(y)
        msg.valid_window.width, msg.valid_window.height = int(w), int(h)
        msg.min_disparity = float(result.min_disparity)
        msg.max_disparity = float(result.max_disparity)
        msg.delta_d = float(result.delta_d)
        self._disparity.publish(msg)

    def _publish_vision(self, placed: PlacedShot, stamp: Any) -> None:
        started = time.perf_counter()
        seen, segmentation = placed.object_points(self.config.camera_pose, self.vision.spec,
                                                  self.config.segmentation)
        updated = placed.integrate_segmented(self.vision, self.config.camera_pose, segmentation)
        cells = vision_cells(self.vision.spec, self.vision.log_odds)
        self._vision.publish(serialize_point_cloud2(cells, self.frames.map_frame, stamp.sec, stamp.nanosec))
        # the object's points for the exploration node: every few, at most MAX_OBJECT_POINTS
        step = max(1, -(-len(seen) // MAX_OBJECT_POINTS))
        self._object.publish(serialize_point_cloud2(
            seen_cloud(seen[::step], placed.camera_in_map(self.config.camera_pose)),
            self.frames.map_frame, stamp.sec, stamp.nanosec))
        self.get_logger().info(
            f'vision map: pair {self.vision.exposures} updated {updated} cells '
            f'from {int(segmentation.keep.sum())} object pixels (support plane '
            f"{'removed' if segmentation.support is not None else 'none'}) in "
            f'{(time.perf_counter() - started) * 1000:.0f} ms')

    def _publish_texture(self) -> None:
        if self.placed is None or self.cells is None:
            return
        started = time.perf_counter()
        cells = self.cells
        centres = np.stack([cells['x'], cells['y'], cells['z']], axis=1).astype(np.float64)
        # the cells the touch map's judge rescued (their surface layer under the threshold)
        rescued = cells['layer'] < self.config.occupied_threshold \
            if 'layer' in (cells.dtype.names or ()) else None
        texture = self.placed.texture(centres, self.config.resolution, self.config.camera_pose,
                                      rescued)
        cloud = textured_cells(cells, texture.colours, texture.textured)
        stamp = stamp_from_seconds(self.placed.shot.stamp_ns * 1e-9)
        self._textured.publish(serialize_point_cloud2(cloud, self.frames.map_frame, stamp.sec,
                                                      stamp.nanosec))
        self.get_logger().debug(
            f'textured {int(texture.textured.sum())} of {len(centres)} occupied cells in '
            f'{(time.perf_counter() - started) * 1000:.1f} ms')

    def _flow(self) -> dict[str, int]:
        """The running totals of what happened to the pairs (diagnostics, the last log)."""
        return {'pairs received': self.pending.received,
                'pairs processed': self.counts['processed'],
                'pairs skipped': self.pending.skipped, 'pairs refused': self.counts['refused'],
                'pairs without an object pose': self.counts['no_object_pose'],
                'images unpaired': self.inputs.pairs.dropped,
                'images duplicate': self.inputs.duplicates}

    def _report(self, now: float, problems: Problems) -> tuple[str, dict[str, object]]:
        counts = self._flow()
        elapsed, increases = self._interval.step(time.monotonic(), counts)
        waiting = self._waiting()
        if waiting is not None:
            problems.add(WARN, *waiting)
        return flow_report(counts, increases, elapsed, problems)

    def close(self) -> None:
        self.pending.close()
        self._worker.join(timeout=30.0)
        flow = self._flow()
        self.get_logger().info(
            f"stopped: {flow['pairs received']} image pairs, {flow['pairs processed']} "
            f"processed, {flow['pairs skipped']} skipped while busy, {flow['pairs refused']} "
            f"refused, {flow['pairs without an object pose']} without an object pose, "
            f"{flow['images unpaired']} images never paired")


WAIT_WARNING = 3.0         # s a pair may wait to be placed before the node says why


def main(args: list[str] | None = None) -> int:
    return run_node('stereo_node', StereoNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
