"""Disparity of a rectified stereo pair: OpenCV's block matching or semi-global matching,
with stereo_image_proc's parameters, as a float image in DisparityImage's convention.

Parameters
----------
:data:`DISPARITY_PARAMETERS` holds the parameters of stereo_image_proc's ``disparity_node``
with its names, defaults and ranges (image_pipeline, ``stereo_image_proc/src/
stereo_image_proc/disparity_node.cpp``, the ``add_param_to_map`` calls), so a ROS user's YAML
carries over. Their steps (odd window sizes, ``disparity_range`` a multiple of 16) are
checked by :meth:`DisparityConfig.from_parameters`. As in stereo_image_proc,
``prefilter_size`` and ``texture_threshold`` are block matching only, ``P1``, ``P2``,
``full_dp`` and ``disp12_max_diff`` semi-global only, and the floating-point ones
(``uniqueness_ratio``, ``P1``, ``P2``) are truncated to the integers OpenCV takes.

Our own parameters, beyond the bare OpenCV call. Figures from
``test/benchmarks/bench_stereo.py``: synthetic 640x480 pairs with known disparity (planes, a
slanted plane, a sphere), as density (valid fraction of the valid window) / bad-2 (fraction
of valid pixels more than 2 px off), the mean of the three scenes; bare OpenCV SGBM with
its default settings scores 0.976-0.978 / 0.008-0.012 (block 5 to 9) on them.

* ``prefilter``: block matching's prefilter. OpenCV's default, and so stereo_image_proc's,
  is the x-Sobel; the normalised response (the image minus its local mean over
  ``prefilter_size``, which is what ``prefilter_size`` is documented as) keeps more pixels
  on curved and slanted surfaces: 0.966 / 0.0023 against 0.956 / 0.0014 (the sphere 0.924
  against 0.898; with weak texture 0.867 against 0.824). Its bad-2 stays several times
  below bare SGBM's and only it keeps every scene above a density of 0.9, so it is our
  default. A Laplacian-of-Gaussian prefilter (the paper's) measured no better than the
  normalised response and is not offered.
* ``left_right_check``: block matching also checks each match from the right image
  (OpenCV's ``disp12MaxDiff``, at least 1 px): occluded pixels next to depth edges go
  invalid instead of taking the foreground's disparity (bad-2 0.0025 -> 0.0023, for no
  measurable time). Semi-global matching always does this in OpenCV (any
  ``disp12MaxDiff`` below 1 means 1 px there), so it changes nothing for it.
* ``median_size``: a 3x3 or 5x5 median of the disparity; invalid pixels stay invalid.
  A 5x5 median lowers bad-2 and the mean error by 5-10 % (block matching 0.0023 -> 0.0021,
  semi-global 0.0038 -> 0.0036) for about 0.5 ms a frame, which block matching's time
  budget (our path within 1.2x the bare matcher) cannot spare: off by default; worth
  turning on with semi-global matching.
* ``wls_lambda``/``wls_sigma``: the edge-preserving weighted-least-squares filter of
  ``cv2.ximgproc`` with a right matcher. It fills every pixel (occlusions included), bleeds
  across depth edges on textured surfaces (bad-2 0.039) and costs a second matcher run
  (2.2-2.7x the bare matcher): off by default.

For the rig (0.3-0.5 m), semi-global matching with a 5 px window measured best within the
time budget: 0.973 / 0.0023, and 0.956 / 0.0056 with weak texture where block matching
falls to a density of 0.867 (``stereo_algorithm: 1``, ``correlation_window_size: 5``,
``median_size: 5`` in the node's YAML); ``full_dp`` improves on it a little more for twice
the time.

Output
------
:class:`DisparityResult` carries what DisparityImage needs: ``d = x_l - x_r - (cx_l -
cx_r)`` in pixels (float32, OpenCV's 1/16 pixel steps), the search range in the same units,
the valid window, and invalid pixels at ``min_disparity - 1``.

No rclpy here: the node declares the table with ``inhand_common.ros_parameters``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from inhand_common.array_types import Bools
from inhand_common.parameters import ParameterError, ParamSpec, validate
from inhand_stereo.image_encoding import to_grey

__all__ = ['BLOCK_MATCHING', 'DISPARITY_PARAMETERS', 'PREFILTERS', 'SEMI_GLOBAL',
           'DisparityConfig', 'DisparityMatcher', 'DisparityResult', 'valid_window']

BLOCK_MATCHING, SEMI_GLOBAL = 0, 1
PREFILTERS = ('normalized_response', 'xsobel')
DISPARITY_SCALE = 16        # OpenCV's fixed point: 16 steps per pixel

# Names, defaults and ranges of stereo_image_proc's disparity_node (ROS 2, rolling/jazzy).
DISPARITY_PARAMETERS = (
    ParamSpec('stereo_algorithm', 0, 'Stereo algorithm: Block Matching (0) or Semi-Global '
              'Block Matching (1)', minimum=0, maximum=1),
    ParamSpec('prefilter_size', 9, 'Normalization window size in pixels (must be odd; block '
              "matching with prefilter 'normalized_response' only)", minimum=5, maximum=255),
    ParamSpec('prefilter_cap', 31, 'Bound on normalized pixel values', minimum=1, maximum=63),
    ParamSpec('correlation_window_size', 15, 'SAD correlation window width in pixels (must '
              'be odd)', minimum=5, maximum=255),
    ParamSpec('min_disparity', 0, 'Disparity to begin search at in pixels', minimum=-2048,
              maximum=2048),
    ParamSpec('disparity_range', 64, 'Number of disparities to search in pixels (must be a '
              'multiple of 16)', minimum=32, maximum=4096),
    ParamSpec('texture_threshold', 10, 'Filter out if SAD window response does not exceed '
              'texture threshold (Block Matching only)', minimum=0, maximum=10000),
    ParamSpec('speckle_size', 100, 'Reject regions smaller than this size in pixels',
              minimum=0, maximum=1000),
    ParamSpec('speckle_range', 4, 'Maximum allowed difference between detected disparities',
              minimum=0, maximum=31),
    ParamSpec('disp12_max_diff', 0, 'Maximum allowed difference in the left-right disparity '
              'check in pixels (Semi-Global Block Matching; block matching too with '
              'left_right_check)', minimum=0, maximum=128),
    ParamSpec('uniqueness_ratio', 15.0, 'Filter out if best match does not sufficiently '
              'exceed the next-best match', minimum=0.0, maximum=100.0),
    ParamSpec('P1', 200.0, 'The first parameter controlling the disparity smoothness '
              '(Semi-Global Block Matching only)', minimum=0.0, maximum=4000.0),
    ParamSpec('P2', 400.0, 'The second parameter controlling the disparity smoothness '
              '(Semi-Global Block Matching only)', minimum=0.0, maximum=4000.0),
    ParamSpec('full_dp', False, 'Run the full variant of the algorithm (Semi-Global Block '
              'Matching only)'),
    # Ours, beyond stereo_image_proc (module doc).
    ParamSpec('prefilter', 'normalized_response', 'Block matching prefilter: '
              "'normalized_response' (image minus its local mean over prefilter_size) or "
              "'xsobel' (OpenCV's and stereo_image_proc's default)", choices=PREFILTERS),
    ParamSpec('left_right_check', True, 'Block matching: invalidate matches the right image '
              'does not confirm within max(1, disp12_max_diff) px (semi-global matching '
              'always checks)'),
    ParamSpec('median_size', 0, 'Median filter of the disparity (0 off, 3 or 5 pixels); '
              'invalid pixels stay invalid', choices=(0, 3, 5)),
    ParamSpec('wls_lambda', 0.0, 'Edge-preserving WLS filter strength (cv2.ximgproc, with a '
              'right matcher: twice the matching cost); 0 = off, about 8000 typical',
              minimum=0.0, maximum=100000.0),
    ParamSpec('wls_sigma', 1.5, 'WLS filter colour sensitivity (larger: smooths across '
              'stronger image edges)', minimum=0.1, maximum=10.0),
)

_ODD = ('prefilter_size', 'correlation_window_size')


@dataclass(frozen=True)
class DisparityConfig:
    """The disparity parameters, checked and typed."""

    stereo_algorithm: int           # BLOCK_MATCHING or SEMI_GLOBAL
    prefilter_size: int             # odd, px
    prefilter_cap: int
    correlation_window_size: int    # odd, px
    min_disparity: int              # px, in x_l - x_r (before the cx adjustment)
    disparity_range: int            # px, a multiple of 16
    texture_threshold: int
    speckle_size: int               # px
    speckle_range: int              # px
    disp12_max_diff: int            # px
    uniqueness_ratio: float         # percent
    P1: float
    P2: float
    full_dp: bool
    prefilter: str                  # one of PREFILTERS
    left_right_check: bool
    median_size: int                # 0, 3 or 5
    wls_lambda: float               # 0 = off
    wls_sigma: float

    @classmethod
    def from_parameters(cls, values: Mapping[str, Any] | None = None) -> DisparityConfig:
        """From parameter values (missing ones take their defaults); refuses values out of
        range and the steps stereo_image_proc's ranges have (odd window sizes,
        ``disparity_range`` a multiple of 16) with ParameterError naming them."""
        checked = validate(DISPARITY_PARAMETERS, dict(values or {}))
        specs = {spec.name: spec for spec in DISPARITY_PARAMETERS}
        problems = []
        for name in _ODD:
            if checked[name] % 2 == 0:
                problems.append(f"parameter '{name}' = {checked[name]!r} is refused: allowed "
                                f'is an odd integer in [{specs[name].minimum:g}, '
                                f'{specs[name].maximum:g}]')
        if checked['disparity_range'] % DISPARITY_SCALE:
            spec = specs['disparity_range']
            problems.append(f"parameter 'disparity_range' = {checked['disparity_range']!r} is "
                            f'refused: allowed is a multiple of 16 in [{spec.minimum:g}, '
                            f'{spec.maximum:g}]')
        if problems:
            raise ParameterError(problems)
        return cls(**{name: checked[name] for name in cls.__dataclass_fields__})

    @property
    def max_search(self) -> int:
        """Largest disparity searched (x_l - x_r, px)."""
        return self.min_disparity + self.disparity_range - 1


def valid_window(width: int, height: int, min_disparity: int, disparity_range: int,
                 window_size: int) -> tuple[int, int, int, int]:
    """(x_offset, y_offset, width, height) of the pixels whose whole correlation window,
    at every disparity searched, lies in both images: DisparityImage's ``valid_window``.

    Left of ``max_disparity + window/2`` a left pixel's match could lie left of the right
    image; a negative ``min_disparity`` likewise cuts the right edge. (stereo_image_proc
    computes this from the message width before it is set, so its window is garbage; this
    is the window it means.)
    """
    border = window_size // 2
    max_d = min_disparity + disparity_range - 1
    x0 = max(max_d, 0) + border
    x1 = width - 1 - border - max(-min_disparity, 0)        # inclusive
    y0, y1 = border, height - 1 - border
    if x1 < x0 or y1 < y0:
        return (0, 0, 0, 0)
    return (x0, y0, x1 - x0 + 1, y1 - y0 + 1)


@dataclass(frozen=True)
class DisparityResult:
    """One disparity image, as stereo_msgs/DisparityImage holds it."""

    disparity: NDArray[np.float32]              # (H, W) px: x_l - x_r - (cx_l - cx_r)
    valid_window: tuple[int, int, int, int]     # x_offset, y_offset, width, height
    min_disparity: float                        # smallest d searched, same units as above
    max_disparity: float                        # largest d searched
    delta_d: float = 1.0 / DISPARITY_SCALE      # smallest step between two disparities

    @property
    def invalid_value(self) -> float:
        """What invalid pixels hold: ``min_disparity - 1``."""
        return self.min_disparity - 1.0

    @property
    def valid(self) -> Bools:
        """(H, W) True where the disparity was measured."""
        mask: Bools = self.disparity >= np.float32(self.min_disparity)
        return mask

    def density(self) -> float:
        """Fraction of the valid window's pixels with a disparity."""
        x, y, w, h = self.valid_window
        if w == 0 or h == 0:
            return 0.0
        return float(np.mean(self.valid[y:y + h, x:x + w]))


