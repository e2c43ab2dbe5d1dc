"""The completed surface and how sure it is: a sparse Gaussian process implicit surface.

A touch map knows the surface where fingers went and nothing elsewhere. To say what the rest
probably is, and how unsure that guess is, the surface is the zero level of a function ``f``
(about the signed distance to the surface, m, negative inside) with a Gaussian process prior
(Dragiev et al., ICRA 2011; Yi et al., IROS 2016)::

    f(x) = m(x) + g(x),    g ~ GP(0, k),    k = s^2 Matern-3/2(|x - x'| / l)

* **Prior mean** ``m``: the first-order distance to a closed shape around the occupied cells,
  so that where no finger went the surface falls back to the simplest shape that holds what
  was touched: the ellipsoid on their principal axes spanning their extent (default), or
  their robust superquadric fit (superquadric.py; a touched cap gives its whole sphere). Such
  a shape can reach far past the object: a point farther from every touched cell than
  :attr:`PredictionSettings.prior_reach` plus its depth inside the shape counts as outside.
* **Observations**: every occupied cell is on the surface (``f = 0``); the point
  :data:`OUTSIDE_OFFSET` cells out along its normal is that far outside, the point
  :data:`INSIDE_OFFSET` in is inside. Normals are surface_mesh.py's, turned towards the free
  space next to a cell where there is some on one side only; a cell with free space on both
  sides is a sheet (a thin wall or plate) and gets an outside point on each side. Free
  cells (visited by a finger, probability at most :data:`FREE_PROBABILITY`, more than
  :data:`FREE_GAP` cells from an occupied one) that the prior puts inside or within
  :data:`FREE_REACH` of its surface are outside, by at most their distance to the nearest
  occupied cell (observed as that distance, with a noise of half of it): what a touch map has
  that a point cloud has not. What a camera saw (``predict_surface --bag``: the object's
  stereo points) adds cells where no finger went: surface where its points are, free space
  in front of them along the rays (:func:`seen_cells`).
* **Sparse**: the deterministic training conditional (Seeger et al. 2003; Quinonero-Candela
  and Rasmussen 2005) on at most :data:`MAX_INDUCING` inducing points (the observations
  thinned on a grid). Its cost is linear in the observations, and far from every inducing
  point its variance is the prior's: it never claims to know the surface where nothing was
  measured. The kernel between inducing points and observations (and the mean's) is left
  out beyond :data:`KERNEL_REACH` length scales, where it is below 1 % of its peak: a few
  inducing points per observation instead of all of them.

The mean is evaluated on a grid of :attr:`PredictionSettings.grid_step` around the object.
Where the map has evidence (within surface_mesh's :data:`~inhand_shape.surface_mesh.REACH` of
an occupied cell) the map's own surface decides (its tangent-plane distance); elsewhere
nothing in front of the touched surface is inside (the process may close the surface behind
what was touched, never bridge a gap the fingers passed over). Its zero level is meshed by
marching cubes (scikit-image), pieces facing inward (hollows) are dropped, and the standard
deviation of ``f`` is evaluated at every vertex. Because ``f`` is about a distance (slope 1),
that standard deviation is in metres: how far the true surface may be from the predicted one.
The process's own cannot exceed ``signal_std``; where only the prior shape stands in for the
object it may be off by much more, so the reported one adds, in quadrature,
:attr:`PredictionSettings.extrapolation` times the distance beyond one length scale from the
nearest touched cell (the next touch's gain uses the process's own: a touch reduces that).
The *completed surface* is the part of that mesh within
:attr:`PredictionSettings.completed_reach` of the surface cells (:meth:`PredictedSurface.completed`):
the touched surface with the gaps between strokes bridged and its edges carried on a little;
beyond, the uncertainty says where to touch next. The defaults and how well they are
calibrated: docs/exploration.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import cho_factor, cho_solve  # type: ignore[import-untyped]
from scipy.sparse import coo_matrix, csr_matrix  # type: ignore[import-untyped]
from scipy.sparse.csgraph import connected_components  # type: ignore[import-untyped]
from scipy.spatial import cKDTree  # type: ignore[import-untyped]

from inhand_common.array_types import Floats, Points, Vector3
from inhand_common.parameters import ParamSpec, validate
from inhand_shape.superquadric import Superquadric, fit_superquadric
from inhand_shape.surface_mesh import REACH, nearest_cells, oriented_normals, tangent_plane_distance

__all__ = ['FREE_PROBABILITY', 'PREDICTION_PARAMETERS', 'SEEN_FREE', 'SEEN_POINTS', 'PredictedSurface',
           'PredictionSettings', 'SurfacePrior', 'predict_map_surface', 'predict_surface',
           'seen_cells', 'thinned']

OUTSIDE_OFFSET = 2.0      # cells: the outside observation of each occupied cell, along its normal
INSIDE_OFFSET = 1.0       # cells: the inside one (short: a wall may be thin)
FREE_PROBABILITY = 0.6    # cells at most this likely occupied, and visited, are free space
FREE_GAP = 1.5            # cells: free cells nearer than this to an occupied one are left out
SIDE_REACH = 3.0          # cells: the free space that says which side of a cell is outside
MIN_SIDE_CELLS = 2        # free cells on a side that make it outside
SIDE_CONE = 0.85          # ... within this cosine of the normal's axis
FREE_REACH = 0.02         # m: free cells the prior puts farther outside than this say nothing new
MAX_INDUCING = 400        # inducing points of the sparse process
MAX_OBSERVATIONS = 6000   # observations used (thinned on a grid beyond)
PRIOR_MARGIN = 1.0        # cells added to the ellipsoid's half extents
PRIOR_FIT_CELLS = 300     # cells the prior's superquadric is fitted to (thinned on a grid)
MAX_GRID_POINTS = 200_000  # prediction grid points (the step grows beyond)
KERNEL_REACH = 4.0        # length scales: farther inducing points are left out of the mean and fit
KERNEL_NEIGHBOURS = 32    # ... and all but the nearest of them out of the mean
_CHUNK = 20000            # query points per kernel block


@dataclass(frozen=True)
class PredictionSettings:
    """The process's hyper-parameters and the prediction grid (PREDICTION_PARAMETERS says
    what each means; the defaults are chosen in docs/exploration.md)."""

    length_scale: float = 0.01      # m
    signal_std: float = 0.01        # m
    noise_std: float = 0.5          # cells
    grid_step: float = 2.0          # cells
    margin: float = 0.01            # m around the prior shape and the cells
    prior: str = 'ellipsoid'        # or 'superquadric'
    prior_reach: float = 0.02       # m: how far past the touched cells the prior may reach
    extrapolation: float = 0.75     # std added per metre beyond a length scale from the cells
    completed_reach: float = 0.0075  # m: how far past the surface cells the completed surface goes

    def __post_init__(self) -> None:
        # refused as a node refuses a parameter: by name, with the allowed values
        validate(PREDICTION_PARAMETERS, {f.name: getattr(self, f.name) for f in fields(self)})


PREDICTION_PARAMETERS = (
    ParamSpec('length_scale', PredictionSettings.length_scale, 'Gaussian process length scale '
              '(m): how far a touch informs the predicted surface', minimum=0.005, maximum=0.2),
    ParamSpec('signal_std', PredictionSettings.signal_std, 'Prior standard deviation of the '
              'surface from the prior shape (m): the uncertainty where nothing was touched',
              minimum=0.001, maximum=0.1),
    ParamSpec('noise_std', PredictionSettings.noise_std, 'Standard deviation of a contact '
              'observation, in cells', minimum=0.05, maximum=5.0),
    ParamSpec('grid_step', PredictionSettings.grid_step, 'Spacing of the prediction grid, in '
              'cells of the map', minimum=1.0, maximum=8.0),
    ParamSpec('margin', PredictionSettings.margin, 'Space around the object the prediction '
              'covers (m)', minimum=0.0, maximum=0.2),
    ParamSpec('prior_reach', PredictionSettings.prior_reach, 'How far past the touched cells the '
              'prior shape may reach (m): a point farther from them than this plus its depth '
              'inside the shape is outside',
              minimum=0.005, maximum=0.5),
    ParamSpec('extrapolation', PredictionSettings.extrapolation, 'Standard deviation added to the '
              'predicted surface per metre of its distance from the nearest touched cell beyond one '
              'length scale: how far the prior shape may be off where it stands in for the object',
              minimum=0.0, maximum=5.0),
    ParamSpec('completed_reach', PredictionSettings.completed_reach, 'How far the completed '
              'surface reaches past the touched (and seen) cells (m): the part of the predicted '
              'surface whose triangles lie this near them, gaps between them bridged',
              minimum=0.001, maximum=1.0),
    ParamSpec('prior', PredictionSettings.prior, 'Shape the surface falls back to where nothing '
              'was touched: the ellipsoid on the cells\' principal axes, or their robust '
              'superquadric fit', choices=('ellipsoid', 'superquadric')),
)
assert {spec.name for spec in PREDICTION_PARAMETERS} == {f.name for f in fields(PredictionSettings)}


@dataclass(frozen=True)
class SurfacePrior:
    """The prior mean's shape: a superquadric (an ellipsoid when both exponents are 1)."""

    shape: Superquadric

    @classmethod
    def ellipsoid_around(cls, points: Points, margin: float) -> SurfacePrior:
        """The ellipsoid on the points' principal axes spanning their extent (plus ``margin``)."""
        centre = points.mean(axis=0)
        _, vectors = np.linalg.eigh(np.cov((points - centre).T) + 1e-12 * np.eye(3))
        local = (points - centre) @ vectors
        low, high = local.min(axis=0), local.max(axis=0)
        return cls(Superquadric((high - low) / 2 + margin, (1.0, 1.0), vectors,
                                centre + vectors @ ((low + high) / 2)))

    @classmethod
    def fitted(cls, points: Points, weights: Floats, resolution: float) -> SurfacePrior:
        """The robust superquadric fit of the points (superquadric.py): it closes a shape
        from the part of it that was touched (a cap gives its sphere). Free to reach past
        the cells (``reach`` 0): predicting the untouched side is what a prior is for, and
        the process's uncertainty, not the fit, says how far to trust it there."""
        keep = thinned(points, resolution, PRIOR_FIT_CELLS)
        return cls(fit_superquadric(points[keep], weights[keep], resolution=resolution,
                                    reach=0.0).superquadric)

    def distance(self, points: Points) -> Floats:
        """First-order (Taubin) signed distance to the shape, m (negative inside)."""
        inside = self.shape.inside_outside(points) < 1.0
        return np.where(inside, -1.0, 1.0) * self.shape.surface_distance(points)

    def bounds(self) -> tuple[Vector3, Vector3]:
        """Axis-aligned box around the shape: the ellipsoid's own when both exponents are at
        least 1 (such a shape lies inside its ellipsoid), else that of its rotated box (a
        turned ellipsoid's rotated box reaches up to sqrt(3) times as far: a grid around it
        would be up to five times larger)."""
        rotation, size = self.shape.rotation, np.asarray(self.shape.size)
        if min(self.shape.shape) >= 1.0:
            half = np.sqrt((rotation ** 2) @ size ** 2)
        else:
            half = np.abs(rotation) @ size
        return self.shape.centre - half, self.shape.centre + half


