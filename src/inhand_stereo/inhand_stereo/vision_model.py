"""The vision sensor model (paper III.C, eqs. 5-7) and the vision local map.

Eq. 5 gives each cell crossed by a stereo ray a Gaussian belief over its occupancy value,
``P(O_c | Z_vis) = N(mu, sigma)``, from the measured range ``d_j`` along the ray and the
cell centre's range ``d_l`` on it (``delta = d_l - d_j``: negative in front of the measured
surface, positive behind it):

* eq. 6, the mean: 0 (free) for ``delta <= -epsilon/2``, ``1/2 + delta/epsilon`` inside the
  band ``|delta| < epsilon/2``, 1 (occupied) behind it;
* eq. 7, the spread: ``sigma_s(d_j) / epsilon`` inside the band, decaying as
  ``exp(-(|delta| - epsilon/2) / tau)`` away from it (confident far from the surface);
* ``sigma_s(d)``, the range noise of the stereo camera at range ``d``: the paper's linear
  model ``sigma_min + zeta d`` (``noise='linear'``) or the stereo one, triangulation error
  growing with the square of the range, ``sigma_min + zeta d^2`` (``noise='stereo'``;
  ``zeta = sigma_disparity / (f B)`` in 1/m for a disparity noise in pixels, focal f in
  pixels and baseline B in metres).

The camera's noise is not the same everywhere: a weakly textured surface gives scattered
matches and a depth edge mixes two surfaces. ``spread_window`` (default 5 px) measures it:
where the depth's local spread (:func:`depth_spread`) is larger than ``sigma_s(d)``, it
takes its place, so scattered depths give weak evidence. Measured on the bundled bottle
(dark glass): the fused map's F@5mm 0.697 -> 0.716, the vision map's precision 0.78 -> 0.81;
on textured surfaces it costs the vision map a little recall (cat: 0.517 -> 0.469) and the
fused map at most 0.003 (a 30 s session: 0.025).

From a belief over the occupancy value to a probability (the paper does not say), two
readings, parameter ``update``:

* ``'mass'`` (default): the probability that the cell is occupied is the belief's mass
  above one half, ``P(O) = Phi((mu - 1/2) / sigma)``: a confident belief (small sigma) gives
  a decisive probability, a vague one stays near 1/2;
* ``'mean'``: the expected occupancy value under the belief truncated to [0, 1].

Each observation of a cell becomes one log-odds update ``logit(P(O))``, clamped to
``[logit(p_free), logit(p_occupied)]`` (one picture is one measurement: it must not make a
cell certain on its own, as the touch model's clamping says for a touch).

Touch maps describe the object's *surface*: the cells the surface passes through. Two
choices make the vision map describe the same shell:

* ``d_l`` is the range of the cell's *far side* on the ray (its centre's range plus half a
  cell): the paper's centre range makes the cell whose centre lies on the surface exactly
  half occupied (mu = 1/2, P(O) = 1/2 whatever sigma), so the cell the surface passes
  through would hover around 1/2; measured to its far side, a cell the surface passes
  through is partly behind it and leans occupied, the cell in front of it leans free.
* Eq. 6 would fill the object's inside behind every seen surface (mu = 1 all the way
  back). The update stops at the cell the surface passes through: cells whose centre is
  more than ``behind`` (default half a cell) behind the measured surface stay unknown.

In front of the surface the free space is carved the whole way to the camera (within the
grid): that is what removes a touch map's strays in the air.

One exposure updates every cell of the grid once, through the cell centre's ray (the
projective form, as volumetric depth fusion does): each centre goes into the rectified left
camera, the depth at its pixel gives ``d_j`` on the ray through the centre, and the cell gets
the model at ``delta``. Cells outside the picture, behind the camera or on a pixel without
depth are not updated (unknown). Vectorised over the grid; no Python loop per cell or ray.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, NamedTuple, TypeAlias

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtr  # type: ignore[import-untyped]

from inhand_common.array_types import Bools, Floats, Matrix3, Vector3
from inhand_common.log_odds import logit
from inhand_common.log_odds import probability as probability_of
from inhand_mapping.occupancy import GridSpec
from inhand_stereo.vision_kernels import depth_surface, expose_grid

__all__ = ['NOISE_MODELS', 'UPDATES', 'VisionMap', 'VisionModel', 'VisionObservation',
           'depth_spread', 'observe_grid', 'warm_up']

NoiseModel: TypeAlias = Literal['linear', 'stereo']
Update: TypeAlias = Literal['mass', 'mean']
NOISE_MODELS: tuple[NoiseModel, ...] = ('linear', 'stereo')
UPDATES: tuple[Update, ...] = ('mass', 'mean')
MIN_DEPTH = 1e-3      # m: cells closer to the camera's centre are not seen
TINY_SIGMA = 1e-9     # occupancy-value units: below this a belief is a point mass


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


@dataclass(frozen=True)
class VisionModel:
    """Eqs. 5-7 with the band limit and the probability reading (module doc)."""

    epsilon: float = 0.01          # m: width of the ramp of eq. 6
    tau: float = 0.01              # m: decay of eq. 7's spread away from the band
    sigma_min: float = 0.001       # m: range noise at the camera
    zeta: float = 0.005            # 1/1 (linear) or 1/m (stereo): growth of the noise
    noise: NoiseModel = 'linear'
    update: Update = 'mass'
    behind: float | None = None    # m (cell centre behind the surface) still updated; None:
    #                                half a cell
    p_free: float = 0.12           # the lowest probability one observation gives
    p_occupied: float = 0.97       # the highest
    spread_window: int = 5         # px: the measured local spread of the depth (0: off)

    def __post_init__(self) -> None:
        problems = []
        for name in ('epsilon', 'tau'):
            if not getattr(self, name) > 0:
                problems.append(f'{name} must be > 0 m, got {getattr(self, name)}')
        if not (self.sigma_min >= 0 and self.zeta >= 0 and self.sigma_min + self.zeta > 0):
            problems.append(f'sigma_min ({self.sigma_min}) and zeta ({self.zeta}) must be '
                            '>= 0 and not both 0')
        if self.noise not in NOISE_MODELS:
            problems.append(f'noise must be one of {NOISE_MODELS}, got {self.noise!r}')
        if self.update not in UPDATES:
            problems.append(f'update must be one of {UPDATES}, got {self.update!r}')
        if self.behind is not None and not self.behind >= 0:
            problems.append(f'behind must be >= 0 m, got {self.behind}')
        if self.spread_window != 0 and not (3 <= self.spread_window <= 31
                                            and self.spread_window % 2 == 1):
            problems.append(f'spread_window must be 0 (off) or odd in [3, 31], got '
                            f'{self.spread_window}')
        if not 0.0 < self.p_free < 0.5 < self.p_occupied < 1.0:
            problems.append(f'need 0 < p_free ({self.p_free}) < 0.5 < p_occupied '
                            f'({self.p_occupied}) < 1')
        if problems:
            raise ValueError('vision model: ' + '; '.join(problems))

    def band_behind(self, resolution: float) -> float:
        """Metres a cell centre may lie behind the measured surface and still be updated."""
        return resolution / 2.0 if self.behind is None else self.behind

    def sigma_s(self, d: ArrayLike) -> Floats:
        """Range noise (m) of a measurement at range ``d`` (m)."""
        d = np.asarray(d, dtype=np.float64)
        growth = d if self.noise == 'linear' else d * d
        sigma: Floats = self.sigma_min + self.zeta * growth
        return sigma

    def mu(self, delta: ArrayLike) -> Floats:
        """Eq. 6: mean occupancy value at ``delta = d_l - d_j`` (m)."""
        delta = np.asarray(delta, dtype=np.float64)
        mu: Floats = np.clip(0.5 + delta / self.epsilon, 0.0, 1.0)
        return mu

    def sigma(self, delta: ArrayLike, d: ArrayLike, spread: ArrayLike | None = None) -> Floats:
        """Eq. 7: spread of the occupancy value (its units) at ``delta``, measured range ``d``;
        ``spread`` (m), the measured local spread of the depth, raises sigma_s where it is
        larger (:func:`depth_spread`)."""
        delta = np.asarray(delta, dtype=np.float64)
        sigma_s = self.sigma_s(d)
        if spread is not None:
            sigma_s = np.maximum(sigma_s, np.asarray(spread, dtype=np.float64))
        base = sigma_s / self.epsilon
        outside = np.maximum(np.abs(delta) - self.epsilon / 2.0, 0.0)
        sigma: Floats = base * np.exp(-outside / self.tau)
        return sigma

    def probability(self, delta: ArrayLike, d: ArrayLike, spread: ArrayLike | None = None
                    ) -> Floats:
        """P(O) of a cell at ``delta`` from a measurement at range ``d``, by ``update``,
        before the clamping to [p_free, p_occupied]."""
        mu = self.mu(delta)
        sigma = np.maximum(self.sigma(delta, d, spread), TINY_SIGMA)
        if self.update == 'mass':
            p: Floats = ndtr((mu - 0.5) / sigma)
            return p
        return _truncated_normal_mean(mu, sigma)

    def kernel_parameters(self) -> Floats:
        """The model as vision_kernels.model_log_odds takes it."""
        return np.array([self.epsilon, self.tau, self.sigma_min, self.zeta,
                         float(self.noise == 'stereo'), float(self.update == 'mean'),
                         self.p_free, self.p_occupied, _logit(self.p_free),
                         _logit(self.p_occupied)])

    def log_odds(self, delta: ArrayLike, d: ArrayLike, spread: ArrayLike | None = None
                 ) -> Floats:
        """The clamped log-odds update of one observation."""
        p = np.clip(self.probability(delta, d, spread), self.p_free, self.p_occupied)
        return logit(p)


def _truncated_normal_mean(mu: Floats, sigma: Floats) -> Floats:
    """Mean of N(mu, sigma) truncated to [0, 1]."""
    a, b = (0.0 - mu) / sigma, (1.0 - mu) / sigma
    mass = np.maximum(ndtr(b) - ndtr(a), 1e-300)
    pdf_a = np.exp(-0.5 * a * a) / math.sqrt(2.0 * math.pi)
    pdf_b = np.exp(-0.5 * b * b) / math.sqrt(2.0 * math.pi)
    mean: Floats = np.clip(mu + sigma * (pdf_a - pdf_b) / mass, 0.0, 1.0)
    return mean


class VisionObservation(NamedTuple):
    """What one exposure says about the grid: the flat indices of the cells it updates
    and their log-odds updates, with the ``delta`` (m) and measured range of each."""

    cells: NDArray[np.intp]       # (M,) flat indices into the (n, n, n) grid
    log_odds: Floats              # (M,)
    delta: Floats                 # (M,) d_l - d_j, d_l to the cell's far side
    range: Floats                 # (M,) d_j


def depth_spread(depth: NDArray[np.floating], window: int = 5) -> NDArray[np.float32]:
    """(H, W) the local spread (m) of a depth image: the RMS over a ``window`` square of
    each pixel's difference from the mean of its 3x3 neighbours. A plane's depth is linear
    in the pixel coordinates and its 3x3 mean is the centre's own value, so a smooth
    surface, slanted or not, shows only the matcher's noise, while a weakly textured
    surface (wrong matches) and a depth edge show their scatter. NaN where too few of the
    window's pixels have a depth. In float32 (the depth's own precision; the box filters
    run about twice as fast as in float64)."""
    import cv2
    z = np.asarray(depth, dtype=np.float32)
    valid = np.isfinite(z)
    filled = np.where(valid, z, np.float32(0.0))

    def box(values: NDArray[np.float32], size: int) -> NDArray[np.float32]:
        return np.asarray(cv2.blur(values, (size, size), borderType=cv2.BORDER_CONSTANT),
                          dtype=np.float32)

    weight = box(valid.astype(np.float32), 3)
    neighbours = box(filled, 3) / np.where(weight > 0, weight, np.float32(1.0))
    complete = valid & (weight > 0.99)
    residual = np.where(complete, filled - neighbours, np.float32(0.0))
    count = box(complete.astype(np.float32), window)
    mean_square = np.maximum(box(residual * residual, window), np.float32(0.0)) / \
        np.where(count > 0, count, np.float32(1.0))
    spread: NDArray[np.float32] = np.where(count >= 0.5, np.sqrt(mean_square),
                                           np.float32(np.nan))
    return spread


def observe_grid(spec: GridSpec, depth: NDArray[np.floating], P: ArrayLike,
                 map_to_camera: tuple[Matrix3, Vector3], model: VisionModel,
                 object_mask: Bools | None = None,
                 spread: NDArray[np.floating] | None = None) -> VisionObservation:
    """The cells of the grid ``spec`` one exposure updates (module doc).

    ``depth`` (H, W): z along the rectified left optical axis per pixel, NaN where there is
    no measurement; ``P`` the rectified left camera's 3x4 projection; ``map_to_camera``
    ``(M, b)`` with ``p_rectified = M p_map + b``. ``object_mask`` (H, W): the object's
    pixels; elsewhere (the table, the backdrop) a measurement only says that the space in
    front of it is free (cells with mu = 0), its own surface is not the object's.
    ``spread`` (H, W): the measured local spread of the depth (:func:`depth_spread`),
    raising sigma_s where it is larger; NaN there means no measurement."""
    surface = np.empty((*np.shape(depth), 2), dtype=np.float32)
    depth_surface(np.ascontiguousarray(depth, dtype=np.float32), _mask_argument(object_mask), 0,
                  surface)
    if spread is not None:
        surface[..., 1] = spread
    return _observation(spec, surface, P, map_to_camera, model)


def _observation(spec: GridSpec, surface: NDArray[np.float32], P: ArrayLike,
                 map_to_camera: tuple[Matrix3, Vector3], model: VisionModel) -> VisionObservation:
    """The cells one exposure of ``surface`` (depth_surface's layout) updates, not applied."""
    size = spec.cells_per_axis ** 3
    cells, updates = np.empty(size, dtype=np.intp), np.empty(size)
    delta, measured_range = np.empty(size), np.empty(size)
    kept = _expose(spec, surface, P, map_to_camera, model, np.empty(0), (0.0, 0.0),
                   (cells, updates, delta, measured_range))
    return VisionObservation(cells[:kept].copy(), updates[:kept].copy(), delta[:kept].copy(),
                             measured_range[:kept].copy())


def _mask_argument(object_mask: Bools | None) -> NDArray[np.bool_]:
    """The object mask as the kernels take it: (0, 0) for none."""
    return (np.empty((0, 0), dtype=bool) if object_mask is None
            else np.ascontiguousarray(object_mask, dtype=bool))


def _expose(spec: GridSpec, surface: NDArray[np.float32], P: ArrayLike,
            map_to_camera: tuple[Matrix3, Vector3], model: VisionModel, log_odds: Floats,
            clamp: tuple[float, float], outputs: tuple[NDArray[np.intp], Floats, Floats, Floats]) -> int:
    """vision_kernels.expose_grid with the model's and the camera's arguments."""
    matrix, offset = map_to_camera
    # The small inputs as fresh (writable) copies: a read-only one (a camera's P from a
    # message buffer) would be another type to numba, and another compile.
    kept: int = expose_grid(
        spec.cells_per_axis, np.array(spec.origin, dtype=np.float64).reshape(3),
        float(spec.resolution), np.array(matrix, dtype=np.float64),
        np.array(offset, dtype=np.float64).reshape(3), np.array(P, dtype=np.float64).reshape(3, 4),
        surface, float(model.band_behind(spec.resolution)), -model.epsilon / 2.0,
        model.kernel_parameters(), log_odds, clamp[0], clamp[1], *outputs)
    return kept


class VisionMap:
    """The vision local map: log-odds per cell of a grid, prior 1/2, clamped like the touch
    map; each exposure is integrated once (:meth:`integrate`)."""

    def __init__(self, spec: GridSpec, model: VisionModel, clamp: tuple[float, float]):
        if not 0.0 < clamp[0] < 0.5 < clamp[1] < 1.0:
            raise ValueError(f'clamp must be (low, high) with 0 < low < 0.5 < high < 1, '
                             f'got {clamp}')
        self.spec, self.model = spec, model
        self.clamp = (_logit(clamp[0]), _logit(clamp[1]))
        self.log_odds: NDArray[np.float64] = np.zeros(spec.shape, dtype=np.float64)
        self.exposures = 0
        self._surface = np.empty((0, 0, 2), dtype=np.float32)   # reused while the size holds

    def _depth_surface(self, depth: NDArray[np.floating], object_mask: Bools | None
                       ) -> NDArray[np.float32]:
        """The depth (with the object mask) and its local spread (the model's
        ``spread_window``; 0: none), side by side as the kernel reads them."""
        if self._surface.shape[:2] != np.shape(depth):
            self._surface = np.empty((*np.shape(depth), 2), dtype=np.float32)
        depth_surface(np.ascontiguousarray(depth, dtype=np.float32), _mask_argument(object_mask),
                      self.model.spread_window, self._surface)
        return self._surface

    def observe(self, depth: NDArray[np.floating], P: ArrayLike,
                map_to_camera: tuple[Matrix3, Vector3], object_mask: Bools | None = None
                ) -> VisionObservation:
        """The exposure's updates, without applying them (:func:`observe_grid`, with the
        depth's local spread when the model's ``spread_window`` is on)."""
        return _observation(self.spec, self._depth_surface(depth, object_mask), P,
                            map_to_camera, self.model)

    def integrate(self, depth: NDArray[np.floating], P: ArrayLike,
                  map_to_camera: tuple[Matrix3, Vector3], object_mask: Bools | None = None
                  ) -> int:
        """Apply one exposure (what :meth:`observe` returns, added and clamped in the same
        pass over the grid); returns how many cells it updated."""
        nothing = np.empty(0)
        updated = _expose(self.spec, self._depth_surface(depth, object_mask), P, map_to_camera,
                          self.model, self.log_odds.reshape(-1), self.clamp,
                          (np.empty(0, dtype=np.intp), nothing, nothing, nothing))
        self.exposures += 1
        return updated

    def reset(self) -> None:
        self.log_odds.fill(0.0)
        self.exposures = 0

    def probabilities(self) -> NDArray[np.float64]:
        """Occupancy probability of every cell (1/2 where vision says nothing)."""
        return probability_of(self.log_odds)

    def observed_mask(self) -> Bools:
        """Cells any exposure updated."""
        observed: Bools = self.log_odds != 0.0
        return observed


def warm_up(model: VisionModel, resolution: float) -> None:
    """Run the compiled kernel of one exposure once: a 4 x 4 depth image of a scratch 8^3
    grid. numba loads the kernel from its cache (or compiles it) on its first call; a node
    pays that at start rather than on its first pair. The kernel's argument types do not
    depend on the image's or the grid's size, so this loads the same machine code."""
    vision = VisionMap(GridSpec(size=8 * resolution, resolution=resolution), model, (0.12, 0.97))
    depth = np.full((4, 4), 0.3, dtype=np.float32)
    camera = np.array([[100.0, 0.0, 2.0, 0.0], [0.0, 100.0, 2.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    placed = (np.eye(3), np.array([0.0, 0.0, 0.3]))
    vision.integrate(depth, camera, placed, np.ones((4, 4), dtype=bool))
    vision.integrate(depth, camera, placed)
