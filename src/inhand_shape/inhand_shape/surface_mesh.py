"""The surface of the occupied cells as a triangle mesh, open where there is no evidence.

A touch map's occupied cells are a shell one or two cells thick where fingers went, with
gaps where none did. Marching cubes on the probability itself would wrap that shell in a
double-sided skin and close every gap with a tube. What a grasp planner or a simulator wants
is the one surface the cells sample, and nothing where they are silent. So:

1. **Normals**: the smallest principal axis of the cells within 2.5 cells of each cell.
2. **Orientation**: the sign is carried along the minimum spanning tree of the cells'
   neighbour graph, weighted by how much neighbouring normals disagree (Hoppe et al. 1992):
   each tree starts at the cell farthest from its component's centre and a cell takes its
   parent's side. Depth by depth, so it is one numpy step per level of the tree, not per
   cell. Then each component as a whole is turned to point away from its centre where most
   of its cells do (area of a closed surface faces outward more than inward; the farthest
   cell alone is a poor judge: the tip of a tail or a leg has a sideways normal).
3. **Signed distance** (Hoppe's tangent planes): at each lattice point near the cells, the
   Gaussian-weighted mean of ``n . (x - p)`` over the nearest cells, ``p`` the cell's centre
   or, where the map knows it, where in the cell the touches were (its contact centroid:
   the mesh then lies 0.6 mm from the true surface on average instead of 1.0 mm on the
   shape benchmark's maps, docs/shape.md). The field exists only within :data:`REACH`
   cells of a cell.
4. **Marching cubes** (scikit-image, with its mask) on that field, only where it exists: the
   surface ends where the evidence ends, and each gap stays a hole.

Holes are counted as the mesh's boundary loops (edges of one triangle only, joined where
they share a vertex): a fully explored closed object gives 0, a cup explored without its
bottom 1 (the rim of the missing bottom) plus one per untouched patch. Separate pieces of
fewer than :data:`MIN_PIECE_FACES` triangles (around a stray cell or two) are left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage  # type: ignore[import-untyped]
from scipy.sparse import coo_matrix  # type: ignore[import-untyped]
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree  # type: ignore[import-untyped]
from scipy.spatial import cKDTree  # type: ignore[import-untyped]

from inhand_common.array_types import Floats, Points
from inhand_common.cell_lattice import Lattice, cell_indices

__all__ = ['NORMAL_RADIUS', 'REACH', 'SurfaceMesh', 'cell_normals', 'nearest_cells',
           'oriented_normals', 'surface_mesh', 'tangent_plane_distance']

NORMAL_RADIUS = 2.5    # cells: the neighbourhood of a cell's normal
REACH = 1.5            # cells: how far from a cell the surface may go
NEIGHBOURS = 6         # cells averaged into the signed distance at a lattice point
MIN_PIECE_FACES = 24   # smaller separate pieces of surface are specks of strays
Faces = NDArray[np.int64]
Pairs = tuple[NDArray[np.intp], NDArray[np.intp]]   # (rows, cols) of neighbour pairs


@dataclass(frozen=True, eq=False)
class SurfaceMesh:
    """Vertices (V, 3) m in the map frame, faces (F, 3) outward oriented, and the holes."""

    vertices: Points
    faces: Faces
    holes: int               # boundary loops (module doc)
    boundary_length: float   # m, the summed length of the boundary edges

    @property
    def area(self) -> float:
        t = self.vertices[self.faces]
        return float(0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())

    def trimesh(self) -> Any:
        """The mesh as a trimesh.Trimesh (for writing PLY, OBJ, STL)."""
        import trimesh
        return trimesh.Trimesh(self.vertices, self.faces, process=False)


def _neighbour_pairs(points: Points, radius: float) -> Pairs:
    """Both directions of every pair closer than ``radius``, and each point with itself."""
    pairs = cKDTree(points).query_pairs(radius, output_type='ndarray')
    own = np.arange(len(points))
    return (np.concatenate([pairs[:, 0], pairs[:, 1], own]),
            np.concatenate([pairs[:, 1], pairs[:, 0], own]))


def cell_normals(points: Points, resolution: float) -> tuple[Floats, Pairs]:
    """Unoriented unit normals (N, 3) of the cells at ``points`` (step 1 of the module doc),
    and the neighbour pairs they were taken over."""
    rows, cols = _neighbour_pairs(points, NORMAL_RADIUS * resolution)
    count = np.bincount(rows, minlength=len(points)).astype(float)
    mean = np.stack([np.bincount(rows, points[cols, k], len(points)) for k in range(3)], axis=1) \
        / count[:, None]
    offset = points[cols] - mean[rows]
    cov = np.zeros((len(points), 3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = np.bincount(rows, offset[:, a] * offset[:, b], len(points))
    _, vectors = np.linalg.eigh(cov)
    return vectors[:, :, 0], (rows, cols)


def _orient(points: Points, normals: Floats, rows: NDArray[np.intp], cols: NDArray[np.intp]) -> Floats:
    """Consistently oriented normals (step 2 of the module doc)."""
    n = len(points)
    keep = rows < cols
    agreement = np.abs(np.einsum('ij,ij->i', normals[rows[keep]], normals[cols[keep]]))
    graph = coo_matrix((1.0 - agreement + 1e-6, (rows[keep], cols[keep])), shape=(n, n)).tocsr()
    tree = minimum_spanning_tree(graph)
    tree = tree + tree.T
    count, label = connected_components(tree, directed=False)
    parent = np.arange(n)
    centres = np.stack([np.bincount(label, points[:, k]) for k in range(3)], axis=1) \
        / np.bincount(label)[:, None]
    for component in range(count):
        members = np.flatnonzero(label == component)
        root = members[np.argmax(np.linalg.norm(points[members] - centres[component], axis=1))]
        order, predecessors = breadth_first_order(tree, root, directed=False)
        parent[order[1:]] = predecessors[order[1:]]
    # a cell's sign is the product of the flips on its path to the root: pointer jumping
    # (each round doubles the path covered) takes log2(depth) vectorised rounds, not one per
    # level of the tree
    sign: Floats = np.where(np.einsum('ij,ij->i', normals, normals[parent]) >= 0, 1.0, -1.0)
    while np.any(parent[parent] != parent):
        sign = sign * sign[parent]
        parent = parent[parent]
    outward = np.einsum('ij,ij->i', normals * sign[:, None], points - centres[label]) > 0
    share = np.bincount(label, outward) / np.bincount(label)
    return normals * (sign * np.where(share[label] < 0.5, -1.0, 1.0))[:, None]


def oriented_normals(points: Points, resolution: float) -> Floats:
    """Consistently oriented unit normals (N, 3) of the cells at ``points`` (steps 1 and 2 of
    the module doc)."""
    normals, (rows, cols) = cell_normals(points, resolution)
    return _orient(points, normals, rows, cols)


def nearest_cells(cells: Points, where: Points, tree: cKDTree | None = None
                  ) -> tuple[Floats, NDArray[np.intp]]:
    """Distances and indices (M, k) of the :data:`NEIGHBOURS` cells nearest to each point of
    ``where``, nearest first (``tree``: a KD-tree of ``cells`` already built)."""
    tree = cKDTree(cells) if tree is None else tree
    distance, index = tree.query(where, k=min(NEIGHBOURS, len(cells)), workers=-1)
    return distance.reshape(len(where), -1), index.reshape(len(where), -1)


def tangent_plane_distance(cells: Points, normals: Floats, where: Points, resolution: float,
                           sheet: NDArray[np.bool_] | None = None,
                           neighbours: tuple[Floats, NDArray[np.intp]] | None = None) -> Floats:
    """Signed distance at ``where`` (M, 3) from the tangent planes of the nearest cells
    (step 3 of the module doc): the Gaussian-weighted mean of ``n . (x - p)`` over the
    :data:`NEIGHBOURS` nearest cells, positive on the side the normals point to. A cell of a
    ``sheet`` (outside on both sides) counts as a slab half a cell thick: ``|n . (x - p)| -
    resolution / 2``. ``neighbours``: :func:`nearest_cells` of ``where``, when the caller
    has it already."""
    distance, nearest = nearest_cells(cells, where) if neighbours is None else neighbours
    weight = np.exp(-(distance / resolution) ** 2)
    planes = np.einsum('ikj,ikj->ik', normals[nearest], where[:, None, :] - cells[nearest])
    if sheet is not None:
        planes = np.where(sheet[nearest], np.abs(planes) - resolution / 2, planes)
    return np.asarray((weight * planes).sum(axis=1) / np.maximum(weight.sum(axis=1), 1e-300))


def _without_specks(vertices: Points, faces: Faces) -> tuple[Points, Faces]:
    """The mesh without its pieces of fewer than :data:`MIN_PIECE_FACES` triangles: a stray
    cell or two far from the rest make a speck of surface whose edge would count as a hole."""
    if len(faces) == 0:
        return vertices, faces
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(len(vertices),) * 2)
    _, label = connected_components(graph, directed=False)
    sizes = np.bincount(label[faces[:, 0]], minlength=label.max() + 1)
    keep = sizes[label[faces[:, 0]]] >= MIN_PIECE_FACES
    used = np.zeros(len(vertices), dtype=bool)
    used[faces[keep].ravel()] = True
    renumber = np.cumsum(used) - 1
    return vertices[used], renumber[faces[keep]]


def _boundary(vertices: Points, faces: Faces) -> tuple[int, float]:
    """(boundary loops, boundary length) of a triangle mesh."""
    if len(faces) == 0:
        return 0, 0.0
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    open_edges = unique[counts == 1]
    if len(open_edges) == 0:
        return 0, 0.0
    length = float(np.linalg.norm(vertices[open_edges[:, 0]] - vertices[open_edges[:, 1]], axis=1).sum())
    used, index = np.unique(open_edges, return_inverse=True)
    index = index.reshape(-1, 2)
    graph = coo_matrix((np.ones(len(index)), (index[:, 0], index[:, 1])), shape=(len(used),) * 2)
    loops, _ = connected_components(graph, directed=False)
    return int(loops), length


def surface_mesh(points: ArrayLike, resolution: float, origin: ArrayLike = (0.0, 0.0, 0.0),
                 surface_points: ArrayLike | None = None) -> SurfaceMesh:
    """The surface through the occupied cells whose centres are ``points`` (N, 3) m on the
    lattice of cell size ``resolution`` whose cell (0, 0, 0) has its low corner at
    ``origin`` (the module doc's method). ``surface_points`` (N, 3): where in each cell the
    surface was measured (the map's contact centroids): each cell's tangent plane passes
    there instead of through its centre. An empty mesh for fewer than 4 cells."""
    from skimage.measure import marching_cubes
    cells = np.asarray(points, dtype=float).reshape(-1, 3)
    through = cells if surface_points is None else \
        np.asarray(surface_points, dtype=float).reshape(-1, 3)
    if through.shape != cells.shape:
        raise ValueError(f'{len(through)} surface points for {len(cells)} cells')
    if len(cells) < 4:
        return SurfaceMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), 0, 0.0)
    normals = oriented_normals(cells, resolution)
    # the lattice of cell centres around the cells, in cell units
    x, y, z = (float(v) for v in np.ravel(origin))
    index = cell_indices(cells, Lattice(resolution, (x, y, z)))
    pad = int(math.ceil(REACH)) + 1
    low = index.min(axis=0) - pad
    shape = tuple(int(v) for v in index.max(axis=0) - low + pad + 1)
    occupied = np.zeros(shape, dtype=bool)
    occupied[tuple((index - low).T)] = True
    near = ndimage.distance_transform_edt(~occupied) <= REACH
    lattice = np.argwhere(near)
    where = (lattice + low + 0.5) * resolution + np.asarray(origin, dtype=float)
    field = np.full(shape, np.nan)
    # the nearest cells by their centres, their planes through where the surface was measured
    field[tuple(lattice.T)] = tangent_plane_distance(through, normals, where, resolution,
                                                     neighbours=nearest_cells(cells, where))
    # only cubes whose eight corners all have a value
    known = ~np.isnan(field)
    # scikit-image looks the mask up at a cube's highest corner
    whole = ndimage.binary_erosion(known, np.ones((2, 2, 2), dtype=bool)) & known
    if not (np.nanmin(field) < 0 < np.nanmax(field)):
        return SurfaceMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), 0, 0.0)
    verts, faces, _, _ = marching_cubes(np.where(known, field, 0.0), 0.0, mask=whole,
                                        gradient_direction='descent', allow_degenerate=False)
    vertices = (verts + low + 0.5) * resolution + np.asarray(origin, dtype=float)
    vertices, faces = _without_specks(vertices, np.asarray(faces, dtype=np.int64))
    holes, length = _boundary(vertices, faces)
    return SurfaceMesh(vertices, faces, holes, length)