def _matern_of(distance: Floats, settings: PredictionSettings) -> Floats:
    """The kernel at the distances ``distance`` (m). In place after the first step: the
    kernel matrices are the process's largest arrays, and each step is then one pass over
    memory instead of a new temporary."""
    r = np.multiply(distance, math.sqrt(3.0) / settings.length_scale, dtype=np.float64)
    decay = np.negative(r)
    np.exp(decay, out=decay)
    r += 1.0
    r *= decay
    r *= settings.signal_std ** 2
    return r


def _matern(a: Points, b: Points, settings: PredictionSettings) -> Floats:
    """The kernel between every point of ``a`` (rows) and of ``b`` (columns)."""
    squared = a @ b.T
    squared *= -2.0
    squared += (a * a).sum(axis=1)[:, None]
    squared += (b * b).sum(axis=1)[None, :]
    np.maximum(squared, 0.0, out=squared)
    return _matern_of(np.sqrt(squared, out=squared), settings)


def thinned(points: Points, spacing: float, limit: int) -> NDArray[np.intp]:
    """Indices of one point per grid cell of ``spacing`` (widened until at most ``limit``)."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.intp)
    while True:
        keys = np.floor(points / spacing).astype(np.int64)
        keys -= keys.min(axis=0)
        # one integer per grid cell: a 1-D unique is several times faster than one of rows
        _, first = np.unique(np.ravel_multi_index(keys.T, tuple(keys.max(axis=0) + 1)),
                             return_index=True)
        if len(first) <= limit:
            return np.sort(first)
        spacing *= 1.25


@dataclass(frozen=True, eq=False)
class _Observations:
    points: Points
    values: Floats
    noise: Floats      # standard deviation of each, m
    normals: Floats    # the occupied cells' oriented normals
    sheet: NDArray[np.bool_]   # the occupied cells with free space on both sides


def _sides(cells: Points, normals: Floats, free: Points, resolution: float, tree: cKDTree
           ) -> tuple[Floats, NDArray[np.bool_]]:
    """The normals turned towards the free space near each cell where there is some on one
    side only, and which cells have free space on both sides (a sheet: a thin wall or plate,
    outside on both faces). Free space decides where it is known; the normals' orientation
    from their neighbours (surface_mesh.py) elsewhere."""
    sheet = np.zeros(len(cells), dtype=bool)
    if len(free) == 0:
        return normals, sheet
    pairs = tree.sparse_distance_matrix(cKDTree(free), SIDE_REACH * resolution, output_type='ndarray')
    cell = pairs['i'].astype(np.intp)
    offset = free[pairs['j']] - cells[cell]
    along = np.einsum('ij,ij->i', normals[cell], offset)
    # only free space along the normal says which side is out (beside a convex edge, air
    # lies below the face's plane)
    axial = np.abs(along) >= SIDE_CONE * np.linalg.norm(offset, axis=1)
    front = np.bincount(cell[axial & (along > 0)], minlength=len(cells))
    back = np.bincount(cell[axial & (along < 0)], minlength=len(cells))
    sheet = (front >= MIN_SIDE_CELLS) & (back >= MIN_SIDE_CELLS)
    flip = ~sheet & (back > front)
    return normals * np.where(flip, -1.0, 1.0)[:, None], sheet


def _observations(cells: Points, free: Points, resolution: float, prior: SurfacePrior,
                  settings: PredictionSettings, tree: cKDTree) -> _Observations:
    """The observations of f (module doc); ``tree``: a KD-tree of ``cells``."""
    noise = settings.noise_std * resolution
    if len(free):
        nearest, _ = tree.query(free, workers=-1)
        # next to the touched surface a barely touched cell may be surface too
        keep = nearest > FREE_GAP * resolution
        free, nearest = free[keep], nearest[keep]
    normals, sheet = _sides(cells, oriented_normals(cells, resolution), free, resolution, tree)
    offset = OUTSIDE_OFFSET * resolution
    inside = INSIDE_OFFSET * resolution
    solid = ~sheet
    points = [cells, cells + offset * normals, cells[solid] - inside * normals[solid],
              cells[sheet] - offset * normals[sheet]]
    values = [np.zeros(len(cells)), np.full(len(cells), offset), np.full(int(solid.sum()), -inside),
              np.full(int(sheet.sum()), offset)]
    sigmas = [np.full(len(v), noise) for v in values]
    if len(free):
        # free cells the prior already puts well outside say nothing new
        near_prior = prior.distance(free) < FREE_REACH
        bound = np.minimum(nearest[near_prior], FREE_REACH)
        points.append(free[near_prior])
        values.append(bound)
        sigmas.append(np.maximum(noise, bound / 2))
    obs = _Observations(np.concatenate(points), np.concatenate(values), np.concatenate(sigmas),
                        normals, sheet)
    if len(obs.points) > MAX_OBSERVATIONS:
        keep = thinned(obs.points, resolution, MAX_OBSERVATIONS)
        obs = _Observations(obs.points[keep], obs.values[keep], obs.noise[keep], normals, sheet)
    return obs


class _PriorMean:
    """The prior mean m: the prior shape's distance, but a point farther from every touched
    cell than ``prior_reach`` plus its depth inside the shape counts as outside, by that
    excess. A shape fitted to part of an object may reach far past it: there its surface is
    pulled back to within about the reach of what was touched. Deep inside (as deep as it is
    far from the cells, like the middle of a touched cap's sphere) stays inside."""

    def __init__(self, prior: SurfacePrior, cells: Points, reach: float, tree: cKDTree | None = None):
        self.prior = prior
        self.tree = cKDTree(cells) if tree is None else tree
        self.reach = reach

    def __call__(self, points: Points, nearest: Floats | None = None) -> Floats:
        """m at ``points``; ``nearest``: their distances to the nearest cell, when known."""
        if nearest is None:
            nearest, _ = self.tree.query(points, workers=-1)
        shape = self.prior.distance(points)
        excess = np.asarray(nearest) - self.reach
        return np.where(excess > -shape, np.maximum(shape, excess), shape)


def _without_cavities(vertices: Points, faces: NDArray[np.int64]
                      ) -> tuple[Points, NDArray[np.int64]]:
    """The mesh's connected pieces that enclose a solid (positive signed volume): a piece
    facing inwards is a hollow inside the object, which touch cannot know of."""
    if len(faces) == 0:
        return vertices, faces
    rows = np.repeat(np.arange(len(faces)), 3)
    graph = coo_matrix((np.ones(len(rows)), (rows, faces.ravel())),
                       shape=(len(faces), len(vertices))).tocsr()
    _, label = connected_components(graph @ graph.T, directed=False)
    t = vertices[faces]
    volume = np.einsum('ij,ij->i', t[:, 0], np.cross(t[:, 1], t[:, 2])) / 6.0
    solid = np.bincount(label, volume) > 0
    used, kept = _compacted(faces[solid[label]])
    return vertices[used], kept


def _compacted(faces: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """A subset of a mesh's ``faces`` (F, 3) without the vertices they leave unused: the
    vertices kept (indices into the old ones, ascending) and the faces renumbered on them."""
    used, renumbered = np.unique(faces, return_inverse=True)
    return used, renumbered.reshape(-1, 3).astype(np.int64)


class _SparseProcess:
    """The DTC posterior of g given the observations (module doc)."""

    def __init__(self, obs: _Observations, prior: _PriorMean, settings: PredictionSettings,
                 resolution: float):
        self.prior = prior
        self.settings = settings
        self.inducing = obs.points[thinned(obs.points, resolution, MAX_INDUCING)]
        self._tree = cKDTree(self.inducing)
        m = len(self.inducing)
        kzz = _matern(self.inducing, self.inducing, settings) + 1e-8 * settings.signal_std ** 2 * np.eye(m)
        # the inducing points' kernel with the observations within KERNEL_REACH length scales
        # (as in the mean): a few per observation, where the dense matrix is mostly below 1 %
        # of the peak and was most of the fit's time
        pairs = self._tree.sparse_distance_matrix(cKDTree(obs.points), KERNEL_REACH * settings.length_scale,
                                                  output_type='ndarray')
        kzx = csr_matrix((_matern_of(pairs['v'], settings) / obs.noise[pairs['j']], (pairs['i'], pairs['j'])),
                         shape=(m, len(obs.points)))
        residual = (obs.values - prior(obs.points)) / obs.noise
        sigma = cho_factor(kzz + (kzx @ kzx.T).toarray(), lower=True)
        self.weights = cho_solve(sigma, kzx @ residual)
        # the posterior covariance is k(a, b) - k_a^T (Kzz^-1 - Sigma^-1) k_b: the difference
        # formed once makes every later variance one matrix product instead of two triangular
        # solves (the same to 1e-16 m on the benchmark's maps)
        identity = np.eye(m)
        reduction = cho_solve(cho_factor(kzz, lower=True), identity) - cho_solve(sigma, identity)
        self._reduction = (reduction + reduction.T) / 2.0

    def mean(self, points: Points, nearest_cell: Floats | None = None) -> Floats:
        """The posterior mean of f: the prior mean plus the kernel-weighted inducing points
        within :data:`KERNEL_REACH` length scales (the kernel is below 1 % of its peak
        beyond), at most the :data:`KERNEL_NEIGHBOURS` nearest of them (on the tuning maps of
        docs/exploration.md all of them gave completed F 0.738 against 0.744). ``nearest_cell``:
        the points' distances to the nearest occupied cell, when the caller has them."""
        reach = KERNEL_REACH * self.settings.length_scale
        # the close pairs only: a grid point has a few inducing points within reach, and
        # fixed-size neighbour lists would be mostly padding
        pairs = self._tree.sparse_distance_matrix(cKDTree(points), reach, output_type='ndarray')
        crowded = np.bincount(pairs['j'], minlength=len(points))[pairs['j']] > KERNEL_NEIGHBOURS
        if crowded.any():
            # where more are in reach (dense inducing points on a small object): the nearest
            # KERNEL_NEIGHBOURS only, sorted for those points alone
            many = pairs[crowded][np.lexsort((pairs['v'][crowded], pairs['j'][crowded]))]
            rank = np.arange(len(many)) - np.searchsorted(many['j'], many['j'], side='left')
            pairs = np.concatenate([pairs[~crowded], many[rank < KERNEL_NEIGHBOURS]])
        g = np.bincount(pairs['j'], _matern_of(pairs['v'], self.settings) * self.weights[pairs['i']],
                        minlength=len(points))
        return np.asarray(self.prior(points, nearest_cell) + g)

    def std(self, points: Points) -> Floats:
        """The process's own standard deviation of f at ``points`` (at most ``signal_std``)."""
        out = np.empty(len(points))
        for start in range(0, len(points), _CHUNK):
            kz = _matern(self.inducing, points[start:start + _CHUNK], self.settings)
            variance = self.settings.signal_std ** 2 - np.einsum('ij,ij->j', kz, self._reduction @ kz)
            out[start:start + _CHUNK] = np.sqrt(np.maximum(variance, 0.0))
        return out

    def total_std(self, points: Points, process_std: Floats | None = None) -> Floats:
        """The standard deviation of the predicted surface at ``points``: the process's
        (``process_std`` when already known) and, in quadrature, ``extrapolation`` times the
        distance beyond one length scale from the nearest touched cell. The process's own
        cannot exceed ``signal_std``, yet where only the prior shape stands in for the object
        it may be off by as much as the object is far: on the tuning maps of
        docs/exploration.md the surface more than 3 cm from every cell was 30-50 mm off with
        a process std of 1 cm."""
        own = self.std(points) if process_std is None else process_std
        if not self.settings.extrapolation or len(points) == 0:
            return own
        beyond = np.maximum(self.prior.tree.query(points, workers=-1)[0] - self.settings.length_scale, 0.0)
        return np.asarray(np.sqrt(own ** 2 + (self.settings.extrapolation * beyond) ** 2))

    def covariance(self, a: Points, b: Points) -> Floats:
        """Posterior covariance of f between ``a`` and ``b`` (rows a, columns b)."""
        ka = _matern(self.inducing, a, self.settings)
        kb = _matern(self.inducing, b, self.settings)
        return np.asarray(_matern(a, b, self.settings) - (self._reduction @ ka).T @ kb)


@dataclass(frozen=True, eq=False)
class PredictedSurface:
    """The predicted surface: mesh ``vertices`` (V, 3) m and outward ``faces`` (F, 3), the
    standard deviation at each vertex ``vertex_std`` (m: how far the true surface may be,
    :meth:`_SparseProcess.total_std`) and the process's own part of it ``process_std`` (what
    a touch can reduce: the next touch's gain), the grid points next to the surface
    ``band_points`` (B, 3) (their standard deviation: :meth:`band_std`), the ``prior`` and
    the process, the counts it was made from, and the surface cells ``cells`` (N, 3) it was
    predicted through (the occupied cells, and those a camera saw). Its part near those cells
    is the completed surface (:meth:`completed`)."""

    vertices: Points
    faces: NDArray[np.int64]
    vertex_std: Floats
    process_std: Floats
    band_points: Points
    prior: SurfacePrior
    process: _SparseProcess | None
    observations: int
    inducing: int
    settings: PredictionSettings
    cells: Points

    @property
    def empty(self) -> bool:
        return len(self.faces) == 0

    def completed(self) -> PredictedSurface:
        """The completed surface: the triangles whose centroid lies within
        ``settings.completed_reach`` of a surface cell, their vertices with their standard
        deviations. Farther out the prediction is mostly the prior shape's guess: after 20
        strokes, half or more of it lies over 5 mm from the true surface beyond a centimetre
        from every cell (docs/exploration.md, "The completed surface, how far it reaches").
        The whole prediction is still what the uncertainty and the next touches are made of."""
        if self.empty or len(self.cells) == 0:
            return self
        centroids = self.vertices[self.faces].mean(axis=1)
        distance, _ = cKDTree(self.cells).query(centroids, distance_upper_bound=self.settings.completed_reach)
        used, faces = _compacted(self.faces[np.isfinite(distance)])
        return replace(self, vertices=self.vertices[used], faces=faces,
                       vertex_std=self.vertex_std[used], process_std=self.process_std[used])

    def band_std(self) -> Floats:
        """The standard deviation (m) at the grid points next to the surface (on request:
        they are more than the vertices, and the viewers draw the vertices)."""
        if self.process is None or len(self.band_points) == 0:
            return np.zeros(len(self.band_points))
        return self.process.total_std(self.band_points)

    def vertex_areas(self) -> Floats:
        """A third of the area of the triangles around each vertex (m^2)."""
        t = self.vertices[self.faces]
        area = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
        area = np.bincount(self.faces.ravel(), np.repeat(area / 3.0, 3), len(self.vertices))
        return area.astype(np.float64)

    def vertex_normals(self) -> Floats:
        """Outward unit normals at the vertices (area-weighted face normals)."""
        t = self.vertices[self.faces]
        face = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        normals = np.stack([np.bincount(self.faces.ravel(), np.repeat(face[:, k], 3),
                                        len(self.vertices)) for k in range(3)], axis=1)
        return np.asarray(normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12))

    def trimesh(self):  # type: ignore[no-untyped-def]
        """The mesh as a trimesh.Trimesh with a per-vertex ``std`` attribute (m)."""
        import trimesh
        mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        mesh.vertex_attributes['std'] = self.vertex_std.astype(np.float32)
        return mesh


MIN_CELLS = 10


def predict_surface(cells: ArrayLike, resolution: float, free: ArrayLike | None = None,
                    settings: PredictionSettings = PredictionSettings(),
                    weights: ArrayLike | None = None, prior: SurfacePrior | None = None
                    ) -> PredictedSurface:
    """The completed surface of the occupied cells' centres ``cells`` (N, 3) m of a map of
    cell size ``resolution`` (``weights``: their occupancy probabilities, for the prior's
    fit), given its free cells' centres ``free`` (module doc). ``prior``: the prior shape of
    an earlier prediction of the same object, kept instead of fitted again (its fit is most of
    the cost). An empty surface for fewer than :data:`MIN_CELLS` cells."""
    from skimage.measure import marching_cubes
    occupied = np.asarray(cells, dtype=float).reshape(-1, 3)
    free_points = np.empty((0, 3)) if free is None else np.asarray(free, dtype=float).reshape(-1, 3)
    if not resolution > 0:
        raise ValueError(f'resolution {resolution}: must be > 0')
    if len(occupied) < MIN_CELLS:
        prior = SurfacePrior(Superquadric(np.full(3, resolution), (1.0, 1.0), np.eye(3), np.zeros(3)))
        return _no_surface(prior, settings)
    if prior is None and settings.prior == 'superquadric':
        w = np.ones(len(occupied)) if weights is None else np.asarray(weights, dtype=float).ravel()
        prior = SurfacePrior.fitted(occupied, w, resolution)
    elif prior is None:
        prior = SurfacePrior.ellipsoid_around(occupied, PRIOR_MARGIN * resolution)
    tree = cKDTree(occupied)
    # the prior's box and the cells', but never more than the cells' extent beyond them (a
    # prior fitted to a sliver may reach far)
    low, high = occupied.min(axis=0), occupied.max(axis=0)
    reach = max(float((high - low).max()), settings.margin)
    prior_low, prior_high = prior.bounds()
    low = np.minimum(low, np.maximum(prior_low, low - reach)) - settings.margin
    high = np.maximum(high, np.minimum(prior_high, high + reach)) + settings.margin
    step = max(settings.grid_step * resolution, float(np.prod(high - low) / MAX_GRID_POINTS) ** (1 / 3))
    axes = [np.arange(a, b + step, step) for a, b in zip(low, high)]
    grid = np.stack(np.meshgrid(*axes, indexing='ij'), axis=-1)
    obs = _observations(occupied, free_points, resolution, prior, settings, tree)
    process = _SparseProcess(obs, _PriorMean(prior, occupied, settings.prior_reach, tree),
                             settings, resolution)
    neighbours = nearest_cells(occupied, grid.reshape(-1, 3), tree)
    values = process.mean(grid.reshape(-1, 3), neighbours[0][:, 0]).reshape(grid.shape[:3])
    # Where the map has evidence, its own surface (surface_mesh's tangent planes) is the answer;
    # elsewhere nothing in front of the touched surface is inside: the process may close the
    # surface behind what was touched, never bridge a gap the fingers passed over.
    planes = tangent_plane_distance(occupied, obs.normals, grid.reshape(-1, 3), resolution, obs.sheet,
                                    neighbours)
    near = neighbours[0][:, 0] <= REACH * resolution
    flat = values.reshape(-1)
    flat[:] = np.where(near, planes, np.maximum(flat, planes))
    # the grid's faces are outside: the surface closes inside the box
    values[[0, -1], :, :] = values[:, [0, -1], :] = values[:, :, [0, -1]] = np.abs(values).max()
    if not values.min() < 0:
        return _no_surface(prior, settings, process, len(obs.points), len(process.inducing))
    verts, faces, _, _ = marching_cubes(values, 0.0, spacing=(step, step, step),
                                        gradient_direction='descent', allow_degenerate=False)
    vertices, faces = _without_cavities(verts + low, np.asarray(faces, dtype=np.int64))
    band = np.abs(values) <= step
    band_points = grid[band]
    own = process.std(vertices)
    return PredictedSurface(vertices, np.asarray(faces, dtype=np.int64), process.total_std(vertices, own),
                            own, band_points, prior, process, len(obs.points), len(process.inducing),
                            settings, occupied)


def _no_surface(prior: SurfacePrior, settings: PredictionSettings, process: _SparseProcess | None = None,
                observations: int = 0, inducing: int = 0) -> PredictedSurface:
    nothing = np.zeros((0, 3))
    return PredictedSurface(nothing, np.zeros((0, 3), dtype=np.int64), np.zeros(0), np.zeros(0), nothing,
                            prior, process, observations, inducing, settings, nothing)


def predict_map_surface(centres: ArrayLike, probabilities: ArrayLike, resolution: float,
                        settings: PredictionSettings = PredictionSettings(),
                        occupied_threshold: float = 0.8, prior: SurfacePrior | None = None,
                        seen: ArrayLike | None = None, seen_from: ArrayLike | None = None
                        ) -> PredictedSurface:
    """:func:`predict_surface` of a map's cells (centres (N, 3) m and occupancy
    probabilities, every touched cell or only the occupied ones): the cells at or above
    ``occupied_threshold`` are the surface, those at most :data:`FREE_PROBABILITY` free space.
    ``seen``: points (K, 3) of the object's surface a camera measured (the stereo points of
    the object, map frame), ``seen_from`` (K, 3) or (3,) where the camera was: the cells
    holding at least :data:`SEEN_POINTS` of them are surface too, and those the rays crossed
    :data:`SEEN_FREE` cells in front of them free (:func:`seen_cells`)."""
    if not 0.5 < occupied_threshold < 1:
        raise ValueError(f'occupied_threshold {occupied_threshold}: must be in (0.5, 1)')
    points = np.asarray(centres, dtype=float).reshape(-1, 3)
    p = np.asarray(probabilities, dtype=float).ravel()
    occupied = p >= occupied_threshold
    free = p <= FREE_PROBABILITY
    surface, weights, empty = points[occupied], p[occupied], points[free]
    if seen is not None and len(points):
        extra, extra_free = seen_cells(seen, seen_from, points, resolution, points[occupied | free],
                                       points[occupied])
        surface = np.concatenate([surface, extra])
        weights = np.concatenate([weights, np.full(len(extra), occupied_threshold)])
        empty = np.concatenate([empty, extra_free])
    return predict_surface(surface, resolution, empty, settings, weights=weights, prior=prior)


SEEN_POINTS = 3     # camera points a cell must hold to be surface (one is a mismatch)
SEEN_FREE = (1.5, 3.0)   # cells in front of a camera point along its ray that are free
# cells towards the camera, up to 4 cm, where a touched cell hides a point behind it
SEEN_BEHIND = tuple(float(k) for k in range(1, 9))


def seen_cells(seen: ArrayLike, seen_from: ArrayLike | None, centres: Points, resolution: float,
               known: Points, occupied_cells: Points | None = None) -> tuple[Points, Points]:
    """(surface, free) cell centres, on the lattice of the map cells ``centres``, from the
    camera's surface points ``seen`` (K, 3) measured from ``seen_from`` ((K, 3) or (3,); None:
    no free space): a cell holding at least :data:`SEEN_POINTS` of them is surface, one
    :data:`SEEN_FREE` cells in front of that many along their rays is free, unless it is
    surface. The ``known`` cells stay as the map has them (occupied: already surface; free: a
    finger went through, which outweighs a camera point there). A point with one of the
    touched cells ``occupied_cells`` in front of it along its ray, within :data:`SEEN_BEHIND`,
    is left out: the camera cannot have seen it there (dark glass reads 5-15 mm behind its
    surface), and a second layer behind the touched surface would make the process draw two."""
    from inhand_common.cell_lattice import cell_indices, infer_lattice
    lattice = infer_lattice(centres, resolution)
    points = np.asarray(seen, dtype=float).reshape(-1, 3)
    finite = np.isfinite(points).all(axis=1)
    occupied_cells = np.empty((0, 3)) if occupied_cells is None else occupied_cells
    known_keys = _packed(cell_indices(known, lattice))

    def counted(where: Points) -> NDArray[np.int64]:
        keys, counts = np.unique(cell_indices(where, lattice), axis=0, return_counts=True)
        keys = keys[counts >= SEEN_POINTS]
        return keys[~np.isin(_packed(keys), known_keys)]

    origin = np.asarray(lattice.origin)
    points = points[finite]
    free = np.empty((0, 3), dtype=np.int64)
    if seen_from is not None and len(points):
        camera = np.broadcast_to(np.asarray(seen_from, dtype=float), (len(finite), 3))[finite]
        ray = points - camera
        ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
        # a point behind a touched surface along its ray is not what the camera saw there
        # (dark glass reads 5-10 mm behind its surface): the touch map wins
        touched = _packed(cell_indices(occupied_cells, lattice))
        behind = np.zeros(len(points), dtype=bool)
        for step in SEEN_BEHIND:
            behind |= np.isin(_packed(cell_indices(points - step * resolution * ray, lattice)),
                              touched)
        points, ray = points[~behind], ray[~behind]
        free = counted(np.concatenate([points - step * resolution * ray for step in SEEN_FREE]))
    surface = counted(points) if len(points) else np.empty((0, 3), dtype=np.int64)
    free = free[~np.isin(_packed(free), _packed(surface))]
    return (np.asarray(origin + (surface + 0.5) * resolution),
            np.asarray(origin + (free + 0.5) * resolution))


def _packed(index: NDArray[np.int64]) -> NDArray[np.int64]:
    """One int64 per cell index (n, 3) (each within +-2^20 cells of the lattice's origin)."""
    shifted = np.asarray(index, dtype=np.int64) + (1 << 20)
    return np.asarray((shifted[:, 0] << 42) | (shifted[:, 1] << 21) | shifted[:, 2])
