"""Exact closest points on a triangle mesh, and which few triangles to ask for them.

A mesh object's contacts and distances must be those of its triangles, not of an
approximation: the distance grid (:mod:`inhand_sim.distance_grid`) brings a point within a
fraction of a millimetre of the surface, and :class:`TriangleBins` then finds the exact
closest point among the triangles that can hold it. Each triangle is listed in every cubic
bin that its bounding box, grown by ``reach``, overlaps; a point within ``reach`` of the
surface finds its closest triangle among those of its own bin (the closest point is within
``reach``, so that triangle's grown box holds the point). Points farther away look in the
bins around theirs, and the few farther than four bins at every triangle: right, only
slower.

Everything is vectorised over (point, triangle) pairs.
"""

from __future__ import annotations

import numpy as np

__all__ = ['TriangleBins', 'closest_points_on_triangles', 'subdivide_long_triangles']


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum('ij,ij->i', u, v)


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray,
                                c: np.ndarray) -> np.ndarray:
    """The point of triangle (a[i], b[i], c[i]) closest to p[i], all (N, 3): the projection
    onto the triangle's plane where it falls inside the triangle, else the nearest of the
    closest points on its three edges. Degenerate (zero-area) triangles: their edges."""
    ab, ac, ap = b - a, c - a, p - a
    d00, d01, d11 = _dot(ab, ab), _dot(ab, ac), _dot(ac, ac)
    d20, d21 = _dot(ap, ab), _dot(ap, ac)
    den = d00 * d11 - d01 * d01
    proper = den > 0.0
    safe = np.where(proper, den, 1.0)
    v = (d11 * d20 - d01 * d21) / safe
    w = (d00 * d21 - d01 * d20) / safe
    out = a + v[:, None] * ab + w[:, None] * ac
    rim = np.flatnonzero(~(proper & (v >= 0.0) & (w >= 0.0) & (v + w <= 1.0)))
    if rim.size:
        q = p[rim]
        best, best_d2 = None, None
        for start, end in ((a[rim], b[rim]), (a[rim], c[rim]), (b[rim], c[rim])):
            edge = end - start
            length2 = _dot(edge, edge)
            t = np.clip(_dot(q - start, edge) / np.where(length2 > 0.0, length2, 1.0), 0.0, 1.0)
            on_edge = start + t[:, None] * edge
            d2 = _dot(on_edge - q, on_edge - q)
            if best is None:
                best, best_d2 = on_edge, d2
            else:
                nearer = d2 < best_d2
                best[nearer], best_d2[nearer] = on_edge[nearer], d2[nearer]
        out[rim] = best
    return out


def subdivide_long_triangles(triangles: np.ndarray, max_edge: float) -> tuple[np.ndarray, np.ndarray]:
    """Triangles (T, 3, 3) cut in two across their longest edge (at its midpoint) until no
    edge is longer than ``max_edge``; returns the pieces and the index of the triangle each
    came from. The pieces cover their triangle exactly, so closest points on them are closest
    points on it; a long sliver becomes a row of pieces (not the 4^k of midpoint subdivision)."""
    pieces = np.asarray(triangles, dtype=float)
    source = np.arange(len(pieces))
    while True:
        edges = np.linalg.norm(np.roll(pieces, -1, axis=1) - pieces, axis=2)   # edge k: k -> k+1
        longest = np.argmax(edges, axis=1)
        long = edges[np.arange(len(pieces)), longest] > max_edge
        if not long.any():
            return pieces, source
        t = pieces[long]
        k = longest[long]
        rows = np.arange(len(t))
        a, b, c = t[rows, k], t[rows, (k + 1) % 3], t[rows, (k + 2) % 3]
        middle = 0.5 * (a + b)
        split = np.concatenate([np.stack([a, middle, c], axis=1), np.stack([middle, b, c], axis=1)])
        pieces = np.concatenate([pieces[~long], split])
        source = np.concatenate([source[~long], np.tile(source[long], 2)])


def _first_per_group(group: np.ndarray, key: np.ndarray) -> np.ndarray:
    """Index of the smallest ``key`` among the entries of each distinct ``group`` value, one
    per group, in ascending group order; ties go to the first."""
    order = np.lexsort((key, group))
    starts = np.flatnonzero(np.r_[True, group[order][1:] != group[order][:-1]])
    return order[starts]


