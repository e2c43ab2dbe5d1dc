"""Superquadrics: the shape, its distance, its surface, and a robust fit to map cells.

A superquadric in its own frame is the set ``F(x) <= 1`` of

    F(x) = ((|x|/a1)^(2/e2) + (|y|/a2)^(2/e2))^(e2/e1) + (|z|/a3)^(2/e1)

with semi-axes ``a1, a2, a3`` (m) and shape exponents ``e1`` (along z) and ``e2`` (in the
x-y cross-section): e -> 0.1 is box-like, e = 1 an ellipsoid, e = 2 a diamond (octahedron);
``e1 = 0.1, e2 = 1`` is a cylinder along z. The pose puts it in the map's frame: ``rotation``
(columns are its x, y, z axes) and ``centre``.

**Distance.** The fit and the residuals use the radial distance of Jaklic et al. (2000) that
EMS uses (Liu et al., "Robust and Accurate Superquadric Recovery: a Probabilistic Approach",
CVPR 2022): ``d = |x| |1 - F(x)^(-e1/2)|``, the distance from x to the surface along the ray
from the centre. It is exact on spheres, close to the Euclidean distance near the surface,
and cheap. It is computed in logarithms, because the powers overflow float64 for e = 0.1.

**The fit** (:func:`fit_superquadric`) is EMS's idea written for map cells: the cells are
drawn from a mixture of the surface (a Gaussian in the radial distance, sigma estimated) and
outliers (uniform over the cells' bounding box), each cell weighted by its occupancy
probability. Expectation-maximisation alternates the posterior that each cell is on the
surface with a weighted least-squares step on the 11 parameters (scipy's trust-region
least squares, bounded exponents and sizes). The local minima of the superquadric cost are
mostly wrong assignments of the axes (a cylinder along x cannot be written with a round
cross-section in x-y), so the fit starts from each of the three principal axes of the cells
as z, and keeps the start with the highest likelihood. Why our own code: no maintained
Python package fits superquadrics with an outlier model (EMS's reference code is a research
script), and the model is 150 lines on scipy.

**Held to its cells.** The surface term says nothing where there is no cell: a side the hand
never touched (a static object's underside, the lower half of a shaft lying on the table)
goes wherever the search pushes it, and a strip of cells along the top of a shaft is as well
explained by one face of a deep slab as by a cylinder. So the least squares also counts how
far the shape reaches past its inlier cells at each end of each of its axes, beyond a cell
of margin (:class:`_Reach`): zero for every side the cells show, a pull back towards the
cells for a side they do not, which the surface term resists only where the pulled-back
shape explains the cells worse (the Solina-Bajcsy cost's ``sqrt(a1 a2 a3)`` is a cruder
form of the same preference, for a smaller shape everywhere).

**Cells, not points.** A cell is occupied when the surface passed through it, anywhere in
its 5 mm, so its centre lies up to half a cell or more off the surface, and a touch map's
cells scatter on both sides of it, by 1.6-3.7 mm on average, not in a Gaussian around it.
Counted by their squared distance, the farthest cells decide: the benchmark's cylinder (a
radius of 30 mm) came out 28.8-29.1 mm with a square-ish cross-section (e2 0.83-0.86 for
1), its box with rounded edges (exponents 0.27-0.58 for 0.1). So a cell's distance counts
only beyond ``CELL_SLACK`` of a cell (0.35): a centre nearer than that is on the surface,
and the surface goes where the band of cells puts it (the cylinder 29.6-29.8 mm, e2
0.91-0.93). The search runs without the slack and the shape it finds is fitted again with
it: with the slack in the search too some fits went astray (seed 7's standing bottle at
half a cell: 1.9 -> 3.1 mm Chamfer; seed 10's standing diamond fitted alone at 0.35: 0.7
-> 2.2 mm). Points on the surface (the benchmark's dense reference) take no slack.

**Where the touches were.** Better than any slack is to know where in each cell the surface
passed: the map keeps the sum of the fingertip positions counted in each cell, and their
mean (the cell's contact centroid, inhand_common.contact_centroids) lies on the surface to
the tracker's noise, 0.4-0.7 mm median against 1.4-2.5 mm for the centres. Given them
(``surface_points``), the shape searched on the cells is fitted last to them, as points on
the surface, from where the search left it and from its switched twin (a rounded cube and
its twin fit cells alike, not the touches), from the same pose and size with box-like,
round and diamond-like exponents (``SHAPE_STARTS``) and their twins, and by a search on
them alone; the most likely. The search on the cells can settle in a shape the touches
tell apart from the truth only when the fit starts near it: a diamond found as a rounded
box turned 45 degrees, a rounded cube as a tilted e ~ 1.2 blob (docs/shape.md, "Where the
touches were").

**Upright on a support.** An object standing on a table that the hand explored from above
shows a band of its sides: the table hides its underside and often the other hand its top.
Given such a band of an ellipsoid, a tilted shape explains it as well as the upright one
(the standing ellipsoid of the benchmark came out 44 degrees off). An object resting alone
on a support has its centre above where it touches it, which for an ellipsoid, a box or a
cylinder is the end of an axis: that axis is vertical. So where the support's normal is
known (``up``: a static map), a fit more than :data:`UPRIGHT_TOLERANCE` off it is made again
with the shape held upright (its axis nearest to ``up`` turned onto it, only turns about it
left free), and the upright fit is taken unless it explains the cells worse by more than
:data:`UPRIGHT_MARGIN` of log-likelihood per cell. A pointed shape (e ~ 1.6) rests on a
face, not on an axis's end; held upright it explains its cells much worse (0.1 per cell
on the benchmark's standing diamond, against 0.005-0.02 for the ellipsoid), and keeps its
free fit.

:func:`fit_least_squares` is the classic baseline (Solina and Bajcsy 1990): least squares
on ``sqrt(a1 a2 a3) (F^e1 - 1)`` from the same starts, every cell counted, no outliers.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares  # type: ignore[import-untyped]
from scipy.spatial.transform import Rotation  # type: ignore[import-untyped]
from scipy.special import beta  # type: ignore[import-untyped]

from inhand_common.array_types import Floats, Matrix3, Points, Vector3, Weights

__all__ = ['EXPONENT_RANGE', 'SHAPE_STARTS', 'FitResult', 'Superquadric', 'area_samples',
           'fit_least_squares', 'fit_superquadric', 'radial_distance']

EXPONENT_RANGE = (0.1, 1.9)    # box-like to diamond-like; outside it the shape degenerates
MAX_FIT_CELLS = 800           # cells the EM iterations use (a probability-weighted subset)
EM_ITERATIONS = 15
TRIM_PERCENTILE = 0.5      # the cells' extent along an axis, ignoring the extreme 0.5 %
TRIM_GAP = 1.5             # cells: a shape reaching this far past its cells is cut back ...
TRIM_KEEP = 0.98           # ... when the cut shape keeps this share of the cells on it
TRIM_ITERATIONS = 8        # EM steps from the cut shape when it does not
REACH_WEIGHT = 0.2         # of the inliers' surface term: the pull back to the cells (_Reach)
REACH_MARGIN = 1.0         # cells: a shape reaches this far past its last inlier cell freely
                           # (the surface lies up to half a cell past the cell centres, and
                           # the extreme inlier is as noisy again)
EM_SCOUT_ITERATIONS = 4    # EM steps from each start before the most likely goes on
CELL_SLACK = 0.35          # cells: a cell centre this near the surface is on it (module doc,
                           # "cells, not points"; 0.25-0.5 measured, docs/shape.md)
SHAPE_STARTS = ((0.2, 0.2), (1.0, 1.0), (1.6, 1.6))   # exponents the last fit on where the
                           # touches were also starts from: box-like, round, diamond-like
                           # (module doc, "Where the touches were")
UPRIGHT_MARGIN = 0.05      # log-likelihood per cell an upright fit may lose and still be
                           # taken (module doc, "Upright on a support"; docs/shape.md)
UPRIGHT_TOLERANCE = math.radians(5.0)   # a fit with an axis this near ``up`` is upright already
_FD_STEP = float(np.finfo(float).eps) ** 0.5   # scipy's relative step of '2-point' differences
_TINY = 1e-12
_HELD = 1e-9               # rad: the bound of a held rotation component (lower < upper)


@dataclass(frozen=True, eq=False)
class Superquadric:
    """Semi-axes ``size`` (3,) m, exponents ``shape`` (e1, e2), pose ``rotation`` (3, 3)
    (columns: the part's axes in the map frame) and ``centre`` (3,) m."""

    size: Vector3
    shape: tuple[float, float]
    rotation: Matrix3
    centre: Vector3

    def local(self, points: ArrayLike) -> Points:
        """``points`` (N, 3) in the superquadric's own frame."""
        return np.asarray((np.asarray(points, dtype=float) - self.centre) @ self.rotation)

    def inside_outside(self, points: ArrayLike) -> Floats:
        """F(x) of the module doc: < 1 inside, 1 on the surface, > 1 outside."""
        return np.exp(_log_inside_outside(self.local(points), self.size, *self.shape))

    def distance(self, points: ArrayLike) -> Floats:
        """The radial distance (module doc) of each point to the surface, >= 0."""
        return radial_distance(self.local(points), self.size, *self.shape)

    def contains(self, points: ArrayLike) -> NDArray[np.bool_]:
        return self.inside_outside(points) <= 1.0

    def _scaled(self, local: Points) -> Floats:
        """F^(e1/2) - 1: zero on the surface, growing like the distance along each ray."""
        return np.exp(self.shape[0] / 2 * _log_inside_outside(local, self.size, *self.shape)) - 1

    def _gradient(self, local: Points) -> Points:
        """The gradient of :meth:`_scaled` in the own frame, by central differences."""
        step = 1e-5 * float(self.size.min())
        gradient = np.empty_like(local)
        for axis in range(3):
            offset = np.zeros(3)
            offset[axis] = step
            gradient[:, axis] = (self._scaled(local + offset) - self._scaled(local - offset)) / (2 * step)
        return gradient

    def normals(self, points: ArrayLike) -> Points:
        """Outward unit normals at ``points`` (on or near the surface)."""
        normals = self._gradient(self.local(points)) @ self.rotation.T
        return np.asarray(normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300))

    def surface_distance(self, points: ArrayLike) -> Floats:
        """Distance to the surface to first order (Taubin 1991: |g| / |grad g|): close to the
        Euclidean distance near the surface also where the radial distance is not (the
        flat sides of an elongated shape, whose rays from the centre meet them obliquely)."""
        local = self.local(points)
        gradient = np.linalg.norm(self._gradient(local), axis=1)
        return np.asarray(np.abs(self._scaled(local)) / np.maximum(gradient, 1e-12))

    @property
    def quaternion(self) -> Floats:
        """The orientation as x, y, z, w."""
        return np.asarray(Rotation.from_matrix(self.rotation).as_quat())

    @property
    def volume(self) -> float:
        """Closed form (Jaklic et al. 2000, eq. 2.60)."""
        a1, a2, a3 = self.size
        e1, e2 = self.shape
        return float(2 * a1 * a2 * a3 * e1 * e2 * beta(e1 / 2 + 1, e1) * beta(e2 / 2, e2 / 2))

    def mesh(self, subdivisions: int = 4) -> tuple[Points, NDArray[np.int64]]:
        """A closed triangle mesh of the surface: (vertices (V, 3) in the map frame, faces
        (F, 3)), outward oriented; the unit icosphere of ``subdivisions`` pushed onto the
        surface along its rays (so every vertex is exactly on it)."""
        directions, faces = _unit_sphere(subdivisions)
        # On the ray t * u the function is F(t u) = t^(2/e1) F(u): the surface is at
        # t = F(u)^(-e1/2).
        reach = np.exp(-self.shape[0] / 2 * _log_inside_outside(directions, self.size, *self.shape))
        vertices = (directions * reach[:, None]) @ self.rotation.T + self.centre
        return vertices, faces

    def surface_samples(self, count: int, rng: np.random.Generator) -> Points:
        """``count`` points spread uniformly over the surface (by area)."""
        vertices, faces = self.mesh(5)
        return area_samples(vertices, faces, count, rng)

    def as_dict(self) -> dict[str, Any]:
        """Plain values for YAML/JSON: size, exponents, centre, quaternion (x, y, z, w)."""
        return {'size': [round(float(v), 5) for v in self.size],
                'exponents': [round(float(v), 3) for v in self.shape],
                'position': [round(float(v), 5) for v in self.centre],
                'orientation': [round(float(v), 6) for v in self.quaternion]}


