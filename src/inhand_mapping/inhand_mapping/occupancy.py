"""The probabilistic voxel map: the paper's Gaussian sensor model and Bayesian update.

Sensor model (paper eq. 3): a fingertip measurement ``x`` supports the occupancy of a cell
by the unnormalised Gaussian

    L = P(Z | O) = exp(-d^2 / (2 sigma^2)),

with ``d`` the distance from ``x`` to the cell: to its nearest point by default
(``distance_to='cell'``: 0 inside, so a measurement inside a cell supports it fully and the
Gaussian of the sensor noise only matters for neighbours), or to its centre
(``distance_to='centre'``, the paper read literally: then a measurement more than 2.5 mm
from the centre of its own 5 mm cell lowers it; see docs/mapping.md).

Update (paper eq. 4) in log-odds, with ``P(Z | not O)`` a constant ``c`` (the paper does not
state it; docs/mapping.md derives 0.45 from the paper's thresholds):

    l <- clamp(l + w log(L / c), l_min, l_max),    l = log(p / (1 - p)),

clamped after every update as in OctoMap. One full measurement inside a cell gives
p = 1 / (1 + c) = 0.69 (under the paper's 0.7: a stray point stays out of the map); two
independent ones give 0.83 (over 0.8).

How much a fingertip's touch counts is the *touch model* (``SensorModel.touch_model``):

* ``'path'`` (the default, touch_paths.py): the fingertip's path through the cells,
  per visit; each cell's log-odds are ``clamp(l0 + touches * log(1 / c))``, eq. 4 with the
  touches at distance 0;
* ``'samples'``: eq. 4 per sample, as below.

In the samples model, ``w`` in [0, 1] says how much of an independent measurement the
sample is:

* **dwell** (dwell.py): a sample counts for the time the fingertip spent where it was
  sampled, in units of ``1 / evidence_rate`` (15 Hz: the paper's rate), so the same motion
  gives the same evidence at 15 or 240 Hz and a finger flying past between strokes, or
  lifting off the surface, counts for little. The speed looks one period ahead, so each
  finger's newest samples wait for the next period (``pending``; ``flush()`` at the end);
* **visits**: samples of one finger in one cell less than ``visit_gap`` apart are one
  visit, and a visit gives at most one measurement's worth. A fingertip resting on a
  spot, or lifting off it again and again (the paper's repeated off-surface movements),
  is one touch, not many; a cell passes 0.8 when it is touched again later or by another
  finger.

With ``evidence_rate = 0`` and ``visit_gap = 0`` every sample is a full measurement (the
paper). Without times (``integrate(points)``) there is neither dwell nor visits.

The update can touch the containing cell only (the paper) or, optionally, its 26
neighbours as well, each with eq. 3 at its own distance. Samples are applied one by one in
the order given (a compiled loop, occupancy_kernels.py), and the dwell and visit state is
kept between calls, so the map (once flushed) does not depend on how the stream was cut
into batches.
"""

from __future__ import annotations

import math
from copy import deepcopy
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from inhand_common.array_types import Bools, CellFloats, CellHits, FingerIds, Floats, Points, Times
from inhand_common.cell_lattice import Lattice
from inhand_common.contact_centroids import centroids
from inhand_common.log_odds import logit, probability
from inhand_mapping import occupancy_kernels as kernels
from inhand_mapping.cell_judge import CellJudge
from inhand_mapping.dwell import DwellWeights, WeightedSamples
from inhand_mapping.touch_paths import TouchPaths

__all__ = ['DISTANCES', 'TOUCH_MODELS', 'GridSpec', 'IntegrationCounts', 'OccupancyGrid', 'SensorModel',
           'logit', 'probability', 'warm_up']

