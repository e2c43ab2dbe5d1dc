"""From image and camera_info messages to stereo shots: the stereo node's input side.

The node (rclpy messages) and the bag tools (rosbags messages) hand the same fields to
:class:`StereoInputs`, so a pair is paired, checked and refused the same way live and
offline:

* images pair by exact stamp (:class:`~inhand_stereo.stereo_pairing.PairBuffer`); the same
  image arriving twice (the node reads each topic best-effort and reliable) is taken once;
* a pair is released with the newest camera_info of each side; a pair that comes before
  its camera_infos is held (the newest one only) until they come;
* :func:`shot_from_messages` checks what the pipeline cannot see (encodings and sizes that
  differ) and runs the pipeline; every refusal is a ValueError naming the problem.

No rclpy here: messages are duck-typed (:class:`ImageMessage`, :class:`CameraInfoMessage`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from typing import Any, Generic, NamedTuple, Protocol, TypeVar

from inhand_stereo.camera_model import CameraModel
from inhand_stereo.image_encoding import image_to_array
from inhand_stereo.stereo_pairing import SIDES, PairBuffer
from inhand_stereo.stereo_pipeline import StereoPipeline, StereoShot

__all__ = ['CameraInfoMessage', 'ImageMessage', 'StereoInputs', 'StereoPair',
           'camera_model_of', 'shot_from_messages']


class ImageMessage(Protocol):
    """The fields of sensor_msgs/Image the pipeline reads."""

    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: Any        # bytes, array('B') (rclpy) or a uint8 array (rosbags)


class CameraInfoMessage(Protocol):
    """The fields of sensor_msgs/CameraInfo the pipeline reads."""

    height: int
    width: int
    distortion_model: str
    d: Sequence[float]
    k: Sequence[float]
    r: Sequence[float]
    p: Sequence[float]


Image = TypeVar('Image', bound=ImageMessage)
Info = TypeVar('Info', bound=CameraInfoMessage)


class StereoPair(NamedTuple, Generic[Image, Info]):
    """One exposure with the calibration it is processed with."""

    stamp_ns: int
    left: Image
    right: Image
    left_info: Info
    right_info: Info


def camera_model_of(msg: CameraInfoMessage, side: str) -> CameraModel:
    """The checked camera model of a CameraInfo message (``side`` names it in refusals)."""
    return CameraModel.from_fields(msg.width, msg.height, msg.k, msg.d, msg.r, msg.p,
                                   msg.distortion_model, name=side)


def shot_from_messages(pipeline: StereoPipeline, pair: StereoPair[Any, Any]) -> StereoShot:
    """The pipeline's shot of one pair; ValueError naming the problem when the pair or its
    calibration cannot be used (encodings or sizes that differ, an unsupported encoding, a
    camera_info inconsistent with the image, a zero focal length, no baseline)."""
    left, right = pair.left, pair.right
    if left.encoding != right.encoding:
        raise ValueError(f'left image is {left.encoding} but right image is {right.encoding}')
    if (left.width, left.height) != (right.width, right.height):
        raise ValueError(f'left image is {left.width}x{left.height} but right image is '
                         f'{right.width}x{right.height}')
    images = [image_to_array(m.encoding, m.height, m.width, m.step, bytes(m.data),
                             bool(m.is_bigendian)) for m in (left, right)]
    return pipeline.process(pair.stamp_ns, images[0], images[1], left.encoding,
                            camera_model_of(pair.left_info, 'left'),
                            camera_model_of(pair.right_info, 'right'))


class StereoInputs(Generic[Image, Info]):
    """Images and camera_infos in (any order), complete pairs out."""

    def __init__(self, depth: int = 4):
        self.pairs: PairBuffer[Image] = PairBuffer(depth)
        self.infos: dict[str, Info] = {}
        self.held: tuple[int, Image, Image] | None = None   # a pair waiting for camera_info
        self.duplicates = 0
        self._seen: dict[str, deque[int]] = {side: deque(maxlen=16) for side in SIDES}

    def missing_infos(self) -> list[str]:
        """The sides without a camera_info yet."""
        return [side for side in SIDES if side not in self.infos]

    def add_image(self, side: str, stamp_ns: int, image: Image) -> StereoPair[Image, Info] | None:
        """Offer one image; the pair it completes, if its camera_infos are there (else it is
        held: :attr:`held`)."""
        if stamp_ns in self._seen[side]:
            self.duplicates += 1     # the same image through the other reader
            return None
        self._seen[side].append(stamp_ns)
        pair = self.pairs.add(side, stamp_ns, image)
        return None if pair is None else self._release(*pair)

    def add_info(self, side: str, info: Info) -> StereoPair[Image, Info] | None:
        """Offer one camera_info; the held pair, if this completes its calibration."""
        if side not in SIDES:
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        self.infos[side] = info
        return None if self.held is None else self._release(*self.held)

    def _release(self, stamp_ns: int, left: Image, right: Image
                 ) -> StereoPair[Image, Info] | None:
        if self.missing_infos():
            self.held = (stamp_ns, left, right)
            return None
        self.held = None
        return StereoPair(stamp_ns, left, right, self.infos['left'], self.infos['right'])