class TriangleBins:
    """The triangles of a mesh binned for exact closest-point queries near its surface.

    ``vertices`` (V, 3), ``faces`` (F, 3) int; ``bin_size`` the bins' edge (m); ``reach``
    how far from the surface a point may be and still be answered from its own bin."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, bin_size: float = 0.003,
                 reach: float = 0.001):
        self.triangles = np.asarray(vertices, dtype=float)[np.asarray(faces)]     # (F, 3, 3)
        self.bin_size, self.reach = float(bin_size), float(reach)
        lo = self.triangles.min(axis=1) - reach
        hi = self.triangles.max(axis=1) + reach
        self.origin = lo.min(axis=0)
        first = np.floor((lo - self.origin) / bin_size).astype(np.int64)
        last = np.floor((hi - self.origin) / bin_size).astype(np.int64)
        self.shape = last.max(axis=0) + 1
        span = last - first + 1
        counts = span.prod(axis=1)
        face = np.repeat(np.arange(len(span)), counts)
        offset = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
        sy, sz = span[face, 1], span[face, 2]
        cell = first[face] + np.stack([offset // (sy * sz), (offset // sz) % sy, offset % sz], axis=1)
        key = self._flat(cell)
        order = np.argsort(key, kind='stable')
        self.faces_in_bins = face[order]
        self.bin_start = np.searchsorted(key[order], np.arange(int(self.shape.prod()) + 1))

    def _flat(self, cell: np.ndarray) -> np.ndarray:
        return (cell[:, 0] * self.shape[1] + cell[:, 1]) * self.shape[2] + cell[:, 2]

    def nearest(self, points: np.ndarray, chunk: int = 16384
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest surface points (N, 3), their distances (N,) and triangle indices (N,) of
        ``points`` (N, 3): exact for every point. A point not within ``reach`` of a triangle
        of its own bin looks in the bins around it (1, 2, then 4 bins away: exact once the
        nearest triangle found is within that many bins), and at last at every triangle."""
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        n = len(points)
        closest = np.empty((n, 3))
        distance = np.full(n, np.inf)
        face = np.full(n, -1, dtype=np.int64)
        cell = np.floor((points - self.origin) / self.bin_size).astype(np.int64)
        todo = np.arange(n)
        for ring, sure in ((0, self.reach), (1, self.bin_size), (2, 2 * self.bin_size),
                           (4, 4 * self.bin_size)):
            offsets = np.stack(np.meshgrid(*[np.arange(-ring, ring + 1)] * 3, indexing='ij'),
                               axis=-1).reshape(-1, 3)
            step = max(1, chunk // len(offsets))
            for start in range(0, len(todo), step):
                part = todo[start:start + step]
                self._from_bins(points, part, cell[part], offsets, closest, distance, face)
            todo = todo[distance[todo] > sure]
            if not todo.size:
                break
        if todo.size:
            self._everything(points, todo, closest, distance, face)
        return closest, distance, face

    def _from_bins(self, points, part, cell, offsets, closest, distance, face) -> None:
        """Nearest triangle of ``points[part]`` among those of the bins at ``offsets`` from
        each point's bin ``cell``."""
        owner = np.repeat(np.arange(len(part)), len(offsets))
        bins = (cell[:, None, :] + offsets[None, :, :]).reshape(-1, 3)
        valid = np.all((bins >= 0) & (bins < self.shape), axis=1)
        owner, key = owner[valid], self._flat(bins[valid])
        counts = self.bin_start[key + 1] - self.bin_start[key]
        pair_owner = np.repeat(owner, counts)
        within = np.arange(len(pair_owner)) - np.repeat(np.cumsum(counts) - counts, counts)
        candidate = self.faces_in_bins[np.repeat(self.bin_start[key], counts) + within]
        if len(pair_owner):
            self._best(points, part, pair_owner, candidate, closest, distance, face)

    def _best(self, points, part, owner, candidate, closest, distance, face) -> None:
        """Keep, for each point of ``part``, its nearest of the ``candidate`` triangles
        (pairs ``owner`` -> ``candidate``) when nearer than what it has."""
        t = self.triangles[candidate]
        q = closest_points_on_triangles(points[part[owner]], t[:, 0], t[:, 1], t[:, 2])
        d2 = np.sum((q - points[part[owner]]) ** 2, axis=1)
        best = _first_per_group(owner, d2)
        target = part[owner[best]]
        d = np.sqrt(d2[best])
        better = d < distance[target]
        target = target[better]
        closest[target] = q[best][better]
        distance[target] = d[better]
        face[target] = candidate[best][better]

    def _everything(self, points, ids, closest, distance, face, budget: int = 4_000_000) -> None:
        """Nearest triangle of ``points[ids]`` among all of them, in chunks of points."""
        n_faces = len(self.triangles)
        step = max(1, budget // max(n_faces, 1))
        for start in range(0, len(ids), step):
            part = ids[start:start + step]
            owner = np.repeat(np.arange(len(part)), n_faces)
            candidate = np.tile(np.arange(n_faces), len(part))
            self._best(points, part, owner, candidate, closest, distance, face)
