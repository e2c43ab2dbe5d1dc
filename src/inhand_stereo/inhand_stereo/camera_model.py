"""One calibrated camera as ROS describes it (sensor_msgs/CameraInfo), checked, in numpy.

The fields and their meaning are CameraInfo's (plumb_bob distortion): ``K`` the intrinsics of
the raw image, ``D`` the distortion coefficients (k1, k2, t1, t2, k3), ``R`` the rectifying
rotation (raw camera frame -> rectified frame), ``P`` the projection of the rectified image
(for the right camera of a stereo pair ``P[0, 3] = -fx' * baseline``). No rclpy here: the
node converts its messages with :meth:`CameraModel.from_fields`, the calibration tools read
and write the camera_calibration_parsers YAML (``camera_info_yaml.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ['CameraModel', 'CameraModelError']


class CameraModelError(ValueError):
    """A camera description that cannot be used, with the reason for the user."""


@dataclass(frozen=True, eq=False)
class CameraModel:
    """A checked CameraInfo: sizes in pixels, matrices as float64 numpy arrays."""

    width: int
    height: int
    K: NDArray[np.float64]          # (3, 3)
    D: NDArray[np.float64]          # (n,) plumb_bob: k1, k2, t1, t2, k3 (n = 0 or 5, or more)
    R: NDArray[np.float64]          # (3, 3)
    P: NDArray[np.float64]          # (3, 4)
    distortion_model: str = 'plumb_bob'
    name: str = ''

    @classmethod
    def from_fields(cls, width: int, height: int, k: Sequence[float], d: Sequence[float],
                    r: Sequence[float], p: Sequence[float], distortion_model: str = 'plumb_bob',
                    name: str = '') -> CameraModel:
        """From CameraInfo's flat fields (row-major k[9], d[n], r[9], p[12]); checked."""
        try:
            K = np.asarray(k, dtype=np.float64).reshape(3, 3)
            R = np.asarray(r, dtype=np.float64).reshape(3, 3)
            P = np.asarray(p, dtype=np.float64).reshape(3, 4)
            D = np.asarray(d, dtype=np.float64).reshape(-1)
        except ValueError as error:
            raise CameraModelError(f'camera_info{_named(name)}: K must have 9 values, R 9, '
                                   f'P 12 ({error})') from None
        model = cls(int(width), int(height), K, D, R, P, distortion_model or 'plumb_bob', name)
        model.check()
        return model

    def check(self) -> None:
        """CameraModelError naming the first problem: no size, a zero or non-finite focal
        length, a distortion model other than plumb_bob (with coefficients), non-finite
        values."""
        where = f'camera_info{_named(self.name)}'
        if self.width <= 0 or self.height <= 0:
            raise CameraModelError(f'{where}: image size {self.width}x{self.height} is empty')
        for label, matrix in (('K', self.K), ('D', self.D), ('R', self.R), ('P', self.P)):
            if not np.all(np.isfinite(matrix)):
                raise CameraModelError(f'{where}: {label} holds a non-finite value')
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise CameraModelError(f'{where}: K has a zero or negative focal length '
                                   f'(fx {self.K[0, 0]:g}, fy {self.K[1, 1]:g}): not calibrated')
        if self.P[0, 0] <= 0 or self.P[1, 1] <= 0:
            raise CameraModelError(f'{where}: P has a zero or negative focal length '
                                   f'(fx {self.P[0, 0]:g}, fy {self.P[1, 1]:g}): not calibrated')
        if len(self.D) and self.distortion_model not in ('plumb_bob', 'rational_polynomial'):
            raise CameraModelError(f"{where}: distortion model '{self.distortion_model}' is "
                                   "not supported (plumb_bob or rational_polynomial)")

    @property
    def size(self) -> tuple[int, int]:
        """(width, height), as OpenCV wants it."""
        return self.width, self.height

    @property
    def is_rectified_input(self) -> bool:
        """The images already are rectified (identity R, no distortion, P = [K | t])."""
        return (not np.any(self.D) and np.allclose(self.R, np.eye(3))
                and np.allclose(self.P[:, :3], self.K))

    @property
    def baseline_term(self) -> float:
        """P[0, 3] = -fx' * Tx: zero for a left (or single) camera."""
        return float(self.P[0, 3])


def _named(name: str) -> str:
    return f' ({name})' if name else ''
