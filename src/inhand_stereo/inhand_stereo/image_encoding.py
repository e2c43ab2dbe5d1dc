"""sensor_msgs/Image payloads <-> numpy arrays, for the encodings a stereo camera sends.

No rclpy here: the node passes the message's fields. Supported: ``mono8``, ``rgb8``, ``bgr8``
(and ``mono16`` scaled to 8 bits); anything else is refused with the encoding's name, so a
camera driver set to Bayer or YUV output gets one clear line instead of a garbled map. Rows
may be padded (``step`` > width x bytes per pixel), as some drivers do.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ['SUPPORTED_ENCODINGS', 'ImageError', 'image_to_array', 'to_grey', 'to_rgb']

# encoding: (channels, bytes per channel)
SUPPORTED_ENCODINGS = {'mono8': (1, 1), 'rgb8': (3, 1), 'bgr8': (3, 1), 'mono16': (1, 2)}


class ImageError(ValueError):
    """An image that cannot be used, with the reason for the user."""


def image_to_array(encoding: str, height: int, width: int, step: int, data: bytes | bytearray
                   | memoryview, is_bigendian: bool = False) -> NDArray[np.uint8]:
    """The image as uint8 (H, W) for mono or (H, W, 3) in its own channel order; a view of
    ``data`` where the layout allows (no copy)."""
    if encoding not in SUPPORTED_ENCODINGS:
        raise ImageError(f"unsupported image encoding '{encoding}' (supported: "
                         f"{', '.join(SUPPORTED_ENCODINGS)})")
    channels, depth = SUPPORTED_ENCODINGS[encoding]
    row = width * channels * depth
    if height <= 0 or width <= 0:
        raise ImageError(f'image size {width}x{height} is empty')
    if step < row:
        raise ImageError(f'image step {step} is shorter than a row of {width} {encoding} '
                         f'pixels ({row} bytes)')
    buffer = np.frombuffer(data, dtype=np.uint8)
    if len(buffer) < step * height:
        raise ImageError(f'image data holds {len(buffer)} bytes, {step * height} expected '
                         f'({height} rows of {step})')
    rows = buffer[:step * height].reshape(height, step)[:, :row]
    if depth == 2:
        order = '>u2' if is_bigendian else '<u2'
        wide = rows.copy().view(order).reshape(height, width)
        return (wide >> 8).astype(np.uint8)
    return rows.reshape(height, width, channels) if channels > 1 else rows


def to_grey(image: NDArray[np.uint8], encoding: str) -> NDArray[np.uint8]:
    """Luma (H, W) uint8 of an image from :func:`image_to_array`."""
    if image.ndim == 2:
        return image
    import cv2
    code = cv2.COLOR_BGR2GRAY if encoding == 'bgr8' else cv2.COLOR_RGB2GRAY
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(image), code), dtype=np.uint8)


def to_rgb(image: NDArray[np.uint8], encoding: str) -> NDArray[np.uint8]:
    """(H, W, 3) uint8 RGB of an image from :func:`image_to_array` (grey replicated)."""
    if image.ndim == 2:
        import cv2
        # cvtColor replicates the grey values as np.repeat would, some 20 times faster.
        return np.asarray(cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_GRAY2RGB),
                          dtype=np.uint8)
    return image[:, :, ::-1] if encoding == 'bgr8' else image