def area_samples(vertices: Points, faces: NDArray[np.int64], count: int,
                 rng: np.random.Generator) -> Points:
    """``count`` points spread uniformly (by area) over the triangle mesh (vertices, faces)."""
    triangles = vertices[faces]
    areas = 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0],
                                          triangles[:, 2] - triangles[:, 0]), axis=1)
    chosen = rng.choice(len(faces), size=count, p=areas / areas.sum())
    u, v = rng.random((2, count))
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    t = triangles[chosen]
    return np.asarray(t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0]))


@functools.lru_cache(maxsize=8)
def _unit_sphere(subdivisions: int) -> tuple[Points, NDArray[np.int64]]:
    """The unit icosphere's vertices and faces, made once per level (read-only): every part
    check samples a superquadric's surface, and making the sphere cost more than the rest."""
    import trimesh
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    vertices = np.array(sphere.vertices, dtype=float)
    faces = np.array(sphere.faces, dtype=np.int64)
    vertices.flags.writeable = faces.flags.writeable = False
    return vertices, faces


def _log_inside_outside(local: Floats, size: ArrayLike, e1: float | Floats, e2: float | Floats) -> Floats:
    """log F(x) (module doc) of points in the superquadric's frame, without overflow:
    ``local`` (..., 3), ``size`` (..., 3) and the exponents broadcast against it (the fit's
    Jacobian evaluates K superquadrics at once: (K, N, 3) with (K, 1, 3) and (K, 1))."""
    logs = np.log(np.maximum(np.abs(local) / np.asarray(size, dtype=float), _TINY))
    cross_section = (e2 / e1) * np.logaddexp(2 / e2 * logs[..., 0], 2 / e2 * logs[..., 1])
    return np.asarray(np.logaddexp(cross_section, 2 / e1 * logs[..., 2]))


