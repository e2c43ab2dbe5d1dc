"""ROS 2 node ``stereo_node``: a stereo pair -> disparity, 3D points and the texture of the map.

Subscribes (best-effort, so camera drivers and reliable bag replays both match)
``stereo/left/image_raw``, ``stereo/right/image_raw`` (sensor_msgs/Image: mono8, rgb8, bgr8)
and ``stereo/left/camera_info``, ``stereo/right/camera_info``; in tracked mode the object
sensor's ``polhemus/<object_name>/pose`` (reliable); and the latched ``occupancy/occupied``.
Left and right images pair by exact stamp, with the newest camera_info of each side.

Publishes, reliable and transient-local (a late subscriber gets the latest):
``stereo/disparity`` (stereo_msgs/DisparityImage, frame ``stereo_left_optical``),
``stereo/points`` (PointCloud2 ``x y z rgb`` in the map frame ``object``) and
``occupancy/textured`` (every occupied cell with ``x y z intensity rgb textured``), the
last re-coloured from the last pair on every map update.

A pair that cannot be used (sizes that differ, an unsupported encoding, a camera_info
inconsistent with the image or with a zero focal length, a right P without a baseline) gets
one log line naming the problem; nothing is published from it and the node keeps running. A
pair that comes before its camera_infos waits for them (with one warning). The work is in
stereo_pipeline.py; this file only translates messages.
"""

from __future__ import annotations

import time
from collections import deque
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from stereo_msgs.msg import DisparityImage

from inhand_common.node_runner import run_node
from inhand_common.packed_rgb import rgb_of_colours
from inhand_common.parameters import ParameterError, ParamSpec
from inhand_common.point_cloud import from_point_cloud2, serialize_point_cloud2
from inhand_common.ros_names import MAP_FRAME, STEREO_FRAME, station_pose_topic
from inhand_common.ros_parameters import declare_parameters
from inhand_common.ros_time import stamp_from_seconds
from inhand_mapping.cloud_layouts import textured_cells
from inhand_mapping.mapping_config import OCCUPANCY_PARAMETERS, REGISTRATION_PARAMETERS
from inhand_mapping.pose_cdr import decode_pose_stamped_many, stamp_seconds
from inhand_mapping.qos import LATCHED_QOS
from inhand_mapping.registration import Registrar
from inhand_stereo.camera_model import CameraModel
from inhand_stereo.disparity import DISPARITY_PARAMETERS, DisparityConfig
from inhand_stereo.image_encoding import image_to_array
from inhand_stereo.stereo_pairing import PairBuffer
from inhand_stereo.stereo_pipeline import StereoPipeline, StereoShot, pose_vector

IMAGE_QOS = qos_profile_sensor_data          # best-effort, depth 5
# A best-effort reader matches every camera driver and bag replay, but Fast DDS never hands it
# a message that needs many UDP fragments (a 640x480 rgb8 image is 921,600 bytes; measured
# here: 0 of 3 arrive, while 400 kB ones do). So each image topic is also read reliably: a
# reliable publisher (a bag replay, most drivers) delivers to both readers, and the copy that
# comes second is recognised by its stamp and dropped. The camera_infos likewise (a fast
# replay's burst loses them on a best-effort reader).
RELIABLE_IMAGE_QOS = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
POSE_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
POINT_FIELDS = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('rgb', '<f4')])


def _shared(table: tuple[ParamSpec, ...], *names: str) -> list[ParamSpec]:
    """The specs of the other nodes' parameters this node shares (same meaning, same
    checks: one YAML value can serve both)."""
    by_name = {spec.name: spec for spec in table}
    return [by_name[name] for name in names]


STEREO_PARAMETERS = (
    *DISPARITY_PARAMETERS,
    ParamSpec('camera_pose', [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], 'Pose of '
              'stereo_left_optical in polhemus_source: [x, y, z, qx, qy, qz, qw] (m; a point p '
              'in the camera frame is R p + t in the tracker frame); calibrate_camera_tracker '
              'writes it', minimum=-10.0, maximum=10.0, length=7),
    ParamSpec('point_step', 2, 'stereo/points takes every point_step-th pixel in each '
              'direction (1: all)', minimum=1, maximum=16),
    *_shared(REGISTRATION_PARAMETERS, 'mode', 'object_name', 'max_gap'),
    *_shared(OCCUPANCY_PARAMETERS, 'resolution'),
)


