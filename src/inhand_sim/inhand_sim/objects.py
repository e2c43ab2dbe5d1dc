"""Object models with exact ground truth: unions of analytic primitives.

:class:`SolidObject` is what the exploration, the sessions, the ground truth and the stereo
rig ask of any object (this module's unions of primitives, and the triangle meshes of
:mod:`inhand_sim.mesh_objects`). Every object here is a union of primitives, each with a
signed distance function (negative inside), an exact uniform-by-area surface sampler and an
exact area. Coordinates are in
metres in the OBJECT frame, which is the frame of the object's tracker sensor: the origin is
where that sensor is mounted (the cat's belly, the bottle's side, the mug's underside) and
+z is the object's "up" (away from the table it stands on).

Distances, and what is exact:

* ``Sphere``, ``RoundCone`` (convex hull of two spheres: capsules, tapered legs, ears,
  the bottle's shoulder), ``RevolvedBox`` (a rounded rectangle revolved about an axis: solid
  cylinders with rounded edges, or a tube: the mug's wall) and ``ArcTube`` (a tube around a
  circular arc: the mug's handle) have exact signed distances.
* ``Ellipsoid`` (the cat's body, head and muzzle) uses bounds. With ``q = p / radii`` (the
  point where the ellipsoid is the unit sphere) and ``f = |q| - 1``: outside,
  ``f / |grad f|``, a lower bound of the distance because ``f`` is convex (the tangent plane
  at ``p`` stays below ``f``), exact along the axes and first-order exact at the surface;
  inside, ``min(radii) * f``, a lower bound of the depth (the map to ``q`` shrinks lengths
  by at most ``1 / min(radii)``). Both are zero exactly on the surface, with the right sign.
* The union is ``min`` over the primitives: outside the object that is the exact distance
  to the union (to the nearest primitive), inside it is a lower bound of the depth.

So for every object ``|sdf(p)|`` never exceeds the true distance to the surface and is
exact outside objects made only of exact primitives (bottle, mug): ``sdf(p) >= 5 mm``
guarantees a point at least 5 mm off the surface.

Surface sampling is uniform by area: each primitive's surface is sampled uniformly (in
proportion to its area) and samples strictly inside another primitive are rejected; what
remains is uniform on the union's boundary.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    'NOMINAL_SIZES',
    'OBJECT_NAMES',
    'ArcTube',
    'Ellipsoid',
    'HeldRegion',
    'ObjectModel',
    'Primitive',
    'RevolvedBox',
    'RoundCone',
    'SolidObject',
    'Sphere',
    'get_object',
]

CM = 0.01


def _normalize(v: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(norm, 1e-300)


def _perpendicular_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing ``axis`` (unit) to a right-handed orthonormal basis."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = _normalize(np.cross(axis, helper))
    e2 = np.cross(axis, e1)
    return e1, e2


def _frame_with_axis(axis) -> np.ndarray:
    """Rotation matrix whose third column is ``axis`` (normalised)."""
    axis = _normalize(np.asarray(axis, dtype=float))
    e1, e2 = _perpendicular_basis(axis)
    return np.stack([e1, e2, axis], axis=1)


def _radial_units(local_xy: np.ndarray) -> np.ndarray:
    """Unit radial vectors (N, 3) in a local frame from (N, 2) x, y; +x on the axis."""
    rho = np.hypot(local_xy[:, 0], local_xy[:, 1])
    safe = np.where(rho > 1e-15, rho, 1.0)
    out = np.zeros((len(local_xy), 3))
    out[:, 0] = np.where(rho > 1e-15, local_xy[:, 0] / safe, 1.0)
    out[:, 1] = np.where(rho > 1e-15, local_xy[:, 1] / safe, 0.0)
    return out


def _uniform_directions(n: int, rng: np.random.Generator) -> np.ndarray:
    return _normalize(rng.normal(size=(n, 3)))


def _rejection(n: int, rng: np.random.Generator, propose, accept_probability) -> np.ndarray:
    """``n`` draws of ``propose(m)`` (an (m, k) array) thinned by ``accept_probability``."""
    chunks, have = [], 0
    while have < n:
        m = max(64, int(1.3 * (n - have)) + 16)
        candidates = propose(m)
        keep = rng.random(m) < accept_probability(candidates)
        chunks.append(candidates[keep])
        have += int(keep.sum())
    return np.concatenate(chunks)[:n]


class Primitive:
    """A solid with a signed distance (or a bound of it) and an area-uniform sampler."""

    area: float

    def sdf_grad(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (N,) and its gradient (N, 3) at points (N, 3)."""
        raise NotImplementedError

    def sdf(self, p: np.ndarray) -> np.ndarray:
        return self.sdf_grad(p)[0]

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``n`` points uniform by area on the primitive's surface, with outward normals."""
        raise NotImplementedError

    def bounds(self) -> np.ndarray:
        """Axis-aligned bounding box, (2, 3): min and max corners."""
        raise NotImplementedError