DISTANCES = ('cell', 'centre')
TOUCH_MODELS = ('path', 'samples')


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
        return round(self.size / self.resolution)

    @property
    def shape(self) -> tuple[int, int, int]:
        n = self.cells_per_axis
        return (n, n, n)

    @property
    def origin(self) -> Floats:
        """Map-frame position (3,) of the outer corner of cell (0, 0, 0)."""
        return np.asarray(self.centre, dtype=float) - self.size / 2.0

    def lattice(self) -> Lattice:
        """The grid's cells as the :class:`~inhand_common.cell_lattice.Lattice` the metrics
        and the cell lookups of inhand_common take."""
        origin = self.origin
        return Lattice(self.resolution, (float(origin[0]), float(origin[1]), float(origin[2])))

    def cell_centres(self, ijk: ArrayLike) -> Points:
        """Map-frame centres (N, 3) of the cells with indices ``ijk`` (N, 3)."""
        return self.origin + (np.asarray(ijk, dtype=float) + 0.5) * self.resolution

    def _cell_coordinates(self, points: ArrayLike) -> Floats:
        """Cell indices (N, 3) of map-frame points as floats (NaN stays NaN)."""
        coordinates: Floats = np.floor((np.asarray(points, dtype=float).reshape(-1, 3)
                                        - self.origin) / self.resolution)
        return coordinates

    def cell_indices(self, points: ArrayLike) -> NDArray[np.intp]:
        """Integer cell indices (N, 3) of finite map-frame points, not checked against the
        grid's bounds (:meth:`contains` says which are inside)."""
        return self._cell_coordinates(points).astype(np.intp)

    def holds(self, ijk: ArrayLike) -> Bools:
        """Which cell indices (N, 3; integers, or floats as floored) lie in the grid."""
        axes = (np.asarray(ijk) >= 0) & (np.asarray(ijk) < self.cells_per_axis)
        inside: Bools = axes[:, 0] & axes[:, 1] & axes[:, 2]    # faster than all(axis=1)
        return inside

    def contains(self, points: ArrayLike) -> Bools:
        """Which map-frame points (N, 3) fall in a cell of the grid."""
        return self.holds(self._cell_coordinates(points))

    def on_faces(self, points: ArrayLike) -> Bools:
        """Which map-frame points (N, 3) fall in the grid's outermost layer of cells: a map
        whose occupied cells reach it may be cut off by a workspace too small."""
        ijk = self._cell_coordinates(points)
        last = self.cells_per_axis - 1
        faces: Bools = self.holds(ijk) & np.any((ijk == 0) | (ijk == last), axis=1)
        return faces


@dataclass(frozen=True)
class SensorModel:
    """Sensor model and update parameters (defaults: the paper's, and docs/mapping.md's choice)."""

    sigma: float = 0.002
    p_z_given_not_occupied: float = 0.45
    prior: float = 0.5
    clamp_min: float = 0.12
    clamp_max: float = 0.97
    neighbourhood: int = 1  # 1: containing cell (paper); 27: also the 26 neighbours
    distance_to: str = 'cell'  # eq. 3's distance: to the cell, or to its 'centre' (paper)
    evidence_rate: float = 15.0  # Hz: samples per second worth one measurement each; 0: every sample
    visit_gap: float = 3.0  # s: one finger's samples in one cell this close are one visit
    touch_model: str = 'path'  # 'path': touch_paths.py; 'samples': eq. 4 per sample
    transit_speed: float = 0.2  # m/s, path model: faster is through the air, not sliding
    speed_context: float = 0.25  # s, path model: the fastest speed within +- this counts
    pass_time: float = 0.15  # s, path model: a slow pass through a cell this long is 2 touches
    layer_factor: float = 0.4  # path model: evidence kept by the layer above the surface (1: off)
    transit_falloff: float = 6.0  # path model: evidence faster than that: (transit_speed / v)^this
    sheet_gain: float = 1.75  # path model: evidence of a cell of a flat sheet counts this often
    cell_judge: bool = True  # path model: the learned judge overrides the rules where sure

    def __post_init__(self) -> None:
        if self.neighbourhood not in (1, 27):
            raise ValueError(f'neighbourhood must be 1 or 27, not {self.neighbourhood}')
        if self.distance_to not in DISTANCES:
            raise ValueError(f'distance_to must be one of {DISTANCES}, not {self.distance_to!r}')
        if not (self.evidence_rate >= 0 and self.visit_gap >= 0):
            raise ValueError('need evidence_rate >= 0 and visit_gap >= 0')
        if self.touch_model not in TOUCH_MODELS:
            raise ValueError(f'touch_model must be one of {TOUCH_MODELS}, not {self.touch_model!r}')
        if self.touch_model == 'path' and self.neighbourhood != 1:
            raise ValueError("neighbourhood 27 is for touch_model 'samples': the path model "
                             'updates the cells the path crosses')
        if not (self.transit_speed > 0 and self.speed_context >= 0 and self.pass_time > 0):
            raise ValueError('need transit_speed > 0, speed_context >= 0 and pass_time > 0')
        if not 1.0 <= self.sheet_gain <= 4.0:
            raise ValueError(f'sheet_gain must be in [1, 4], not {self.sheet_gain}')
        if not self.transit_falloff >= 1.0:
            raise ValueError(f'transit_falloff must be at least 1, not {self.transit_falloff}')
        if not 0.0 <= self.layer_factor <= 1.0:
            raise ValueError(f'layer_factor must be in [0, 1], not {self.layer_factor}')
        if not isinstance(self.cell_judge, bool):
            raise ValueError(f'cell_judge must be true or false, not {self.cell_judge!r}')
        if not 0.0 < self.clamp_min < self.prior < self.clamp_max < 1.0:
            raise ValueError('need 0 < clamp_min < prior < clamp_max < 1')
        # sigma squared, not sigma: eq. 3 divides by it (2e-285 m passed "> 0" and its
        # square was 0 -- a damaged map file found by fuzzing)
        if not (0.0 < self.p_z_given_not_occupied < 1.0 and self.sigma > 0
                and self.sigma ** 2 > 0):
            raise ValueError(f'need 0 < P(Z|not O) < 1 and sigma > 0 (with a square above '
                             f'0), not {self.p_z_given_not_occupied} and {self.sigma}')