def radial_distance(local: Floats, size: ArrayLike, e1: float | Floats, e2: float | Floats) -> Floats:
    """The radial distance (module doc) of points given in the superquadric's frame (shapes
    as :func:`_log_inside_outside`)."""
    radius = np.linalg.norm(local, axis=-1)
    return np.asarray(radius * np.abs(1 - np.exp(-e1 / 2 * _log_inside_outside(local, size, e1, e2))))


@dataclass(frozen=True, eq=False)
class FitResult:
    """A fitted superquadric and how well it explains the cells it was fitted to.

    ``distances`` (N,) the cells' distances to the surface (:meth:`Superquadric.surface_distance`);
    ``inlier`` (N,) the posterior that a
    cell is on the surface (1 for the least-squares baseline); ``sigma`` the surface's spread
    (m); ``residual`` the probability-weighted RMS distance of the inliers (m);
    ``explained`` the weighted share of cells within ``2 sigma`` (at least one cell width)."""

    superquadric: Superquadric
    distances: Floats
    inlier: Weights
    sigma: float
    residual: float
    explained: float
    log_likelihood: float


def _principal_frame(points: Points, weights: Weights) -> tuple[Vector3, Matrix3, Vector3]:
    """Weighted centre, principal axes (columns, largest spread first, right-handed) and
    the half-extents along them (5th-95th percentile)."""
    centre = np.average(points, axis=0, weights=weights)
    cov = np.cov((points - centre).T, aweights=weights) if len(points) > 3 else np.eye(3)
    _, vectors = np.linalg.eigh(cov)
    axes = vectors[:, ::-1]
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    along = (points - centre) @ axes
    lo, hi = np.percentile(along, [2, 98], axis=0)
    centre = centre + axes @ ((lo + hi) / 2)
    return centre, axes, np.maximum((hi - lo) / 2, _TINY)