class Sphere(Primitive):
    def __init__(self, centre, radius: float):
        self.centre = np.asarray(centre, dtype=float)
        self.radius = float(radius)
        self.area = 4.0 * math.pi * self.radius ** 2

    def sdf_grad(self, p):
        v = p - self.centre
        d = np.linalg.norm(v, axis=1)
        return d - self.radius, _normalize(v)

    def sample(self, n, rng):
        m = _uniform_directions(n, rng)
        return self.centre + self.radius * m, m

    def bounds(self):
        return np.stack([self.centre - self.radius, self.centre + self.radius])


class RoundCone(Primitive):
    """Convex hull of the spheres (a, r1) and (b, r2): a capsule when r1 == r2. Exact SDF."""

    def __init__(self, a, b, r1: float, r2: float):
        self.a = np.asarray(a, dtype=float)
        self.b = np.asarray(b, dtype=float)
        self.r1, self.r2 = float(r1), float(r2)
        ba = self.b - self.a
        self.length = float(np.linalg.norm(ba))
        if self.length <= abs(self.r1 - self.r2):
            raise ValueError('RoundCone: one sphere contains the other; use a Sphere')
        self.axis = ba / self.length
        self.s = (self.r1 - self.r2) / self.length  # axial component of the lateral normal
        self.c = math.sqrt(1.0 - self.s ** 2)        # radial component
        self.e1, self.e2 = _perpendicular_basis(self.axis)
        self.area_a = 2.0 * math.pi * self.r1 ** 2 * (1.0 + self.s)
        self.area_b = 2.0 * math.pi * self.r2 ** 2 * (1.0 - self.s)
        self.area_lateral = math.pi * self.c ** 2 * self.length * (self.r1 + self.r2)
        self.area = self.area_a + self.area_b + self.area_lateral

    def sdf_grad(self, p):
        pa = p - self.a
        y = pa @ self.axis
        radial = pa - y[:, None] * self.axis
        x = np.linalg.norm(radial, axis=1)
        e_r = np.where(x[:, None] > 1e-15, radial / np.maximum(x, 1e-300)[:, None], self.e1)
        w = y * self.c - x * self.s  # coordinate along the lateral line, from a's tangent point
        in_a = w < 0.0
        in_b = w > self.length * self.c
        pb = p - self.b
        da = np.linalg.norm(pa, axis=1)
        db = np.linalg.norm(pb, axis=1)
        d = np.where(in_a, da - self.r1,
                     np.where(in_b, db - self.r2, y * self.s + x * self.c - self.r1))
        g_lat = self.s * self.axis + self.c * e_r
        g = np.where(in_a[:, None], _normalize(pa), np.where(in_b[:, None], _normalize(pb), g_lat))
        return d, g

    def _cap(self, n, rng, centre, radius, lo, hi):
        mu = rng.uniform(lo, hi, n)
        phi = rng.uniform(0.0, 2.0 * math.pi, n)
        ring = np.sqrt(np.maximum(1.0 - mu ** 2, 0.0))
        m = (mu[:, None] * self.axis + (ring * np.cos(phi))[:, None] * self.e1
             + (ring * np.sin(phi))[:, None] * self.e2)
        return centre + radius * m, m

    def sample(self, n, rng):
        counts = rng.multinomial(n, np.array([self.area_a, self.area_b, self.area_lateral]) / self.area)
        pa, na = self._cap(counts[0], rng, self.a, self.r1, -1.0, self.s)
        pb, nb = self._cap(counts[1], rng, self.b, self.r2, self.s, 1.0)
        # Lateral: t along the slant with density proportional to the radius there.
        u = rng.random(counts[2])
        k = self.r2 - self.r1
        c_ = u * (self.r1 + 0.5 * k)
        t = 2.0 * c_ / (self.r1 + np.sqrt(np.maximum(self.r1 ** 2 + 2.0 * k * c_, 0.0)))
        phi = rng.uniform(0.0, 2.0 * math.pi, counts[2])
        e_r = np.cos(phi)[:, None] * self.e1 + np.sin(phi)[:, None] * self.e2
        normal = self.s * self.axis + self.c * e_r
        radius = self.r1 + t * k
        pl = self.a + t[:, None] * (self.b - self.a) + radius[:, None] * normal
        points = np.concatenate([pa, pb, pl])
        normals = np.concatenate([na, nb, normal])
        order = rng.permutation(n)
        return points[order], normals[order]

    def bounds(self):
        lo = np.minimum(self.a - self.r1, self.b - self.r2)
        hi = np.maximum(self.a + self.r1, self.b + self.r2)
        return np.stack([lo, hi])