class DisparityMatcher:
    """Disparity of rectified pairs with one configuration (module doc).

    The OpenCV matchers keep scratch buffers between frames, so keep one matcher for the
    node's life (rebuild it when parameters change). Not thread-safe: one call at a time.
    """

    def __init__(self, config: DisparityConfig | Mapping[str, Any] | None = None) -> None:
        if not isinstance(config, DisparityConfig):
            config = DisparityConfig.from_parameters(config)
        self.config = config
        self._matcher = _make_matcher(config)
        self._right_matcher: cv2.StereoMatcher | None = None
        self._wls: Any = None
        if config.wls_lambda > 0.0:
            self._right_matcher = cv2.ximgproc.createRightMatcher(self._matcher)
            self._wls = cv2.ximgproc.createDisparityWLSFilter(self._matcher)
            self._wls.setLambda(config.wls_lambda)
            self._wls.setSigmaColor(config.wls_sigma)

    @property
    def opencv_matcher(self) -> cv2.StereoMatcher:
        """The cv2.StereoBM or cv2.StereoSGBM this matcher calls (benchmarks compare with it)."""
        return self._matcher

    def compute(self, left: NDArray[np.uint8], right: NDArray[np.uint8], *,
                cx_offset: float = 0.0, encoding: str = 'rgb8') -> DisparityResult:
        """Disparity of a rectified pair (mono8 (H, W) or colour (H, W, 3) uint8, converted
        to grey once; ``encoding`` says the channel order of colour images).

        ``cx_offset`` is ``cx_left - cx_right`` of the rectified cameras
        (:attr:`~inhand_stereo.rectification.StereoRectifier.cx_offset`): the search range
        stays in ``x_l - x_r`` as the parameters say, the output is shifted by it.
        """
        if left.shape[:2] != right.shape[:2]:
            raise ValueError(f'left image {left.shape} and right image {right.shape} differ '
                             'in size')
        grey_left, grey_right = to_grey(left, encoding), to_grey(right, encoding)
        config = self.config
        height, width = grey_left.shape
        for name in _ODD:
            if getattr(config, name) > min(width, height):
                raise ValueError(f"parameter '{name}' = {getattr(config, name)} is larger than "
                                 f'the {width}x{height} image')
        fixed = np.asarray(self._matcher.compute(grey_left, grey_right), dtype=np.int16)
        invalid_fixed = (config.min_disparity - 1) * DISPARITY_SCALE
        if self._wls is not None and self._right_matcher is not None:
            fixed = self._filter_wls(fixed, grey_left, grey_right, invalid_fixed)
        if config.median_size:
            fixed = _median(fixed, config.median_size, invalid_fixed)
        # One pass: the int16 values are cast and scaled (by a power of two: exact) at once.
        disparity = np.multiply(fixed, np.float32(1.0 / DISPARITY_SCALE), dtype=np.float32)
        offset = np.float32(cx_offset)
        if offset:
            disparity -= offset
        window = valid_window(width, height, config.min_disparity, config.disparity_range,
                              config.correlation_window_size)
        return DisparityResult(
            disparity=disparity, valid_window=window,
            min_disparity=float(np.float32(config.min_disparity) - offset),
            max_disparity=float(np.float32(config.max_search) - offset))

    def _filter_wls(self, fixed: NDArray[np.int16], grey_left: NDArray[np.uint8],
                    grey_right: NDArray[np.uint8], invalid_fixed: int) -> NDArray[np.int16]:
        """WLS-filtered disparity (fixed point); values outside the searched range, where
        the filter has spread nothing, are marked invalid."""
        assert self._right_matcher is not None
        right_disparity = np.asarray(self._right_matcher.compute(grey_right, grey_left),
                                     dtype=np.int16)
        filtered = np.asarray(self._wls.filter(fixed, grey_left,
                                               disparity_map_right=right_disparity),
                              dtype=np.int16)
        lowest = self.config.min_disparity * DISPARITY_SCALE
        filtered[filtered < lowest] = invalid_fixed
        return filtered