def _starts(points: Points, weights: Weights) -> list[tuple[Vector3, Matrix3, Vector3]]:
    """Initial poses and sizes: the principal frame with each of its axes as z."""
    centre, axes, half = _principal_frame(points, weights)
    starts = []
    for z in range(3):
        order = [(z + 1) % 3, (z + 2) % 3, z]
        frame = axes[:, order]
        if np.linalg.det(frame) < 0:
            frame[:, 0] *= -1
        starts.append((centre, frame, half[order]))
    return starts


@dataclass(frozen=True)
class _Reach:
    """How far a shape reaches past its cells, as a fit residual. The surface term alone
    has no say where no cell is: a side no cell shows (a static object's underside, the
    lower half of a shaft lying on the table) goes wherever the search pushes it, and a
    strip of cells along a shaft is as well explained by one face of a deep slab as by a
    cylinder. Past each end of each of the shape's axes, the distance by which it reaches
    beyond ``margin`` of its last inlier cell is a residual of ``weight``: zero for a shape
    its cells span (every seen side), a pull back towards the cells for an unseen one,
    which the surface term resists only where it explains the cells worse."""

    inlier: NDArray[np.bool_]     # the cells that count (the surface's, not the strays)
    weight: float
    margin: float                 # m

    def past(self, local: Floats, size: Floats) -> Floats:
        """(..., 6) for cells ``local`` (..., N, 3) in the shape's frame and ``size`` (..., 3):
        the reach past the cells at the + ends, then at the - ends, less the margin, >= 0."""
        cells = local[..., self.inlier, :]
        beyond = np.concatenate([size - cells.max(axis=-2), size + cells.min(axis=-2)], axis=-1)
        return np.asarray(np.maximum(beyond - self.margin, 0.0))


class _Parameters:
    """The 11 fit parameters as one vector: log sizes, exponents, a rotation vector
    relative to ``base``, and the centre. ``about`` (a unit vector): the shape is held with
    one axis along it (the base's axis nearest to it turned onto it, the rotation bounded to
    turns about that axis)."""

    def __init__(self, base: Matrix3, size_bounds: tuple[float, float], slack: float = 0.0,
                 about: Vector3 | None = None):
        held = None
        if about is not None:
            base, held = _upright_base(base, about)
        self.base = base
        self.slack = slack
        self.about = about
        lo, hi = np.log(size_bounds[0]), np.log(size_bounds[1])
        e_lo, e_hi = EXPONENT_RANGE
        self.lower = np.array([lo, lo, lo, e_lo, e_lo, -np.pi, -np.pi, -np.pi, -np.inf, -np.inf, -np.inf])
        self.upper = np.array([hi, hi, hi, e_hi, e_hi, np.pi, np.pi, np.pi, np.inf, np.inf, np.inf])
        if held is not None:    # no turn but about the held axis (bounds must differ)
            for k in range(3):
                if k != held:
                    self.lower[5 + k], self.upper[5 + k] = -_HELD, _HELD

    def vector(self, size: Vector3, shape: tuple[float, float], centre: Vector3) -> Floats:
        x = np.concatenate([np.log(size), shape, np.zeros(3), centre])
        return np.asarray(np.clip(x, self.lower + 1e-9, self.upper - 1e-9), dtype=float)

    def superquadric(self, x: Floats) -> Superquadric:
        rotation = self.base @ _rotation_matrix(x[5:8])
        return Superquadric(np.exp(x[:3]), (float(x[3]), float(x[4])), rotation, x[8:11].copy())

    def local(self, x: Floats, points: Points) -> Points:
        """``points`` in the frame of the superquadric ``x``."""
        return np.asarray((points - x[8:11]) @ (self.base @ _rotation_matrix(x[5:8])))

    def distances(self, x: Floats, points: Points) -> Floats:
        return _beyond_slack(radial_distance(self.local(x, points), np.exp(x[:3]), x[3], x[4]),
                             self.slack)

    def residuals(self, x: Floats, points: Points, scale: Floats, reach: _Reach | None = None
                  ) -> Floats:
        """The fit's residuals: ``scale`` * distances (N,), then, with ``reach``, how far
        the shape reaches past its cells (6,)."""
        local = self.local(x, points)
        d = scale * _beyond_slack(radial_distance(local, np.exp(x[:3]), x[3], x[4]), self.slack)
        if reach is None:
            return np.asarray(d)
        return np.concatenate([d, reach.weight * reach.past(local, np.exp(x[:3]))])

    def jacobian(self, x: Floats, points: Points, scale: Floats, reach: _Reach | None = None
                 ) -> Floats:
        """d(residuals)/dx ((N, 11), with ``reach`` (N + 6, 11)) by forward differences with
        scipy's own steps (least_squares' default '2-point' Jacobian), all 11 shifted
        parameter vectors in one vectorised pass: the residual on a few hundred cells costs
        less than the Python call around it, and the Jacobian's 11 calls were most of a
        fit's time."""
        step = _FD_STEP * np.where(x >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(x))
        # a step past the upper bound goes the other way (scipy: '1-sided' schemes)
        step = np.where((x + step > self.upper) & (x - step >= self.lower), -step, step)
        step = (x + step) - x
        shifted = np.vstack([x, x + np.diag(step)])
        offset = points - x[8:11]
        rotation = self.base @ _rotation_matrix(x[5:8])
        base = offset @ rotation
        local = np.empty((12,) + points.shape)
        local[:6] = base                      # sizes and exponents: the same frame
        for k in range(5, 8):                 # a turned frame
            local[k + 1] = offset @ (self.base @ _rotation_matrix(shifted[k + 1, 5:8]))
        # a moved centre: the points shift by the step along that axis, in the frame
        local[9:] = base[None, :, :] - step[8:, None, None] * rotation[None, :, :].transpose(1, 0, 2)
        d = _beyond_slack(radial_distance(local, np.exp(shifted[:, None, :3]), shifted[:, 3:4],
                                          shifted[:, 4:5]), self.slack)
        jacobian = scale[:, None] * ((d[1:] - d[0]) / step[:, None]).T
        if reach is None:
            return np.asarray(jacobian)
        past = reach.weight * reach.past(local, np.exp(shifted[:, :3]))
        return np.vstack([jacobian, ((past[1:] - past[0]) / step[:, None]).T])