def _round_cones_sdf_grad(k: dict, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Min over several round cones at once (same formulas as RoundCone.sdf_grad)."""
    pa = p[:, None, :] - k['a'][None]                        # (N, P, 3)
    y = np.einsum('npk,pk->np', pa, k['axis'])
    radial = pa - y[..., None] * k['axis'][None]
    x = np.sqrt(np.einsum('npk,npk->np', radial, radial))
    pb = p[:, None, :] - k['b'][None]
    da = np.sqrt(np.einsum('npk,npk->np', pa, pa))
    db = np.sqrt(np.einsum('npk,npk->np', pb, pb))
    w = y * k['c'] - x * k['s']
    in_a = w < 0.0
    in_b = w > k['length'] * k['c']
    d = np.where(in_a, da - k['r1'], np.where(in_b, db - k['r2'],
                                              y * k['s'] + x * k['c'] - k['r1']))
    best = np.argmin(d, axis=1)
    rows = np.arange(len(p))
    dmin = d[rows, best]
    xb = x[rows, best]
    e_r = np.where((xb > 1e-15)[:, None], radial[rows, best] / np.maximum(xb, 1e-300)[:, None],
                   k['e1'][best])
    g_lat = k['s'][best, None] * k['axis'][best] + k['c'][best, None] * e_r
    ga = pa[rows, best] / np.maximum(da[rows, best], 1e-300)[:, None]
    gb = pb[rows, best] / np.maximum(db[rows, best], 1e-300)[:, None]
    g = np.where(in_a[rows, best][:, None], ga, np.where(in_b[rows, best][:, None], gb, g_lat))
    return dmin, g


class Ellipsoid(Primitive):
    """Ellipsoid with semi-axes ``radii`` along the columns of ``rotation``.

    Distance bounds (see the module docstring): outside ``k0 (k0 - 1) / k1`` with
    ``k0 = |p / r|``, ``k1 = |p / r^2|`` (the first-order distance ``f / |grad f|`` of the
    convex ``f = k0 - 1``, which convexity makes a lower bound; exact on the axes, within a
    few percent near the surface); inside ``min(radii) (k0 - 1)``."""

    def __init__(self, centre, radii, rotation=None):
        self.centre = np.asarray(centre, dtype=float)
        self.radii = np.asarray(radii, dtype=float)
        self.rotation = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
        self.min_radius = float(self.radii.min())
        r0, r1, r2 = self.radii
        self._factor_max = r0 * r1 * r2 / self.min_radius
        # Area: the sphere-to-ellipsoid area factor integrated by Gauss-Legendre in cos(theta)
        # and the midpoint rule in phi (smooth and periodic: converged to ~1e-12 here).
        mu, wmu = np.polynomial.legendre.leggauss(96)
        phi = (np.arange(192) + 0.5) * (2.0 * math.pi / 192)
        mu_g, phi_g = np.meshgrid(mu, phi, indexing='ij')
        st = np.sqrt(1.0 - mu_g ** 2)
        u = np.stack([st * np.cos(phi_g), st * np.sin(phi_g), mu_g], axis=-1)
        factor = self._area_factor(u.reshape(-1, 3)).reshape(96, 192)
        self.area = float((factor * wmu[:, None]).sum() * (2.0 * math.pi / 192))

    def _area_factor(self, u):
        return np.prod(self.radii) * np.linalg.norm(u / self.radii, axis=1)

    def sdf_grad(self, p):
        local = (p - self.centre) @ self.rotation
        k0 = np.linalg.norm(local / self.radii, axis=1)
        over_r2 = local / self.radii ** 2
        k1 = np.linalg.norm(over_r2, axis=1)
        outside = k0 > 1.0
        safe_k0 = np.maximum(k0, 1e-300)
        d = np.where(outside, k0 * (k0 - 1.0) / np.maximum(k1, 1e-300),
                     self.min_radius * (k0 - 1.0))
        g_in = self.min_radius * over_r2 / safe_k0[:, None]
        g = np.where(outside[:, None], _normalize(over_r2), g_in)
        return d, g @ self.rotation.T

    def sample(self, n, rng):
        u = _rejection(n, rng, lambda m: _uniform_directions(m, rng),
                       lambda c: self._area_factor(c) / self._factor_max)
        local = u * self.radii
        normal = _normalize(u / self.radii)
        return self.centre + local @ self.rotation.T, normal @ self.rotation.T

    def bounds(self):
        half = np.sqrt(((self.rotation * self.radii) ** 2).sum(axis=1))
        return np.stack([self.centre - half, self.centre + half])


@dataclass(frozen=True)
class _ProfilePiece:
    """A piece of a profile boundary in the (rho, z) half-plane: a segment or an arc."""
    kind: str            # 'line' or 'arc'
    a: tuple             # line: start (rho, z); arc: centre (rho, z)
    b: tuple             # line: end (rho, z);   arc: (radius, unused)
    normal: tuple = (0.0, 0.0)   # line: outward normal in (rho, z)
    angles: tuple = (0.0, 0.0)   # arc: phi0, phi1 (point = centre + radius (cos, sin))

    def area(self) -> float:
        if self.kind == 'line':
            length = math.dist(self.a, self.b)
            return 2.0 * math.pi * length * 0.5 * (self.a[0] + self.b[0])
        (rc, _), (r, _) = self.a, self.b
        f0, f1 = self.angles
        return 2.0 * math.pi * r * (rc * (f1 - f0) + r * (math.sin(f1) - math.sin(f0)))

    def rho_max(self) -> float:
        if self.kind == 'line':
            return max(self.a[0], self.b[0])
        return self.a[0] + self.b[0]

    def points(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(rho, z, n_rho, n_z) at parameters t in [0, 1], uniform in arc length."""
        if self.kind == 'line':
            rho = self.a[0] + t * (self.b[0] - self.a[0])
            z = self.a[1] + t * (self.b[1] - self.a[1])
            return rho, z, np.full_like(t, self.normal[0]), np.full_like(t, self.normal[1])
        (rc, zc), (r, _) = self.a, self.b
        phi = self.angles[0] + t * (self.angles[1] - self.angles[0])
        return rc + r * np.cos(phi), zc + r * np.sin(phi), np.cos(phi), np.sin(phi)


class RevolvedBox(Primitive):
    """A rounded rectangle in the (radius, height) plane revolved about an axis. Exact SDF.

    ``inner_radius == 0``: a solid cylinder of ``outer_radius`` from ``z0`` to ``z1`` along
    the axis with edges rounded by ``rounding``. ``inner_radius > 0``: a tube (wall between
    the two radii) with all four edges rounded.
    """

    def __init__(self, origin, axis, outer_radius: float, z0: float, z1: float,
                 rounding: float = 0.0, inner_radius: float = 0.0):
        self.origin = np.asarray(origin, dtype=float)
        self.rotation = _frame_with_axis(axis)
        self.r_in, self.r_out = float(inner_radius), float(outer_radius)
        self.z0, self.z1 = float(z0), float(z1)
        self.rounding = float(rounding)
        rr = self.rounding
        half_z = 0.5 * (self.z1 - self.z0)
        if self.r_in > 0.0:
            half_r = 0.5 * (self.r_out - self.r_in)
            self._centre = (0.5 * (self.r_in + self.r_out), 0.5 * (self.z0 + self.z1))
        else:
            half_r = self.r_out
            self._centre = (0.0, 0.5 * (self.z0 + self.z1))
        if rr < 0 or rr > min(half_r, half_z) + 1e-12:
            raise ValueError('RevolvedBox: rounding must be within the half sizes')
        self._half = (max(half_r - rr, 0.0), max(half_z - rr, 0.0))
        pieces = []
        ro, ri, z0, z1 = self.r_out, self.r_in, self.z0, self.z1
        hp = 0.5 * math.pi
        if ri > 0.0:
            pieces.append(_ProfilePiece('line', (ri + rr, z0), (ro - rr, z0), (0.0, -1.0)))
        else:
            pieces.append(_ProfilePiece('line', (0.0, z0), (ro - rr, z0), (0.0, -1.0)))
        pieces += [
            _ProfilePiece('arc', (ro - rr, z0 + rr), (rr, 0.0), angles=(-hp, 0.0)),
            _ProfilePiece('line', (ro, z0 + rr), (ro, z1 - rr), (1.0, 0.0)),
            _ProfilePiece('arc', (ro - rr, z1 - rr), (rr, 0.0), angles=(0.0, hp)),
        ]
        if ri > 0.0:
            pieces += [
                _ProfilePiece('line', (ro - rr, z1), (ri + rr, z1), (0.0, 1.0)),
                _ProfilePiece('arc', (ri + rr, z1 - rr), (rr, 0.0), angles=(hp, math.pi)),
                _ProfilePiece('line', (ri, z1 - rr), (ri, z0 + rr), (-1.0, 0.0)),
                _ProfilePiece('arc', (ri + rr, z0 + rr), (rr, 0.0), angles=(math.pi, 3 * hp)),
            ]
        else:
            pieces.append(_ProfilePiece('line', (ro - rr, z1), (0.0, z1), (0.0, 1.0)))
        self.pieces = [p for p in pieces if p.area() > 0.0]
        self.piece_areas = np.array([p.area() for p in self.pieces])
        self.area = float(self.piece_areas.sum())

    def sdf_grad(self, p):
        local = (p - self.origin) @ self.rotation
        rho = np.hypot(local[:, 0], local[:, 1])
        e_r = _radial_units(local[:, :2])
        dr = rho - self._centre[0]
        dz = local[:, 2] - self._centre[1]
        qx = np.abs(dr) - self._half[0]
        qz = np.abs(dz) - self._half[1]
        ox, oz = np.maximum(qx, 0.0), np.maximum(qz, 0.0)
        outside = np.hypot(ox, oz)
        d = outside + np.minimum(np.maximum(qx, qz), 0.0) - self.rounding
        sx, sz = np.where(dr >= 0, 1.0, -1.0), np.where(dz >= 0, 1.0, -1.0)
        is_out = outside > 0.0
        safe = np.where(is_out, outside, 1.0)
        gx = np.where(is_out, ox / safe, (qx >= qz).astype(float)) * sx
        gz = np.where(is_out, oz / safe, (qx < qz).astype(float)) * sz
        g_local = gx[:, None] * e_r
        g_local[:, 2] = gz
        return d, g_local @ self.rotation.T

    def sample(self, n, rng):
        counts = rng.multinomial(n, self.piece_areas / self.area)
        pts, nrm = [], []
        for piece, count in zip(self.pieces, counts):
            if not count:
                continue
            rho_max = piece.rho_max()
            t = _rejection(count, rng, lambda m: rng.random((m, 1)),
                           lambda c, piece=piece, rho_max=rho_max:
                           piece.points(c[:, 0])[0] / rho_max)[:, 0]
            rho, z, n_rho, n_z = piece.points(t)
            psi = rng.uniform(0.0, 2.0 * math.pi, count)
            cos, sin = np.cos(psi), np.sin(psi)
            pts.append(np.stack([rho * cos, rho * sin, z], axis=1))
            nrm.append(np.stack([n_rho * cos, n_rho * sin, n_z], axis=1))
        points = np.concatenate(pts) @ self.rotation.T + self.origin
        normals = np.concatenate(nrm) @ self.rotation.T
        order = rng.permutation(n)
        return points[order], normals[order]

    def bounds(self):
        axis = self.rotation[:, 2]
        ends = np.stack([self.origin + self.z0 * axis, self.origin + self.z1 * axis])
        spread = self.r_out * np.sqrt(np.maximum(1.0 - axis ** 2, 0.0))
        return np.stack([ends.min(axis=0) - spread, ends.max(axis=0) + spread])


class ArcTube(Primitive):
    """A tube of radius ``tube_radius`` around a circular arc, with round ends. Exact SDF.

    The arc has radius ``arc_radius`` about ``centre`` in the plane of the first two columns
    of ``rotation``, from angle ``-half_angle`` to ``+half_angle`` about the first column.
    """

    def __init__(self, centre, rotation, arc_radius: float, tube_radius: float,
                 half_angle: float):
        self.centre = np.asarray(centre, dtype=float)
        self.rotation = np.asarray(rotation, dtype=float)
        self.ra, self.rb, self.alpha = float(arc_radius), float(tube_radius), float(half_angle)
        if not (0.0 < self.rb < self.ra) or not (0.0 < self.alpha < math.pi):
            raise ValueError('ArcTube: need 0 < tube_radius < arc_radius, 0 < half_angle < pi')
        self.area_lateral = 2.0 * self.alpha * 2.0 * math.pi * self.ra * self.rb
        self.area_cap = 2.0 * math.pi * self.rb ** 2
        self.area = self.area_lateral + 2.0 * self.area_cap

    def _ends(self):
        a = self.alpha
        return (np.array([math.cos(a), math.sin(a), 0.0]) * self.ra,
                np.array([math.cos(a), -math.sin(a), 0.0]) * self.ra)

    def sdf_grad(self, p):
        local = (p - self.centre) @ self.rotation
        theta = np.arctan2(local[:, 1], local[:, 0])
        on_arc = np.abs(theta) <= self.alpha
        nearest = np.zeros_like(local)
        nearest[:, 0] = self.ra * np.cos(np.clip(theta, -self.alpha, self.alpha))
        nearest[:, 1] = self.ra * np.sin(np.clip(theta, -self.alpha, self.alpha))
        # Beyond the arc the nearest arc point is one of its ends (the distance grows with
        # the angular difference): take the nearer of the two.
        plus, minus = self._ends()
        behind = ~on_arc
        if behind.any():
            dp = np.linalg.norm(local[behind] - plus, axis=1)
            dm = np.linalg.norm(local[behind] - minus, axis=1)
            nearest[behind] = np.where((dp <= dm)[:, None], plus, minus)
        v = local - nearest
        d = np.linalg.norm(v, axis=1) - self.rb
        return d, _normalize(v) @ self.rotation.T

    def sample(self, n, rng):
        counts = rng.multinomial(n, np.array([self.area_lateral, self.area_cap, self.area_cap])
                                 / self.area)
        m = counts[0]
        phi = _rejection(m, rng, lambda k: rng.uniform(-math.pi, math.pi, (k, 1)),
                         lambda c: (self.ra + self.rb * np.cos(c[:, 0])) / (self.ra + self.rb))[:, 0]
        theta = rng.uniform(-self.alpha, self.alpha, m)
        radial = np.stack([np.cos(theta), np.sin(theta), np.zeros(m)], axis=1)
        normal = np.cos(phi)[:, None] * radial
        normal[:, 2] = np.sin(phi)
        lateral = self.ra * radial + self.rb * normal
        pts, nrm = [lateral], [normal]
        for count, end, sign in ((counts[1], self._ends()[0], 1.0), (counts[2], self._ends()[1], -1.0)):
            angle = sign * self.alpha
            outward = sign * np.array([-math.sin(angle), math.cos(angle), 0.0])
            e1, e2 = _perpendicular_basis(outward)
            mu = rng.random(count)
            psi = rng.uniform(0.0, 2.0 * math.pi, count)
            ring = np.sqrt(1.0 - mu ** 2)
            mm = (mu[:, None] * outward + (ring * np.cos(psi))[:, None] * e1
                  + (ring * np.sin(psi))[:, None] * e2)
            pts.append(end + self.rb * mm)
            nrm.append(mm)
        points = np.concatenate(pts) @ self.rotation.T + self.centre
        normals = np.concatenate(nrm) @ self.rotation.T
        order = rng.permutation(n)
        return points[order], normals[order]

    def bounds(self):
        theta = np.linspace(-self.alpha, self.alpha, 20001)
        arc = self.ra * np.stack([np.cos(theta), np.sin(theta), np.zeros_like(theta)], axis=1)
        world = arc @ self.rotation.T + self.centre
        return np.stack([world.min(axis=0) - self.rb, world.max(axis=0) + self.rb])


@dataclass(frozen=True)
class HeldRegion:
    """Where the other hand holds the object: a union of balls (centres (K, 3), radii (K,)),
    object frame. Fingertips of the exploring hand do not touch the surface inside it."""
    name: str
    centres: tuple
    radii: tuple

    def contains(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        inside = np.zeros(len(points), dtype=bool)
        for centre, radius in zip(self.centres, self.radii):
            inside |= np.sum((points - np.asarray(centre)) ** 2, axis=1) < radius ** 2
        return inside


class SolidObject:
    """What the exploration, the sessions, the ground truth and the stereo rig ask of an
    object, whatever it is made of (a union of primitives here, a triangle mesh in
    :mod:`inhand_sim.mesh_objects`). Coordinates are metres in its OBJECT frame (the object
    sensor's frame), +z up.

    ``table_z``: height of the plane the object stands on; ``static_grip``: where the other
    hand holds it on the table; ``moving_grips``: the successive grips of a hand-held
    session (one more at each re-grasp, cycling); ``second_sensor``: pose (position,
    quaternion x, y, z, w) of a second object sensor rigidly attached to it; ``texture``:
    its painting in :mod:`inhand_sim.textures`.
    """
    name: str
    table_z: float
    static_grip: HeldRegion
    moving_grips: list
    second_sensor: tuple
    nominal_size: tuple
    description: str

    @property
    def texture(self) -> str:
        return self.name

    def sdf_grad(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (N,) (negative inside) and its gradient (N, 3) at points (N, 3)."""
        raise NotImplementedError

    def sdf(self, points) -> np.ndarray:
        return self.sdf_grad(points)[0]

    def normals(self, points) -> np.ndarray:
        """Outward unit normals (normalised SDF gradient) at points on or near the surface."""
        return _normalize(self.sdf_grad(points)[1])

    def project_to_surface(self, points) -> np.ndarray:
        """The surface points nearest to ``points`` (N, 3), on the surface itself."""
        raise NotImplementedError

    def sample_surface(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``n`` points (n, 3) uniform by area on the surface and their outward normals."""
        raise NotImplementedError

    def surface_area(self) -> float:
        """Area of the surface, m^2."""
        raise NotImplementedError

    @property
    def bounds(self) -> np.ndarray:
        """Axis-aligned bounding box (2, 3), object frame."""
        raise NotImplementedError

    @property
    def centre(self) -> np.ndarray:
        """Centre of the bounding box, object frame."""
        return self.bounds.mean(axis=0)

    @property
    def size(self) -> np.ndarray:
        return self.bounds[1] - self.bounds[0]

    def _newton(self, p: np.ndarray, iterations: int, tolerance: float) -> np.ndarray:
        """Newton steps ``p <- p - f grad f / |grad f|^2`` along the SDF gradient (in place)
        until ``|f| < tolerance``: onto the zero set of :meth:`sdf_grad`."""
        active = np.arange(len(p))
        for _ in range(iterations):
            d, g = self.sdf_grad(p[active])
            todo = np.abs(d) >= tolerance
            if not todo.any():
                break
            active, d, g = active[todo], d[todo], g[todo]
            g2 = np.maximum(np.sum(g * g, axis=1), 1e-300)
            p[active] -= (d / g2)[:, None] * g
        return p


@dataclass
class ObjectModel(SolidObject):
    """A named union of primitives in its OBJECT frame (origin at the object sensor, +z up);
    the fields as :class:`SolidObject` has them."""
    name: str
    primitives: list
    table_z: float
    static_grip: HeldRegion
    moving_grips: list
    second_sensor: tuple
    nominal_size: tuple
    description: str = ''
    _bounds: np.ndarray = field(default=None, repr=False)

    # --- distances -------------------------------------------------------------------------
    def sdf_grad(self, points, chunk: int = 65536) -> tuple[np.ndarray, np.ndarray]:
        """Union SDF (negative inside: exact outside exact primitives, a lower bound of the
        distance otherwise, see the module docstring) and its gradient (unit for exact
        primitives)."""
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        n = len(points)
        d = np.full(n, np.inf)
        g = np.zeros((n, 3))
        cones, others = self._groups()
        for start in range(0, n, chunk):
            sl = slice(start, start + chunk)
            p = points[sl]
            dd, gg = d[sl], g[sl]
            parts = [prim.sdf_grad(p) for prim in others]
            if cones is not None:
                parts.append(_round_cones_sdf_grad(cones, p))
            for di, gi in parts:
                better = di < dd
                dd[better] = di[better]
                gg[better] = gi[better]
        return d, g

    def _groups(self):
        """Round cones evaluated together (one numpy pass for all), the rest one by one."""
        if getattr(self, '_group_cache', None) is None:
            cones = [p for p in self.primitives if isinstance(p, RoundCone)]
            others = [p for p in self.primitives if not isinstance(p, RoundCone)]
            packed = None
            if cones:
                packed = {k: np.array([getattr(c, k) for c in cones])
                          for k in ('a', 'b', 'axis', 'e1', 'r1', 'r2', 's', 'c', 'length')}
            self._group_cache = (packed, others)
        return self._group_cache

    def project_to_surface(self, points, iterations: int = 30, tolerance: float = 1e-12
                           ) -> np.ndarray:
        """Points moved onto the surface by Newton steps along the SDF gradient,
        ``p <- p - f grad f / |grad f|^2``, until ``|f| < tolerance`` (about 3 steps from a
        millimetre away). Near the surface this is the nearest surface point (exactly so
        for exact primitives). A point deep inside two overlapping primitives can bounce
        between their boundaries: such rare points restart from the nearest of a fixed set
        of surface samples."""
        p = self._newton(np.array(points, dtype=float).reshape(-1, 3), iterations, tolerance)
        d = self.sdf(p)
        stuck = np.flatnonzero(np.abs(d) >= max(tolerance, 1e-9))
        if stuck.size:
            anchors = self._anchors()
            for i in stuck:
                p[i] = anchors[np.argmin(np.sum((anchors - p[i]) ** 2, axis=1))]
            p[stuck] = self._newton(p[stuck], iterations, tolerance)
        return p

    def _anchors(self) -> np.ndarray:
        if getattr(self, '_anchor_points', None) is None:
            self._anchor_points = self.sample_surface(20_000, np.random.default_rng(12345))[0]
        return self._anchor_points

    # --- surface sampling ------------------------------------------------------------------
    def sample_surface(self, n: int, rng: np.random.Generator
                       ) -> tuple[np.ndarray, np.ndarray]:
        """``n`` points (n, 3) uniform by area on the object's surface and their outward
        normals: primitives sampled in proportion to their areas, samples strictly inside
        another primitive rejected."""
        areas = np.array([p.area for p in self.primitives])
        weights = areas / areas.sum()
        got_p, got_n, have = [], [], 0
        accept_rate = 0.7
        while have < n:
            m = int((n - have) / accept_rate * 1.1) + 256
            counts = rng.multinomial(m, weights)
            for i, (prim, count) in enumerate(zip(self.primitives, counts)):
                if not count:
                    continue
                pts, nrm = prim.sample(int(count), rng)
                keep = np.ones(len(pts), dtype=bool)
                for j, other in enumerate(self.primitives):
                    if j != i:
                        keep &= other.sdf(pts) > -1e-12
                got_p.append(pts[keep])
                got_n.append(nrm[keep])
                have += int(keep.sum())
            accept_rate = max(0.05, min(1.0, have / max(m, 1)))
        points = np.concatenate(got_p)
        normals = np.concatenate(got_n)
        order = rng.permutation(len(points))[:n]
        return points[order], normals[order]

    def surface_area(self, samples: int = 200_000, seed: int = 0) -> float:
        """Area of the union's surface (m^2): primitive areas times their kept fractions."""
        rng = np.random.default_rng(seed)
        total = 0.0
        for i, prim in enumerate(self.primitives):
            pts, _ = prim.sample(samples // len(self.primitives), rng)
            keep = np.ones(len(pts), dtype=bool)
            for j, other in enumerate(self.primitives):
                if j != i:
                    keep &= other.sdf(pts) > -1e-12
            total += prim.area * keep.mean()
        return total

    @property
    def bounds(self) -> np.ndarray:
        """Axis-aligned bounding box (2, 3), object frame. Exact: a primitive's extreme point
        inside another primitive would make that one extend further."""
        if self._bounds is None:
            boxes = np.stack([p.bounds() for p in self.primitives])
            self._bounds = np.stack([boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)])
        return self._bounds


# --- the objects ---------------------------------------------------------------------------

def _cm(*values) -> np.ndarray:
    return np.asarray(values, dtype=float) * CM


def _shifted(offset_cm):
    """Helper: natural coordinates in cm (table at z = 0) -> object frame in metres."""
    offset = np.asarray(offset_cm, dtype=float) * CM

    def at(x, y, z):
        return np.array([x, y, z], dtype=float) * CM - offset
    return at, offset


def make_cat() -> ObjectModel:
    """A wooden-cat-like figure standing on four legs, about 12.8 x 5.6 x 10.3 cm
    (nose to tail, flank to flank, feet to ear tips). Object frame: the sensor on the belly
    (underside of the body, between the legs); x towards the head, z up."""
    at, offset = _shifted((0.0, 0.0, 2.5))
    prims = [
        Ellipsoid(at(0.0, 0.0, 4.6), _cm(4.3, 2.8, 2.1)),                 # body
        Ellipsoid(at(4.4, 0.0, 7.6), _cm(1.9, 2.0, 1.75)),                # head
        Ellipsoid(at(5.95, 0.0, 7.1), _cm(0.75, 1.0, 0.65)),              # muzzle
        RoundCone(at(3.1, 0.0, 5.4), at(4.1, 0.0, 6.9), 1.55 * CM, 1.3 * CM),  # neck
    ]
    for side in (1.0, -1.0):
        prims.append(RoundCone(at(4.1, side * 1.1, 8.7), at(3.9, side * 1.45, 10.1),
                               0.75 * CM, 0.18 * CM))                      # ears
    for fx in (2.7, -2.7):
        for side in (1.0, -1.0):
            prims.append(RoundCone(at(fx, side * 1.45, 3.6), at(fx + 0.1, side * 1.65, 0.7),
                                   0.9 * CM, 0.7 * CM))                    # legs
    tail = [((-3.9, 0.0, 5.0), 0.6), ((-5.2, 0.0, 5.6), 0.5), ((-5.8, 0.0, 7.0), 0.45),
            ((-5.5, 0.0, 8.3), 0.4)]
    for (p0, r0), (p1, r1) in zip(tail[:-1], tail[1:]):
        prims.append(RoundCone(at(*p0), at(*p1), r0 * CM, r1 * CM))        # tail
    back = HeldRegion('back', (tuple(at(-0.5, 0.0, 8.0)),), (0.027,))
    below = HeldRegion('belly and legs', (tuple(at(0.0, 0.0, 1.6)),), (0.032,))
    rear = HeldRegion('rear and tail', (tuple(at(-4.8, 0.0, 5.2)),), (0.027,))
    return ObjectModel(
        name='cat', primitives=prims, table_z=float(-offset[2]), static_grip=back,
        moving_grips=[back, below, rear],
        second_sensor=(at(-0.5, -2.75, 4.8), (0.7071067811865476, 0.0, 0.0, 0.7071067811865476)),
        nominal_size=(0.12, 0.06, 0.10),
        description='wooden cat: body, head, muzzle, neck, two ears, four legs, tail')


def make_bottle() -> ObjectModel:
    """A Bordeaux wine bottle, 30 cm tall, 7.5 cm across: body, rounded shoulder, neck, lip.
    Object frame: the sensor taped on the side of the body 14 cm above the bottom (so the
    whole bottle fits a 35 cm workspace centred on the sensor); z along the bottle's axis, up."""
    at, offset = _shifted((3.75, 0.0, 14.0))
    up = np.array([0.0, 0.0, 1.0])
    axis_origin = at(0.0, 0.0, 0.0)
    prims = [
        RevolvedBox(axis_origin, up, 3.75 * CM, 0.0, 20.5 * CM, rounding=0.5 * CM),   # body
        RoundCone(at(0.0, 0.0, 20.0), at(0.0, 0.0, 25.0), 3.75 * CM, 1.45 * CM),      # shoulder
        RevolvedBox(axis_origin, up, 1.45 * CM, 24.0 * CM, 29.0 * CM, rounding=0.2 * CM),  # neck
        RevolvedBox(axis_origin, up, 1.6 * CM, 28.3 * CM, 30.0 * CM, rounding=0.3 * CM),   # lip
    ]
    top = HeldRegion('top of the neck', (tuple(at(0.0, 0.0, 30.6)),), (0.034,))
    neck = HeldRegion('neck', (tuple(at(0.0, 0.0, 26.5)),), (0.038,))
    bottom = HeldRegion('bottom', (tuple(at(0.0, 0.0, -0.5)),), (0.065,))
    return ObjectModel(
        name='bottle', primitives=prims, table_z=float(-offset[2]), static_grip=top,
        moving_grips=[neck, bottom],
        second_sensor=(at(-3.75, 0.0, 9.0), (0.0, 0.0, 1.0, 0.0)),
        nominal_size=(0.075, 0.075, 0.30),
        description='wine bottle: body, shoulder, neck, lip')


def make_mug() -> ObjectModel:
    """A mug 8 cm across and 9.5 cm tall, 4 mm wall, 7 mm bottom, open top, with a round
    handle reaching 3.2 cm out. Object frame: the sensor under the bottom, at its centre; z up,
    x towards the handle."""
    at, offset = _shifted((0.0, 0.0, 0.0))
    up = np.array([0.0, 0.0, 1.0])
    origin = at(0.0, 0.0, 0.0)
    handle_rotation = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    prims = [
        RevolvedBox(origin, up, 4.0 * CM, 0.0, 9.5 * CM, rounding=0.2 * CM,
                    inner_radius=3.6 * CM),                                           # wall
        RevolvedBox(origin, up, 4.0 * CM, 0.0, 0.7 * CM, rounding=0.2 * CM),          # bottom
        ArcTube(at(4.0, 0.0, 4.75), handle_rotation, math.hypot(0.3, 2.6) * CM, 0.55 * CM,
                math.atan2(2.6, 0.3)),                                                # handle
    ]
    rim = HeldRegion('rim, far side', (tuple(at(-4.0, 0.0, 9.9)),), (0.022,))
    handle = HeldRegion('handle', (tuple(at(6.2, 0.0, 4.75)),), (0.023,))
    side = HeldRegion('bottom and far side', (tuple(at(-3.0, 0.0, 1.0)),), (0.035,))
    return ObjectModel(
        name='mug', primitives=prims, table_z=float(-offset[2]), static_grip=rim,
        moving_grips=[handle, side],
        second_sensor=(at(-4.0, 0.0, 4.5), (0.0, 0.0, 1.0, 0.0)),
        nominal_size=(0.112, 0.08, 0.095),
        description='mug: wall, bottom, open top, handle')


_FACTORIES = {'cat': make_cat, 'bottle': make_bottle, 'mug': make_mug}
OBJECT_NAMES = tuple(_FACTORIES)
NOMINAL_SIZES = {'cat': (0.12, 0.06, 0.10), 'bottle': (0.075, 0.075, 0.30),
                 'mug': (0.112, 0.08, 0.095)}


def get_object(name: str) -> ObjectModel:
    """The object model called ``name`` (one of OBJECT_NAMES)."""
    try:
        return _FACTORIES[name]()
    except KeyError:
        raise ValueError(f'unknown object {name!r}: choose one of {", ".join(OBJECT_NAMES)}') from None