def _make_matcher(config: DisparityConfig) -> cv2.StereoMatcher:
    """The OpenCV matcher with the configuration's settings, as stereo_image_proc sets
    them (floating-point parameters truncated to OpenCV's integers)."""
    uniqueness = int(config.uniqueness_ratio)
    if config.stereo_algorithm == BLOCK_MATCHING:
        bm = cv2.StereoBM.create(config.disparity_range, config.correlation_window_size)
        bm.setMinDisparity(config.min_disparity)
        bm.setPreFilterType(cv2.StereoBM_PREFILTER_NORMALIZED_RESPONSE
                            if config.prefilter == 'normalized_response'
                            else cv2.StereoBM_PREFILTER_XSOBEL)
        bm.setPreFilterSize(config.prefilter_size)
        bm.setPreFilterCap(config.prefilter_cap)
        bm.setTextureThreshold(config.texture_threshold)
        bm.setUniquenessRatio(uniqueness)
        bm.setSpeckleWindowSize(config.speckle_size)
        bm.setSpeckleRange(config.speckle_range)
        bm.setDisp12MaxDiff(max(1, config.disp12_max_diff) if config.left_right_check else -1)
        return bm
    sgbm = cv2.StereoSGBM.create(
        minDisparity=config.min_disparity, numDisparities=config.disparity_range,
        blockSize=config.correlation_window_size, P1=int(config.P1), P2=int(config.P2),
        disp12MaxDiff=config.disp12_max_diff, preFilterCap=config.prefilter_cap,
        uniquenessRatio=uniqueness, speckleWindowSize=config.speckle_size,
        speckleRange=config.speckle_range,
        mode=cv2.StereoSGBM_MODE_HH if config.full_dp else cv2.StereoSGBM_MODE_SGBM)
    return sgbm


def _median(fixed: NDArray[np.int16], size: int, invalid_fixed: int) -> NDArray[np.int16]:
    """Median of a fixed-point disparity; pixels invalid before stay invalid.

    cv2.medianBlur takes no int16 with a 5x5 window, so the values go through uint16 with the
    sign bit flipped (an order-preserving map: int16 order is uint16 order after ``^ 0x8000``);
    that is twice as fast as a float32 median.
    """
    flip = np.uint16(0x8000)
    shifted = fixed.view(np.uint16) ^ flip
    smoothed = cv2.medianBlur(shifted, size)
    result = (np.asarray(smoothed, dtype=np.uint16) ^ flip).view(np.int16)
    result[fixed == invalid_fixed] = invalid_fixed
    return result