def _beyond_slack(distances: Floats, slack: float) -> Floats:
    """What of the radial distances the cells' own extent (``slack``, m) does not explain."""
    return np.asarray(np.maximum(distances - slack, 0.0)) if slack > 0 else distances


def _upright_base(base: Matrix3, up: Vector3) -> tuple[Matrix3, int]:
    """``base`` with its axis nearest to the line of ``up`` turned onto it (the others made
    perpendicular, right-handed), and that axis's index."""
    base = np.asarray(base, dtype=float)
    k = int(np.argmax(np.abs(up @ base)))
    axis = up * (1.0 if float(up @ base[:, k]) >= 0 else -1.0)
    i, j = (k + 1) % 3, (k + 2) % 3
    first = base[:, i] - float(axis @ base[:, i]) * axis   # never 0: axis k is the nearest
    first = first / np.linalg.norm(first)
    turned = np.empty((3, 3))
    turned[:, k], turned[:, i], turned[:, j] = axis, first, np.cross(axis, first)
    return turned, k


def _tilt(sq: Superquadric, up: Vector3) -> float:
    """Angle (rad) between the line of ``up`` and the shape's axis nearest to it."""
    return math.acos(min(1.0, float(np.max(np.abs(up @ sq.rotation)))))


def _rotation_matrix(rotvec: Floats) -> Matrix3:
    """Rodrigues' formula, ``cos a I + sin a [k]x + (1 - cos a) k k^T``, in scalars: scipy's
    Rotation, or even numpy on 3x3 arrays, costs more than the residuals it is used in."""
    x, y, z = float(rotvec[0]), float(rotvec[1]), float(rotvec[2])
    angle = math.sqrt(x * x + y * y + z * z)
    if angle < 1e-12:
        return np.eye(3)
    x, y, z = x / angle, y / angle, z / angle
    s, c = math.sin(angle), math.cos(angle)
    t = 1.0 - c
    return np.array([[t * x * x + c, t * x * y - s * z, t * x * z + s * y],
                     [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
                     [t * x * z - s * y, t * y * z + s * x, t * z * z + c]])


def _subset(points: Points, weights: Weights, limit: int) -> tuple[Points, Weights]:
    """At most ``limit`` cells, drawn without replacement by weight (the same every run);
    a cell of weight 0 is never drawn, and where fewer than ``limit`` weigh anything, those
    are the subset."""
    if len(points) <= limit:
        return points, weights
    weighing = np.flatnonzero(weights > 0)
    if len(weighing) <= limit:
        return points[weighing], weights[weighing]
    rng = np.random.default_rng(0)
    chosen = rng.choice(weighing, size=limit, replace=False, p=weights[weighing] / weights[weighing].sum())
    return points[chosen], np.ones(limit)


def _mixture(distances: Floats, sigma: float, outlier_ratio: float, density: float
             ) -> tuple[Floats, Floats]:
    """(posterior of the surface, mixture likelihood) per cell."""
    surface = (1 - outlier_ratio) * np.exp(-0.5 * (distances / sigma) ** 2) \
        / (2 * np.pi * sigma ** 2) ** 1.5
    total = surface + outlier_ratio * density
    return surface / total, total


@dataclass
class _State:
    """One EM run's current point: parameters, their packing, sigma, log-likelihood."""
    x: Floats
    packing: _Parameters
    sigma: float
    likelihood: float = -math.inf


def _em(points: Points, weights: Weights, state: _State, resolution: float,
        outlier_ratio: float, iterations: int, sigma_cap: float = math.inf,
        reach_weight: float = 0.0) -> _State:
    """``iterations`` EM steps (fewer when converged) from ``state``, sigma at most
    ``sigma_cap``; the state after them."""
    x, packing = state.x, state.packing
    sigma = min(state.sigma, sigma_cap)
    density = 1.0 / np.prod(np.maximum(np.ptp(points, axis=0), resolution))
    sigma_floor = resolution / 2
    for _ in range(iterations):
        posterior, _ = _mixture(packing.distances(x, points), sigma, outlier_ratio, density)
        scale = np.sqrt(weights * posterior)
        inlier = posterior >= 0.5
        # reaching r past the cells costs as much as reach_weight^2 of the inliers' weight
        # lying r off the surface
        reach = _Reach(inlier, reach_weight * math.sqrt(float(np.sum((weights * posterior)[inlier]))),
                       REACH_MARGIN * resolution) if reach_weight > 0 and inlier.any() else None
        fit = least_squares(
            lambda v, scale=scale, reach=reach: packing.residuals(v, points, scale, reach), x,
            jac=lambda v, scale=scale, reach=reach: packing.jacobian(v, points, scale, reach),
            bounds=(packing.lower, packing.upper), max_nfev=12, x_scale='jac')
        change = float(np.abs(fit.x - x).max())
        x = fit.x
        d = packing.distances(x, points)
        posterior, _ = _mixture(d, sigma, outlier_ratio, density)
        new_sigma = math.sqrt(float(np.sum(weights * posterior * d ** 2))
                              / max(3 * float(np.sum(weights * posterior)), _TINY))
        new_sigma = min(max(new_sigma, sigma_floor), sigma_cap)
        converged = change < 1e-4 and abs(new_sigma - sigma) < 1e-5
        sigma = new_sigma
        if converged:
            break
    _, likelihood = _mixture(packing.distances(x, points), sigma, outlier_ratio, density)
    return _State(x, packing, sigma, float(np.sum(weights * np.log(likelihood))))


def _packing(points: Points, base: Matrix3, resolution: float, slack: float = 0.0,
             about: Vector3 | None = None) -> _Parameters:
    """The parameter packing around ``base``, sizes from a quarter cell to twice the cells'
    span, ``slack`` (m) as for :func:`fit_superquadric`, held ``about`` an axis if given."""
    span = float(np.ptp(points, axis=0).max()) if len(points) > 1 else resolution
    return _Parameters(base, (resolution / 4, max(2 * span, resolution)), slack, about)


def _state_of(sq: Superquadric, points: Points, resolution: float,
              sigma: float | None = None, slack: float = 0.0,
              about: Vector3 | None = None) -> _State:
    """An EM state at ``sq`` (held ``about`` an axis if given); ``sigma`` by default a fifth
    of its mean semi-axis (at least half a cell)."""
    packing = _packing(points, sq.rotation, resolution, slack, about)
    if sigma is None:
        sigma = max(0.2 * float(np.mean(sq.size)), resolution / 2)
    return _State(packing.vector(sq.size, sq.shape, sq.centre), packing, sigma)


def _switched(state: _State) -> _State:
    """EMS's similar candidate: the same cross-section turned 45 degrees about z with the
    other exponent (a square and a diamond look alike to a local search), sizes rescaled so
    the turned shape has the same reach."""
    sq = state.packing.superquadric(state.x)
    e1, e2 = sq.shape
    twin = min(max(2.0 - e2, EXPONENT_RANGE[0]), EXPONENT_RANGE[1])
    reach = 2.0 ** ((1.0 - e2) / 2) / 2.0 ** ((1.0 - twin) / 2)
    size = sq.size * np.array([reach, reach, 1.0])
    turn = Rotation.from_euler('z', 45, degrees=True).as_matrix()
    packing = _Parameters(sq.rotation @ turn, (np.exp(state.packing.lower[0]),
                                               np.exp(state.packing.upper[0])), state.packing.slack,
                          state.packing.about)
    return _State(packing.vector(size, (e1, twin), sq.centre), packing, state.sigma)


def _on_share(sq: Superquadric, points: Points, weights: Weights, tolerance: float) -> float:
    return float(np.average(sq.surface_distance(points) <= tolerance, weights=weights))


def _trimmed(sq: Superquadric, points: Points, weights: Weights, resolution: float
             ) -> Superquadric | None:
    """The superquadric cut back to where its cells end along each of its axes (module
    doc, "unseen sides"); None when it does not reach past them."""
    local = sq.local(points)
    near = sq.surface_distance(points) <= resolution
    if np.count_nonzero(near) < 10:
        return None
    low, high = np.percentile(local[near], [TRIM_PERCENTILE, 100 - TRIM_PERCENTILE], axis=0)
    # the surface lies up to half a cell past the last cell centres
    low, high = np.maximum(low - resolution / 2, -sq.size), np.minimum(high + resolution / 2, sq.size)
    gap = np.maximum(sq.size - high, sq.size + low)
    if gap.max() <= TRIM_GAP * resolution:
        return None
    cut = gap > TRIM_GAP * resolution
    size = np.where(cut, np.maximum((high - low) / 2, resolution / 2), sq.size)
    shift = np.where(cut, (high + low) / 2, 0.0)
    return Superquadric(size, sq.shape, sq.rotation, sq.centre + sq.rotation @ shift)


def _weights_of(points: Points, weights: ArrayLike | None) -> Weights:
    if weights is None:
        return np.ones(len(points))
    w = np.asarray(weights, dtype=float)
    if w.shape != (len(points),) or (w < 0).any() or not np.isfinite(w).all():
        raise ValueError(f'weights must be {len(points)} non-negative numbers')
    if not (w > 0).any():
        raise ValueError(f'the weights of all {len(points)} points are 0: no point counts in the fit')
    return w


def _result(sq: Superquadric, points: Points, weights: Weights, sigma: float,
            inlier: Floats, resolution: float, log_likelihood: float) -> FitResult:
    d = sq.surface_distance(points)
    near = d <= max(2 * sigma, resolution)
    total = max(float(weights.sum()), _TINY)
    w_in = weights * inlier
    residual = math.sqrt(float(np.sum(w_in * d ** 2)) / max(float(w_in.sum()), _TINY))
    return FitResult(sq, d, inlier, sigma, residual, float(np.sum(weights * near)) / total,
                     log_likelihood)


def _prepared(points: ArrayLike, weights: ArrayLike | None
              ) -> tuple[Points, Weights, Points, Weights]:
    """(cells, weights, the subset the search uses, its weights); ValueError for fewer than
    10 cells."""
    cells = np.asarray(points, dtype=float)
    if cells.ndim != 2 or cells.shape[1] != 3 or len(cells) < 10:
        raise ValueError(f'a superquadric needs at least 10 cells, got {len(cells)}')
    w = _weights_of(cells, weights)
    return (cells, w, *_subset(cells, w, MAX_FIT_CELLS))


def fit_superquadric(points: ArrayLike, weights: ArrayLike | None = None, *,
                     resolution: float = 0.005, outlier_ratio: float = 0.2,
                     start: Superquadric | None = None, reach: float = REACH_WEIGHT,
                     slack: float | None = None, surface_points: ArrayLike | None = None,
                     alternatives: bool = False, up: ArrayLike | None = None) -> FitResult:
    """The superquadric that best explains ``points`` (N, 3) m (cell centres) weighted by
    ``weights`` (N,) (occupancy probabilities; default 1), with the outlier model of the
    module doc. ``resolution`` (the cell size) floors the surface's spread. ``start``: a
    superquadric near the answer (a fit of most of the same cells), searched from alone.
    ``reach``: the weight of how far the shape reaches past its cells (module doc, "held
    to its cells"; 0: free to reach anywhere no cell says otherwise). ``slack``: cells (of
    ``resolution``) a cell centre may lie off the surface and still be on it (module doc,
    "cells, not points"; default :data:`CELL_SLACK`; 0 for points on the surface). Without
    ``start`` the search runs without it and the shape found is then fitted again with it.
    ``surface_points`` (N, 3): where in each cell the surface was measured (the map's
    contact centroids): the shape found on the cells is then fitted again to them, as points
    on the surface (no slack), with its ``alternatives`` (so for a fit from ``start``): from
    where it is and from its switched twin, from its pose and size with each exponent pair
    of :data:`SHAPE_STARTS` and their twins, and by a search of their own; the most likely
    (module doc, "Where the touches were"). ``up`` (3,): the object stands on a support
    whose normal this is (a static map): the same fit is also made with the shape held
    upright, one axis along ``up``, and taken when it explains the cells nearly as well
    (module doc, "Upright on a support"). ValueError for fewer than 10 points."""
    axis = None
    if up is not None:      # refused before any fit is made
        axis = np.asarray(up, dtype=float).reshape(3)
        if not np.linalg.norm(axis) > 0:
            raise ValueError(f'up {list(axis)}: must be a nonzero vector')
        axis = axis / np.linalg.norm(axis)
    fit = functools.partial(_fit_any, points, weights, resolution=resolution,
                            outlier_ratio=outlier_ratio, start=start, reach=reach, slack=slack,
                            surface_points=surface_points, alternatives=alternatives)
    found = fit()
    if axis is None or _tilt(found.superquadric, axis) <= UPRIGHT_TOLERANCE:
        return found
    upright = fit(about=axis)
    lost = (found.log_likelihood - upright.log_likelihood) / len(found.inlier)
    return upright if lost <= UPRIGHT_MARGIN else found


def _fit_any(points: ArrayLike, weights: ArrayLike | None = None, *,
             resolution: float = 0.005, outlier_ratio: float = 0.2,
             start: Superquadric | None = None, reach: float = REACH_WEIGHT,
             slack: float | None = None, surface_points: ArrayLike | None = None,
             alternatives: bool = False, about: Vector3 | None = None) -> FitResult:
    """:func:`fit_superquadric` without the upright alternative; ``about``: every shape of
    the fit held with one axis along this unit vector."""
    if surface_points is not None:
        found = _fit_any(points, weights, resolution=resolution, outlier_ratio=outlier_ratio,
                         start=start, reach=reach, slack=slack, about=about)
        return _fit_any(surface_points, weights, resolution=resolution,
                        outlier_ratio=outlier_ratio, start=found.superquadric, reach=reach,
                        slack=0.0, alternatives=True, about=about)
    cells, w, fit_cells, fit_weights = _prepared(points, weights)
    within = (CELL_SLACK if slack is None else slack) * resolution
    if start is None:
        found = _fit(cells, w, fit_cells, fit_weights, resolution, outlier_ratio, None, reach, 0.0,
                     about=about)
        if within <= 0.0:
            return found
        start = found.superquadric
    if not alternatives:
        return _fit(cells, w, fit_cells, fit_weights, resolution, outlier_ratio, start, reach,
                    within, about=about)
    starts = [start] + [Superquadric(start.size, shape, start.rotation, start.centre)
                        for shape in SHAPE_STARTS]
    fits = [_fit(cells, w, fit_cells, fit_weights, resolution, outlier_ratio, s, reach, within,
                 twin=True, about=about) for s in starts]
    fits.append(_fit_any(cells, w, resolution=resolution, outlier_ratio=outlier_ratio,
                         reach=reach, slack=slack, about=about))
    return max(fits, key=lambda fit: fit.log_likelihood)


def _fit(cells: Points, w: Weights, fit_cells: Points, fit_weights: Weights, resolution: float,
         outlier_ratio: float, start: Superquadric | None, reach: float, slack: float,
         twin: bool = False, about: Vector3 | None = None) -> FitResult:
    """:func:`fit_superquadric` with ``slack`` in metres: from ``start``, or searched for;
    ``twin``: from ``start`` and from its switched twin, the more likely; ``about``: held
    with one axis along it."""
    if start is None:
        # A few EM steps from each start, then the most likely one and its switched twin
        # carried on to convergence.
        states = [_em(fit_cells, fit_weights,
                      _state_of(Superquadric(half, (1.0, 1.0), frame, centre), fit_cells, resolution,
                                slack=slack, about=about),
                      resolution, outlier_ratio, EM_SCOUT_ITERATIONS, reach_weight=reach)
                  for centre, frame, half in _starts(fit_cells, fit_weights)]
        leader = max(states, key=lambda s: s.likelihood)
        candidates = [leader, _switched(leader)]
    else:
        candidates = [_state_of(start, fit_cells, resolution, slack=slack, about=about)]
        if twin:
            candidates.append(_switched(candidates[0]))
    # The cells' own spread is about a cell: a larger sigma would let one shape through
    # two parts pass for a fit of both.
    finals = [_em(fit_cells, fit_weights, state, resolution, outlier_ratio, EM_ITERATIONS,
                  sigma_cap=resolution, reach_weight=reach)
              for state in candidates]
    best = max(finals, key=lambda s: s.likelihood)
    sq, sigma, likelihood = best.packing.superquadric(best.x), best.sigma, best.likelihood
    # A side no cell shows (a static object's underside on the table) is where the search
    # left it, not where the cells say: cut back to where they end, when that keeps them.
    cut = _trimmed(sq, fit_cells, fit_weights, resolution)
    if cut is not None:
        keep = TRIM_KEEP * _on_share(sq, fit_cells, fit_weights, resolution)
        # as cut; else refitted from the cut (the search then starts on the cells' side)
        refitted = _em(fit_cells, fit_weights, _state_of(cut, fit_cells, resolution, sigma, slack, about),
                       resolution, outlier_ratio, TRIM_ITERATIONS, sigma_cap=resolution,
                       reach_weight=reach)
        for candidate, state in ((cut, None), (refitted.packing.superquadric(refitted.x), refitted)):
            if _on_share(candidate, fit_cells, fit_weights, resolution) >= keep:
                sq = candidate
                if state is not None:
                    sigma, likelihood = state.sigma, state.likelihood
                break
    span = np.prod(np.maximum(np.ptp(cells, axis=0), resolution))
    posterior, _ = _mixture(_beyond_slack(sq.distance(cells), slack), sigma, outlier_ratio, 1.0 / span)
    return _result(sq, cells, w, sigma, posterior, resolution, likelihood)


def fit_least_squares(points: ArrayLike, weights: ArrayLike | None = None, *,
                      resolution: float = 0.005) -> FitResult:
    """The classic fit (Solina and Bajcsy 1990, module doc) from the same starts; every cell
    counts as surface."""
    cells, w, fit_cells, fit_weights = _prepared(points, weights)
    scale = np.sqrt(fit_weights)
    best: tuple[float, Superquadric] | None = None
    for centre, frame, half in _starts(fit_cells, fit_weights):
        packing = _packing(fit_cells, frame, resolution)

        def residuals(v: Floats, packing: _Parameters = packing) -> Floats:
            rotation = packing.base @ _rotation_matrix(v[5:8])
            local = (fit_cells - v[8:11]) @ rotation
            f = np.exp(v[3] * _log_inside_outside(local, np.exp(v[:3]), v[3], v[4]))
            return np.asarray(scale * math.sqrt(float(np.exp(v[:3]).prod())) * (f - 1))

        fit = least_squares(residuals, packing.vector(half, (1.0, 1.0), centre),
                            bounds=(packing.lower, packing.upper), max_nfev=300, x_scale='jac')
        if best is None or fit.cost < best[0]:
            best = (float(fit.cost), packing.superquadric(fit.x))
    assert best is not None
    sq = best[1]
    d = sq.distance(cells)
    sigma = max(math.sqrt(float(np.average(d ** 2, weights=w))), resolution / 2)
    return _result(sq, cells, w, sigma, np.ones(len(cells)), resolution, float('nan'))