def camera_pose_from(values: list[float]) -> np.ndarray:
    """The camera_pose parameter, its quaternion normalised; ParameterError if it is none."""
    pose = np.asarray(values, dtype=np.float64)
    norm = float(np.linalg.norm(pose[3:]))
    if not norm > 1e-6:
        raise ParameterError([f"parameter 'camera_pose' = {list(values)}: the quaternion "
                              '(last four values) must not be zero'])
    pose[3:] /= norm
    return pose


def camera_model_of(msg: CameraInfo, side: str) -> CameraModel:
    """The checked camera model of a CameraInfo message (``side`` names it in refusals)."""
    return CameraModel.from_fields(msg.width, msg.height, msg.k, msg.d, msg.r, msg.p,
                                   msg.distortion_model, name=side)


class StereoNode(Node):
    def __init__(self) -> None:
        super().__init__('stereo_node')
        values = declare_parameters(self, STEREO_PARAMETERS)
        self.camera_pose = camera_pose_from(values['camera_pose'])
        self.resolution = float(values['resolution'])
        disparity = {spec.name: values[spec.name] for spec in DISPARITY_PARAMETERS}
        self.pipeline = StereoPipeline(DisparityConfig.from_parameters(disparity),
                                       point_step=values['point_step'])
        self.registrar = Registrar(values['mode'], values['max_gap'])
        self.pairs: PairBuffer[Image] = PairBuffer()
        self.infos: dict[str, CameraInfo] = {}
        self.shot: StereoShot | None = None
        self.shot_pose: np.ndarray | None = None     # map frame in the tracker at the shot
        self.cells: np.ndarray | None = None         # the latest occupied cloud's points
        self.counts = {'pairs': 0, 'refused': 0, 'no_object_pose': 0}
        self._seen: dict[str, deque[int]] = {side: deque(maxlen=16) for side in ('left', 'right')}
        for side in ('left', 'right'):
            for qos in (IMAGE_QOS, RELIABLE_IMAGE_QOS):
                self.create_subscription(Image, f'stereo/{side}/image_raw',
                                         lambda msg, side=side: self._on_image(side, msg), qos)
                # camera_info too: a best-effort reader loses it in a fast replay's burst
                self.create_subscription(CameraInfo, f'stereo/{side}/camera_info',
                                         lambda msg, side=side: self._on_info(side, msg), qos)
        if values['mode'] == 'tracked':
            self.create_subscription(PoseStamped, station_pose_topic(values['object_name']),
                                     self._on_object_pose, POSE_QOS, raw=True)
        self.create_subscription(PointCloud2, 'occupancy/occupied', self._on_map, LATCHED_QOS)
        self._disparity = self.create_publisher(DisparityImage, 'stereo/disparity', LATCHED_QOS)
        self._points = self.create_publisher(PointCloud2, 'stereo/points', LATCHED_QOS)
        self._textured = self.create_publisher(PointCloud2, 'occupancy/textured', LATCHED_QOS)
        self._pending: StereoShot | None = None     # waits for the object pose at its stamp
        self._unexplained: tuple[int, Image, Image] | None = None   # waits for camera_info
        config = self.pipeline.matcher.config
        self.get_logger().info(
            f"stereo: {'semi-global' if config.stereo_algorithm else 'block'} matching, "
            f'disparities {config.min_disparity}..{config.max_search} px; {values["mode"]} '
            f'mode; camera_pose {np.round(self.camera_pose, 4).tolist()}')

    # ------------------------------------------------------------------ inputs
    def _on_image(self, side: str, msg: Image) -> None:
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if stamp_ns in self._seen[side]:
            return   # the same image through the other reader
        self._seen[side].append(stamp_ns)
        pair = self.pairs.add(side, stamp_ns, msg)
        if pair is not None:
            self._process(*pair)

    def _on_info(self, side: str, msg: CameraInfo) -> None:
        self.infos[side] = msg
        if self._unexplained is not None and len(self.infos) == 2:
            # a pair came before its camera_infos (they travel on their own topics)
            self._process(*self._unexplained)

    def _on_object_pose(self, raw: bytes) -> None:
        stamps, _, poses = decode_pose_stamped_many([raw])
        self.registrar.add_object_pose(float(stamp_seconds(stamps)[0]), poses[0, :3],
                                       poses[0, 3:])
        if self._pending is not None:
            self._place(self._pending)

    def _on_map(self, msg: PointCloud2) -> None:
        self.cells = np.array(from_point_cloud2(msg))
        self._publish_texture()

    # ------------------------------------------------------------------ work
    def _process(self, stamp_ns: int, left: Image, right: Image) -> None:
        missing = [side for side in ('left', 'right') if side not in self.infos]
        if missing:
            # Held until the camera_info comes; a newer pair replaces it, and the node says so
            # once (a camera without calibration publishes none).
            if self._unexplained is None:
                self.get_logger().warning(
                    f'stereo pair at {stamp_ns * 1e-9:.3f} s waits: no camera_info for the '
                    f'{" and ".join(missing)} camera yet (stereo/{missing[0]}/camera_info)')
            self._unexplained = (stamp_ns, left, right)
            return
        self._unexplained = None
        self.counts['pairs'] += 1
        try:
            if left.encoding != right.encoding:
                raise ValueError(f'left image is {left.encoding} but right image is '
                                 f'{right.encoding}')
            if (left.width, left.height) != (right.width, right.height):
                raise ValueError(f'left image is {left.width}x{left.height} but right image '
                                 f'is {right.width}x{right.height}')
            images = [image_to_array(m.encoding, m.height, m.width, m.step, m.data,
                                     bool(m.is_bigendian)) for m in (left, right)]
            shot = self.pipeline.process(stamp_ns, images[0], images[1], left.encoding,
                                         camera_model_of(self.infos['left'], 'left'),
                                         camera_model_of(self.infos['right'], 'right'))
        except ValueError as error:
            self.counts['refused'] += 1
            self.get_logger().error(f'stereo pair at {stamp_ns * 1e-9:.3f} s not used: {error}')
            return
        self._publish_disparity(shot, left.header)
        self._place(shot)

    def _place(self, shot: StereoShot) -> None:
        """Bring the shot into the map frame once the object pose at its stamp is known."""
        where = self.registrar.object_pose_at(shot.stamp_ns * 1e-9)
        if where.state == 'later':
            self._pending = shot
            return
        self._pending = None
        if where.rotation is None or where.position is None:
            self.counts['no_object_pose'] += 1
            self.get_logger().error(
                f'stereo pair at {shot.stamp_ns * 1e-9:.3f} s not used: no object pose at its '
                f'stamp ({where.state.replace("_", " ")}); the images cannot be placed on '
                'the object')
            return
        self.shot, self.shot_pose = shot, pose_vector(where.rotation, where.position)
        points = shot.points_in_map(self.camera_pose, self.shot_pose)
        cloud = np.empty(len(points), dtype=POINT_FIELDS)
        for axis, name in enumerate('xyz'):
            cloud[name] = points[:, axis]
        cloud['rgb'] = rgb_of_colours(shot.colours)
        stamp = stamp_from_seconds(shot.stamp_ns * 1e-9)
        self._points.publish(serialize_point_cloud2(cloud, MAP_FRAME, stamp.sec,
                                                    stamp.nanosec))
        self._publish_texture()

    # ------------------------------------------------------------------ outputs
    def _publish_disparity(self, shot: StereoShot, header: Any) -> None:
        result, rectifier = shot.disparity, shot.rectifier
        msg = DisparityImage()
        msg.header.stamp = header.stamp
        msg.header.frame_id = STEREO_FRAME
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

    def _publish_texture(self) -> None:
        if self.shot is None or self.cells is None:
            return
        started = time.perf_counter()
        cells = self.cells
        centres = np.stack([cells['x'], cells['y'], cells['z']], axis=1).astype(np.float64)
        texture = self.shot.texture(centres, self.resolution, self.camera_pose, self.shot_pose)
        cloud = textured_cells(cells, texture.colours, texture.textured)
        stamp = stamp_from_seconds(self.shot.stamp_ns * 1e-9)
        self._textured.publish(serialize_point_cloud2(cloud, MAP_FRAME, stamp.sec,
                                                      stamp.nanosec))
        self.get_logger().debug(
            f'textured {int(texture.textured.sum())} of {len(centres)} occupied cells in '
            f'{(time.perf_counter() - started) * 1000:.1f} ms')

    def close(self) -> None:
        dropped = self.pairs.dropped
        self.get_logger().info(
            f"stopped: {self.counts['pairs']} image pairs, {self.counts['refused']} refused, "
            f"{self.counts['no_object_pose']} without an object pose, {dropped} images never "
            'paired')


def main(args: list[str] | None = None) -> int:
    return run_node('stereo_node', StereoNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
