"""The probabilistic voxel map: the paper's Gaussian sensor model and Bayesian update.

Sensor model (paper eq. 3): a fingertip measurement ``x`` supports the occupancy of a cell
with centre ``mu`` by the unnormalised Gaussian

    P(Z | O) = exp(-|x - mu|^2 / (2 sigma^2)).

Update (paper eq. 4) in log-odds, with ``P(Z | not O)`` a constant ``c`` (the paper does not
state it; see the README for the choice of 0.45):

    l <- clamp(l + log(P(Z | O) / c), l_min, l_max),    l = log(p / (1 - p)).

One measurement at a cell centre gives p = 1 / (1 + c) = 0.69 (< 0.7: a stray point stays
out of the map); two give 0.83 (> 0.8). A measurement far from the centre (L < c) lowers the
cell: eq. 4 read literally.

The update can touch the containing cell only (the paper) or, optionally, its 26
neighbours as well, each with eq. 3 at its own centre.

How it is fast: with ``e`` the offset of a point from its containing cell's centre and
``o`` a neighbour offset (in cells), ``|e - o|^2 = |e|^2 - 2 o.e + |o|^2``. Summed over the
points of a batch in one containing cell this needs only the count ``n``, ``sum e`` and
``sum |e|^2`` per cell: one pass over the points gathers them, then each touched cell adds
its contribution to itself (and to its 26 neighbours). Exact; the two loops are compiled
(occupancy_kernels.py), because a scatter in numpy costs several passes per statistic.

Clamping (as in OctoMap) is applied after each batch. The nodes and ``build_map`` feed the
grid through :class:`WindowedIntegrator`, which cuts the measurement stream into fixed
windows of sensor time, so the map does not depend on how messages happened to be batched.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from inhand_mapping import occupancy_kernels as kernels

__all__ = ['GridSpec', 'SensorModel', 'OccupancyGrid', 'IntegrationCounts',
           'WindowedIntegrator', 'logit', 'probability']


def logit(p):
    p = np.asarray(p, dtype=float)
    return np.log(p / (1.0 - p))


def probability(log_odds):
    return 1.0 / (1.0 + np.exp(-np.asarray(log_odds, dtype=float)))


@dataclass(frozen=True)
class GridSpec:
    """A cube of ``size`` metres centred at ``centre`` (map frame), cut into cubic cells."""

    size: float = 0.35
    resolution: float = 0.005
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not (self.resolution > 0 and self.size > 0):
            raise ValueError(f'workspace size {self.size} m and resolution {self.resolution} m '
                             'must be positive to make a whole number of cells')
        cells = self.size / self.resolution
        if abs(cells - round(cells)) > 1e-6:
            raise ValueError(f'workspace size {self.size} m is not a whole number of '
                             f'{self.resolution} m cells')

    @property
    def cells_per_axis(self) -> int:
        return int(round(self.size / self.resolution))

    @property
    def shape(self) -> tuple[int, int, int]:
        n = self.cells_per_axis
        return (n, n, n)

    @property
    def origin(self) -> np.ndarray:
        """Map-frame position of the outer corner of cell (0, 0, 0)."""
        return np.asarray(self.centre, dtype=float) - self.size / 2.0

    def cell_centres(self, ijk) -> np.ndarray:
        return self.origin + (np.asarray(ijk, dtype=float) + 0.5) * self.resolution


@dataclass(frozen=True)
class SensorModel:
    """Sensor model and update parameters (defaults: the paper's, and the README's choice)."""

    sigma: float = 0.002
    p_z_given_not_occupied: float = 0.45
    prior: float = 0.5
    clamp_min: float = 0.12
    clamp_max: float = 0.97
    neighbourhood: int = 1  # 1: containing cell (paper); 27: also the 26 neighbours

    def __post_init__(self) -> None:
        if self.neighbourhood not in (1, 27):
            raise ValueError(f'neighbourhood must be 1 or 27, not {self.neighbourhood}')
        if not 0.0 < self.clamp_min < self.prior < self.clamp_max < 1.0:
            raise ValueError('need 0 < clamp_min < prior < clamp_max < 1')
        if not 0.0 < self.p_z_given_not_occupied < 1.0 or self.sigma <= 0:
            raise ValueError('need 0 < P(Z|not O) < 1 and sigma > 0')


@dataclass
class IntegrationCounts:
    """What happened to the measurements given to the grid (totals since creation)."""

    integrated: int = 0
    outside: int = 0
    invalid: int = 0


class OccupancyGrid:
    """Log-odds occupancy per cell, plus hit count and first-touch time per cell."""

    def __init__(self, spec: GridSpec = GridSpec(), model: SensorModel = SensorModel()):
        self.spec = spec
        self.model = model
        self.prior_log_odds = float(logit(model.prior))
        self.log_odds = np.full(spec.shape, self.prior_log_odds, dtype=np.float64)
        self.hits = np.zeros(spec.shape, dtype=np.uint32)
        self.first_touch = np.full(spec.shape, np.nan, dtype=np.float64)
        self._probability = np.full(spec.shape, float(model.prior), dtype=np.float64)
        self.earliest_touch = math.inf  # min of first_touch, kept up to date
        self.counts = IntegrationCounts()
        self._l_min = float(logit(model.clamp_min))
        self._l_max = float(logit(model.clamp_max))
        self._log_c = math.log(model.p_z_given_not_occupied)
        self._scratch_arrays = None

    # ------------------------------------------------------------------ update
    def integrate(self, points, times=None) -> IntegrationCounts:
        """Apply eq. 4 for every point (map frame, metres) as one batch.

        ``times`` (seconds, one per point) feed the first-touch time. Points outside the
        workspace are counted and ignored; NaN or infinite ones are rejected and counted.
        Returns this batch's counts.
        """
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        has_times = times is not None
        if has_times:
            times = np.ascontiguousarray(times, dtype=np.float64).reshape(-1)
            if times.shape[0] != points.shape[0]:
                raise ValueError(f'{points.shape[0]} points but {times.shape[0]} times')
        else:
            times = np.empty(0)
        spec, model = self.spec, self.model
        n = spec.cells_per_axis
        scratch = self._scratch()
        touched = np.empty(min(points.shape[0], n ** 3), dtype=np.int64)
        n_touched, integrated, outside, invalid = kernels.accumulate(
            points, times, has_times, spec.origin, 1.0 / spec.resolution, n, scratch['count'],
            scratch['sum_e'], scratch['sum_e2'], scratch['first'], touched)
        kernels.apply(touched, n_touched, scratch['count'], scratch['sum_e'], scratch['sum_e2'],
                      scratch['first'], self.log_odds.reshape(-1),
                      self._probability.reshape(-1), self.hits.reshape(-1),
                      self.first_touch.reshape(-1), n,
                      -spec.resolution ** 2 / (2.0 * model.sigma ** 2), self._log_c,
                      1 if model.neighbourhood == 27 else 0, self._l_min, self._l_max)
        if has_times and integrated:
            touched_times = self.first_touch.reshape(-1)[touched[:n_touched]]
            self.earliest_touch = min(self.earliest_touch, float(np.nanmin(touched_times)))
        batch = IntegrationCounts(integrated=int(integrated), outside=int(outside),
                                  invalid=int(invalid))
        self.counts.integrated += batch.integrated
        self.counts.outside += batch.outside
        self.counts.invalid += batch.invalid
        return batch

    def _scratch(self) -> dict[str, np.ndarray]:
        """Per-cell sums of one batch; kept between batches (the kernel clears what it used)."""
        if self.__dict__.get('_scratch_arrays') is None:
            size = self.spec.cells_per_axis ** 3
            self._scratch_arrays = {
                'count': np.zeros(size, dtype=np.int64),
                'sum_e': np.zeros((3, size), dtype=np.float64),
                'sum_e2': np.zeros(size, dtype=np.float64),
                'first': np.full(size, np.inf, dtype=np.float64),
            }
        return self._scratch_arrays

    def reset(self) -> None:
        self.log_odds.fill(self.prior_log_odds)
        self._probability.fill(self.model.prior)
        self.earliest_touch = math.inf
        self.hits.fill(0)
        self.first_touch.fill(np.nan)
        self.counts = IntegrationCounts()

    # ------------------------------------------------------------------ queries
    def probabilities(self) -> np.ndarray:
        """Occupancy probability of every cell (read-only; kept current by each update)."""
        view = self._probability.view()
        view.flags.writeable = False
        return view

    def refresh(self) -> None:
        """Recompute what is derived from the arrays after they were set directly (loading)."""
        self._probability[...] = probability(self.log_odds)
        finite = self.first_touch[np.isfinite(self.first_touch)]
        self.earliest_touch = float(finite.min()) if finite.size else math.inf

    def touched_mask(self) -> np.ndarray:
        """Cells any measurement has updated (their log-odds left the prior, or were hit)."""
        return (self.log_odds != self.prior_log_odds) | (self.hits > 0)

    def cells(self, mask: np.ndarray | None = None, threshold: float | None = None):
        """(centres (M, 3), probabilities (M,), hits (M,), first touch (M,)) of the cells in
        ``mask`` (default: touched) and, if given, with probability above ``threshold``."""
        if mask is None:
            mask = self.touched_mask()
        p = self.probabilities()
        if threshold is not None:
            mask = mask & (p > threshold)
        ijk = np.argwhere(mask)
        return (self.spec.cell_centres(ijk), p[mask], self.hits[mask], self.first_touch[mask])


@dataclass
class WindowedIntegrator:
    """Feeds a grid in fixed windows of sensor time, whatever the input batching.

    Points are held until a point of a later window arrives (or ``flush``), then each
    complete window is integrated as one batch, in time order. The node (points in
    messages) and ``build_map`` (points from a bag) therefore build the same map. This
    holds for streams whose stamps never go back past a window already integrated, which
    is what the registrar emits; a point that does is integrated with its own batch and
    counted in ``late_points``.
    """

    grid: OccupancyGrid
    window: float = 0.1
    late_points: int = 0
    _points: list = field(default_factory=list)
    _times: list = field(default_factory=list)
    _integrated_until: float = -math.inf  # windows before this one are done

    def add(self, points, times) -> int:
        """Queue points; integrates every window that is now complete. Returns how many
        points were integrated (or counted as outside/invalid) by this call."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        times = np.asarray(times, dtype=np.float64).reshape(-1)
        if len(points):
            self._points.append(points)
            self._times.append(times)
        if not self._times:
            return 0
        all_times = np.concatenate(self._times)
        finite = all_times[np.isfinite(all_times)]
        if finite.size == 0:
            return self.flush()
        latest_window = math.floor(finite.max() / self.window)
        all_points = np.concatenate(self._points)
        # Everything before the newest window is complete (NaN times go out now, rejected).
        ready = ~(np.floor(all_times / self.window) >= latest_window)
        self._points = [all_points[~ready]]
        self._times = [all_times[~ready]]
        return self._integrate_windows(all_points[ready], all_times[ready])

    def clear(self) -> None:
        """Forget queued points and window history (the map is being reset)."""
        self._points, self._times = [], []
        self._integrated_until = -math.inf

    def flush(self) -> int:
        """Integrate whatever is queued (end of a bag, or before saving/publishing)."""
        if not self._times:
            return 0
        points, times = np.concatenate(self._points), np.concatenate(self._times)
        self._points, self._times = [], []
        return self._integrate_windows(points, times)

    @property
    def pending(self) -> int:
        return int(sum(len(t) for t in self._times))

    def _integrate_windows(self, points: np.ndarray, times: np.ndarray) -> int:
        if len(points) == 0:
            return 0
        done = 0
        valid = np.isfinite(times)
        if not valid.all():  # rejected and counted by the grid, in one go
            counts = self.grid.integrate(points[~valid], times[~valid])
            done += counts.invalid
            points, times = points[valid], times[valid]
        if len(times) == 0:
            return done
        window_ids = np.floor(times / self.window)
        self.late_points += int(np.count_nonzero(window_ids < self._integrated_until))
        self._integrated_until = max(self._integrated_until, float(window_ids.max()) + 1.0)
        order = np.argsort(window_ids, kind='stable')
        points, times, window_ids = points[order], times[order], window_ids[order]
        boundaries = np.flatnonzero(np.diff(window_ids) != 0) + 1
        for chunk_p, chunk_t in zip(np.split(points, boundaries), np.split(times, boundaries)):
            counts = self.grid.integrate(chunk_p, chunk_t)
            done += counts.integrated + counts.outside + counts.invalid
        return done