@dataclass
class IntegrationCounts:
    """What happened to the measurements given to the grid (totals since creation)."""

    integrated: int = 0
    outside: int = 0
    invalid: int = 0

    def __add__(self, other: IntegrationCounts) -> IntegrationCounts:
        return IntegrationCounts(self.integrated + other.integrated,
                                 self.outside + other.outside, self.invalid + other.invalid)


class OccupancyGrid:
    """Log-odds occupancy per cell, plus hit count and first-touch time per cell.

    The (n, n, n) arrays are updated in place, never replaced: the compiled kernels work on
    flat views of them made once, here (``cell_arrays``).
    """

    def __init__(self, spec: GridSpec = GridSpec(), model: SensorModel = SensorModel()):
        self.spec = spec
        self.model = model
        self.prior_log_odds = float(logit(model.prior))
        # The map read (``log_odds``) is the touch evidence with the surface layer applied
        # (surface_layer.py); the path model marks what changed, ``log_odds`` applies it.
        self._log_odds: CellFloats = np.full(spec.shape, self.prior_log_odds, dtype=np.float64)
        self.hits: CellHits = np.zeros(spec.shape, dtype=np.uint32)
        self.first_touch: CellFloats = np.full(spec.shape, np.nan, dtype=np.float64)
        # Where in each cell its hits were: the sum of their positions (map frame, m), so
        # that the surface is known to better than a cell (contact_centroids).
        self.contact_sum: Floats = np.zeros((*spec.shape, 3), dtype=np.float64)
        self._probability: CellFloats = np.full(spec.shape, float(model.prior), dtype=np.float64)
        self.earliest_touch = math.inf  # min of first_touch, kept up to date
        self.counts = IntegrationCounts()
        path_model = model.touch_model == 'path'
        self._dwell = (DwellWeights(1.0 / model.evidence_rate, spec.resolution)
                       if model.evidence_rate > 0 and not path_model else None)
        size = spec.cells_per_axis ** 3
        # What the kernels are given on every call, made once: the geometry, the model in
        # the kernel's units, and flat views of the cell arrays.
        self.geometry = kernels.GridGeometry(
            origin=spec.origin, resolution=float(spec.resolution),
            inv_res=1.0 / spec.resolution, n=spec.cells_per_axis)
        self._update_model = kernels.UpdateModel(
            half_inv_var=spec.resolution ** 2 / (2.0 * model.sigma ** 2),
            log_c=math.log(model.p_z_given_not_occupied),
            reach=1 if model.neighbourhood == 27 else 0,
            to_cell=model.distance_to == 'cell',
            visit_gap=float(model.visit_gap),
            l_min=float(logit(model.clamp_min)), l_max=float(logit(model.clamp_max)))
        self.cell_arrays = kernels.CellArrays(
            log_odds=self._log_odds.reshape(-1), probability=self._probability.reshape(-1),
            hits=self.hits.reshape(-1), first_touch=self.first_touch.reshape(-1),
            contact_sum=self.contact_sum.reshape(-1), changed_mark=np.zeros(size, dtype=np.bool_))
        # Per finger (rows) and cell: see kernels.Visits. Rows are added as fingers appear.
        self._visit_last: Floats = np.empty((0, size))
        self._visit_weight: Floats = np.empty((0, size))
        self._visits = kernels.Visits(self._visit_last.reshape(-1), self._visit_weight.reshape(-1))
        self._paths = TouchPaths(
            self.geometry, self.cell_arrays, p_z_given_not_occupied=model.p_z_given_not_occupied,
            prior=model.prior, clamp_min=model.clamp_min, clamp_max=model.clamp_max,
            transit_speed=model.transit_speed, transit_falloff=model.transit_falloff,
            speed_context=model.speed_context,
            pass_time=model.pass_time, visit_gap=model.visit_gap,
            layer_factor=model.layer_factor, sheet_gain=model.sheet_gain) if path_model else None
        # The cell judge's verdicts, over the surface layer's map (cell_judge.py).
        self._judge = (CellJudge(spec.shape, spec.origin, spec.resolution)
                       if path_model and model.cell_judge else None)

    @property
    def log_odds(self) -> CellFloats:
        """Log-odds of every cell (n, n, n), up to date: the path model's surface layer is
        applied here, to the cells around what changed since the last read, so a node pays
        for it at the rate it reads the map. Writing into it sets the map (loading,
        fusion's view), taken as it is."""
        self.apply_layer()
        return self._log_odds

    @property
    def touch_evidence(self) -> CellFloats | None:
        """The path model's evidence per cell (n, n, n), in touches, before the surface
        layer (read-only); None for the samples model."""
        if self._paths is None:
            return None
        view = self._paths.evidence.reshape(self.spec.shape).view()
        view.flags.writeable = False
        return view

    def restore_touch_evidence(self, evidence: ArrayLike,
                               judged: tuple[ArrayLike, ArrayLike] | None = None) -> None:
        """Take the path model's evidence of a saved map (``touch_evidence``), whose
        log-odds this grid holds already: touches go on from it exactly (without it they go
        on from the evidence the log-odds give). ``judged``: the map's ``judged`` as saved
        (without it, a cell the judge overrode keeps that value as the layer's until the
        layer recomputes it). Nothing for the samples model."""
        if self._paths is None:
            return
        if self._judge is not None and judged is not None:
            self._judge.resume(*judged)
            # the layer's neighbours lend their support as the layer showed them, not as
            # the judge did (TouchPaths.follow)
            shown = self._log_odds.copy()
            shown.reshape(-1)[self._judge.overridden] = self._judge.rules
            self._paths.follow(shown)
        self._paths.restore(np.asarray(evidence, dtype=float))

    @property
    def judged(self) -> tuple[NDArray[np.intp], Floats] | None:
        """(flat indices of the cells whose probability the cell judge set, the surface
        layer's log-odds it replaced), or None without the judge (cell_judge.py)."""
        if self._judge is None:
            return None
        self.apply_layer()
        return self._judge.overridden, self._judge.rules

    def layer_overrides(self) -> tuple[NDArray[np.intp], Floats]:
        """(flat indices, ascending; the surface layer's probability there) of the cells
        whose probability the cell judge set (cell_judge.py; none without the judge). A cell
        the judge raised over the occupancy threshold from under it is one it rescued: most
        are a second cell across a thinly touched surface, which the shape's parts leave out
        (docs/shape.md, "With the touch map's cell judge")."""
        judged = self.judged
        if judged is None:
            return np.empty(0, dtype=np.intp), np.empty(0)
        cells, rules = judged
        order = np.argsort(cells, kind='stable')
        return cells[order], probability(rules[order])

    def layer_probabilities(self, mask: Bools | None = None, threshold: float | None = None
                            ) -> Floats:
        """(M,) the surface layer's probability of each cell of ``cells(mask, threshold)``
        (same order): the map's own but where the cell judge overrode it
        (:meth:`layer_overrides`)."""
        layer = self.probabilities().reshape(-1).copy()
        cells, rules = self.layer_overrides()
        layer[cells] = rules
        picked: Floats = layer.reshape(self.log_odds.shape)[self._selected(mask, threshold)]
        return picked

    def apply_layer(self) -> None:
        """Bring the cells around what changed since the last read up to date with the path
        model's surface layer (surface_layer.py), and then with the cell judge
        (cell_judge.py) where the model has it. ``log_odds`` and ``probabilities()`` do
        this; code that reads ``cell_arrays`` directly calls it first."""
        if self._paths is None:
            return
        counts = self._paths.counts
        if self._judge is None or not counts.n_dirty[0]:
            self._paths.apply_layer()
            return
        # The judge judges the layer's map: its overrides are taken back first, the layer
        # brought up to date, then the cells near what changed judged again.
        changed = counts.dirty[:counts.n_dirty[0]].copy()
        flat_log_odds, flat_probability = self.cell_arrays.log_odds, self.cell_arrays.probability
        self._judge.undo(flat_log_odds, flat_probability)
        self._paths.apply_layer()
        self._judge.update(self._paths.evidence, self.hits, self.contact_sum, changed)
        self._judge.apply(flat_log_odds, flat_probability,
                          (self.model.clamp_min, self.model.clamp_max))

    def _forget_judged(self) -> None:
        """The log-odds were set from outside (a map loaded or shown): they are the map."""
        if self._judge is not None:
            self._judge.forget()

    # ------------------------------------------------------------------ update
    def integrate(self, points: ArrayLike, times: ArrayLike | None = None,
                  fingers: ArrayLike | None = None) -> IntegrationCounts:
        """Apply eq. 4 for every point (map frame, metres), in order.

        ``times`` (seconds, one per point) feed the first-touch time, the dwell weights and
        the visits; ``fingers`` (non-negative integers, one per point; default all 0) say
        whose fingertip each point is. Points outside the workspace are counted and
        ignored; NaN or infinite ones are rejected and counted.

        A timed sample's weight depends on where its finger is one period later (dwell.py),
        so each finger's newest samples (up to two periods) are held back and applied by a
        later call, or by ``flush()`` at the end of a stream; ``pending`` says how many.
        Returns the counts of the samples this call applied.
        """
        positions: Points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        count = positions.shape[0]
        stamps: Times | None = None
        if times is not None:
            stamps = np.ascontiguousarray(times, dtype=np.float64).reshape(-1)
            if stamps.shape[0] != count:
                raise ValueError(f'{count} points but {stamps.shape[0]} times')
        finger_ids = self._finger_ids(fingers, count)
        if self._paths is not None:
            return self._integrate_path(positions, stamps, finger_ids)
        if stamps is None:
            # No times, no dwell: applied at once, after what is held back (order kept).
            held = self.flush()
            return held + self._apply(WeightedSamples(positions, np.empty(0), finger_ids,
                                                      np.ones(count)), has_times=False)
        if self._dwell is None:
            return self._apply(WeightedSamples(positions, stamps, finger_ids, np.ones(count)))
        return self._apply(self._dwell.push(positions, stamps, finger_ids))

    def flush(self) -> IntegrationCounts:
        """Apply the samples held back for their dwell weights, or walk the paths to their
        ends (the end of a stream: a bag replayed, a map about to be saved). Returns the
        counts of the samples applied (the path model counted its samples when given)."""
        if self._paths is not None:
            self._touched_at(self._paths.flush())
            return IntegrationCounts()
        if self._dwell is None:
            return IntegrationCounts()
        return self._apply(self._dwell.flush())

    def settled_copy(self) -> OccupancyGrid:
        """A copy of this grid with what it holds back applied, as ``flush`` would; this
        grid is left as it is. What a save or a pause in the stream shows: flushing the
        live grid instead ends every finger's track (or dwell look-ahead) early, and the
        samples after it start new ones, so a map saved every 10 s of a 22 s session
        differed from the unsaved one in 132 cells (7 of them occupied or not)."""
        settled = OccupancyGrid(self.spec, self.model)
        for name in ('log_odds', 'hits', 'first_touch', 'contact_sum', '_probability'):
            getattr(settled, name)[...] = getattr(self, name)
        settled.earliest_touch, settled.counts = self.earliest_touch, self.counts
        if self._paths is not None:
            assert settled._paths is not None
            settled._paths.take_state(self._paths)
            if self._judge is not None:
                settled._judge = self._judge.copy()
        elif self._dwell is not None:
            settled._visit_state(self._visit_last.shape[0])
            settled._visit_last[...] = self._visit_last
            settled._visit_weight[...] = self._visit_weight
            settled._dwell = deepcopy(self._dwell)   # small: two periods of samples
        settled.flush()
        return settled

    @property
    def pending(self) -> int:
        """Samples given to ``integrate`` and not applied yet (see there)."""
        if self._paths is not None:
            return self._paths.pending
        return 0 if self._dwell is None else self._dwell.pending

    def held_points(self) -> Points:
        """(M, 3) positions given to ``integrate`` whose evidence the path model has not
        applied yet (empty for the samples model, whose hold is one sample per finger)."""
        if self._paths is None:
            return np.empty((0, 3))
        return self._paths.held_points()

    def _integrate_path(self, positions: Points, stamps: Times | None,
                        finger_ids: FingerIds) -> IntegrationCounts:
        """The path model (touch_paths.py): samples counted when given, paths walked as
        their speeds settle. Untimed points are one touch each, after what is pending."""
        assert self._paths is not None
        if stamps is None:
            self.flush()
            integrated, outside, invalid = self._paths.add_points(positions)
        else:
            integrated, outside, invalid, earliest = self._paths.push(positions, stamps,
                                                                      finger_ids)
            self._touched_at(earliest)
        taken = IntegrationCounts(integrated=int(integrated), outside=int(outside),
                                  invalid=int(invalid))
        self.counts = self.counts + taken
        return taken

    def _touched_at(self, earliest: float) -> None:
        self.earliest_touch = min(self.earliest_touch, float(earliest))

    def _apply(self, samples: WeightedSamples, has_times: bool = True) -> IntegrationCounts:
        count = samples.points.shape[0]   # not samples.count: without times, times is empty
        # Visits need times; without them the kernel never reads the (then empty) state.
        visits = self._visit_state(int(samples.fingers.max()) + 1 if has_times and count else 0)
        batch = kernels.SampleBatch(
            points=np.ascontiguousarray(samples.points), times=np.ascontiguousarray(samples.times),
            has_times=has_times, fingers=np.ascontiguousarray(samples.fingers, dtype=np.int64),
            weights=np.ascontiguousarray(samples.weights))
        # Room for every cell whose neighbourhood changes (at most one per sample).
        changed = np.empty(min(count, self.log_odds.size), dtype=np.int64)
        integrated, outside, invalid, earliest = kernels.integrate(
            batch, self.geometry, self._update_model, self.cell_arrays, visits, changed)
        self.earliest_touch = min(self.earliest_touch, float(earliest))
        applied = IntegrationCounts(integrated=int(integrated), outside=int(outside),
                                    invalid=int(invalid))
        self.counts = self.counts + applied
        return applied

    @staticmethod
    def _finger_ids(fingers: ArrayLike | None, count: int) -> FingerIds:
        if fingers is None:
            return np.zeros(count, dtype=np.int64)
        ids = np.asarray(fingers).reshape(-1)
        if ids.shape[0] != count:
            raise ValueError(f'{count} points but {ids.shape[0]} finger ids')
        if count and (not np.issubdtype(ids.dtype, np.integer) or ids.min() < 0):
            raise ValueError('finger ids must be non-negative integers')
        return np.ascontiguousarray(ids, dtype=np.int64)

    def _visit_state(self, fingers: int) -> kernels.Visits:
        """Per finger and cell: when the finger was last there, and how much its current
        visit has given. Grown when a new finger id appears."""
        have = self._visit_last.shape[0]
        if fingers > have:
            size = self.spec.cells_per_axis ** 3
            self._visit_last = np.concatenate(
                [self._visit_last, np.full((fingers - have, size), -np.inf)])
            self._visit_weight = np.concatenate(
                [self._visit_weight, np.zeros((fingers - have, size))])
            self._visits = kernels.Visits(self._visit_last.reshape(-1),
                                          self._visit_weight.reshape(-1))
        return self._visits

    def reset(self) -> None:
        self._log_odds.fill(self.prior_log_odds)
        self._probability.fill(self.model.prior)
        self.earliest_touch = math.inf
        self.hits.fill(0)
        self.first_touch.fill(np.nan)
        self.contact_sum.fill(0.0)
        self.counts = IntegrationCounts()
        self._visit_last.fill(-np.inf)
        self._visit_weight.fill(0.0)
        if self._dwell is not None:
            self._dwell.reset()   # the samples held back go too
        if self._paths is not None:
            self._paths.reset()

    # ------------------------------------------------------------------ queries
    def probabilities(self) -> CellFloats:
        """Occupancy probability of every cell (read-only; kept current by each update)."""
        self.apply_layer()
        view = self._probability.view()
        view.flags.writeable = False
        return view

    def show(self, log_odds: ArrayLike, source: OccupancyGrid,
             layer: tuple[ArrayLike, ArrayLike] | None = None) -> None:
        """Become a view of another map of the same grid: ``log_odds`` (a global map fused
        from ``source`` and another sensor) with ``source``'s hit counts and first touches,
        copied in place (the kernels keep their views of these arrays). ``layer``: (flat
        cells, log-odds) the view without the cell judge's verdicts at the cells ``source``'s
        judge overrode (:meth:`hold_layer`)."""
        if source.spec != self.spec:
            raise ValueError(f'grids differ: {source.spec} and {self.spec}')
        self.log_odds[...] = log_odds
        self.hits[...] = source.hits
        self.first_touch[...] = source.first_touch
        self.contact_sum[...] = source.contact_sum
        self.counts = source.counts
        self.refresh()
        if layer is not None:
            self.hold_layer(*layer)

    def hold_layer(self, cells: ArrayLike, log_odds: ArrayLike) -> None:
        """This map, a view set from outside (a fused map, a fused map's file), differs
        from its surface layer's at ``cells`` (flat), where the layer gave ``log_odds``:
        what :meth:`layer_overrides` says. Nothing without the judge."""
        if self._judge is not None:
            self._judge.resume(cells, log_odds)

    def refresh(self) -> None:
        """Recompute what is derived from the arrays after they were set directly (loading)."""
        self._forget_judged()
        self._probability[...] = probability(self.log_odds)
        if self._paths is not None:
            self._paths.follow(self.log_odds)
        finite = self.first_touch[np.isfinite(self.first_touch)]
        self.earliest_touch = float(finite.min()) if finite.size else math.inf

    def touched_mask(self) -> Bools:
        """Cells any measurement has updated (their log-odds left the prior, or were hit)."""
        touched: Bools = (self.log_odds != self.prior_log_odds) | (self.hits > 0)
        return touched

    def cells(self, mask: Bools | None = None, threshold: float | None = None
              ) -> tuple[Points, Floats, CellHits, Times]:
        """(centres (M, 3), probabilities (M,), hits (M,), first touch (M,)) of the cells in
        ``mask`` (default: touched) and, if given, with probability above ``threshold``."""
        mask = self._selected(mask, threshold)
        return (self.spec.cell_centres(np.argwhere(mask)), self.probabilities()[mask],
                self.hits[mask], self.first_touch[mask])

    def contact_centroids(self, mask: Bools | None = None, threshold: float | None = None
                          ) -> Points:
        """(M, 3): where in each cell of ``cells(mask, threshold)`` (same order) its hits
        were, their mean position; the cell's centre where it has none
        (inhand_common.contact_centroids)."""
        mask = self._selected(mask, threshold)
        return centroids(self.spec.cell_centres(np.argwhere(mask)), self.contact_sum[mask],
                         self.hits[mask])

    def _selected(self, mask: Bools | None, threshold: float | None) -> Bools:
        if mask is None:
            mask = self.touched_mask()
        if threshold is not None:
            mask = mask & (self.probabilities() > threshold)
        return mask


def warm_up(model: SensorModel, resolution: float) -> None:
    """Run the compiled kernels of ``model`` once, on a scratch grid of 8^3 cells.

    numba loads a kernel from its cache (or compiles it) on its first call: 0.35-0.56 s for
    the path model's. A node pays that at start rather than on the first touch, which a
    live view showed as the slowest cells of a session. The kernels' types do not depend on
    the grid's size, so the scratch grid loads the same machine code as the real one.
    """
    grid = OccupancyGrid(GridSpec(size=8 * resolution, resolution=resolution), model)
    count = 120                                     # 0.5 s at 240 Hz, 3 fingers: past the
    times = np.arange(count) / 240.0                # path model's look-ahead
    stroke = np.linspace(-2.0, 2.0, count)[:, None] * resolution * np.array([[1.0, 0.5, 0.0]])
    grid.integrate(stroke, times, np.arange(count) % 3)
    grid.held_points()
    grid.probabilities()                            # the surface layer's and the judge's
    grid.integrate(stroke[:2])                      # untimed points take their own kernel
    grid.flush()
    grid.probabilities()                            # the judge around what changed
