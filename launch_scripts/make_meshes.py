"""Make the meshes that inhand_sim ships (src/inhand_sim/meshes/), bit for bit.

    .venv/bin/python launch_scripts/make_meshes.py [DIR]      (default DIR: src/inhand_sim/meshes)

Why made, not drawn: the simulator must be measured on objects that are not unions of its
own primitives, the way a scanned object is not: a smooth implicit shape with small bumps,
meshed by marching cubes (PyMCubes) on a 1 mm grid and decimated by quadric edge collapse
(fast-simplification) to about 24,000 irregular triangles, as a scanner's mesh after its
own clean-up. Each is watertight (checked here) and saved as binary PLY in metres, z up:

* ``cup``: a tapered mug 8.2 cm across at the rim and 9.5 cm tall with a 5 mm wall, a
  7 mm bottom, rounded edges and a handle (a torus arc, filleted into the wall): concave
  and two-sided, the fingers explore inside and outside.
* ``animal``: a standing dog-like figure (body, chest, head, muzzle, ears, four legs and a
  tail blended smoothly, flat feet), 15 x 6 x 12 cm, with the bumps of carved wood.
* ``duck``: a duck-like figure on a flat base (body, raised tail, neck, head, a flat beak),
  12 x 8 x 10 cm, lumpy like a hand-made figure.

Deterministic: no randomness but hashed lattice noise (inhand_sim.textures.value_noise),
and numpy's float64 sin/cos/exp kept on its AVX2 paths (as launch_scripts/make_bags.sh does)
so the bytes are the same on every x86_64 machine; a test regenerates them and compares.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path

# Before numpy is imported: the same float64 transcendental functions on every x86_64 CPU.
os.environ.setdefault('NPY_DISABLE_CPU_FEATURES', 'X86_V4 AVX512_ICL AVX512_SPR')
os.environ.setdefault('OPENBLAS_CORETYPE', 'Haswell')

import fast_simplification
import mcubes
import numpy as np
import trimesh

from inhand_sim.textures import fbm

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DIR = ROOT / 'src' / 'inhand_sim' / 'meshes'
GRID = 0.001            # marching cubes spacing, m
FACES = 24_000          # triangles after decimation
CM = 0.01

Field = Callable[[np.ndarray], np.ndarray]


# --- implicit shapes (approximate signed distances, m; negative inside) ---------------------

def smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum: the union of two shapes with a fillet of about ``k``."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k / 4.0


def ellipsoid(p: np.ndarray, centre, radii, tilt_deg: float = 0.0) -> np.ndarray:
    """First-order distance to an ellipsoid turned by ``tilt_deg`` about y (f / |grad f|)."""
    t = np.radians(tilt_deg)
    v = p - np.asarray(centre) * CM
    x = v[:, 0] * np.cos(t) + v[:, 2] * np.sin(t)
    z = -v[:, 0] * np.sin(t) + v[:, 2] * np.cos(t)
    r = np.asarray(radii) * CM
    q = np.stack([x / r[0], v[:, 1] / r[1], z / r[2]], axis=1)
    k0 = np.linalg.norm(q, axis=1)
    k1 = np.linalg.norm(q / r, axis=1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def capsule(p: np.ndarray, a, b, ra: float, rb: float) -> np.ndarray:
    """Distance to a tapered capsule from ``a`` (radius ``ra``) to ``b`` (cm), approximately."""
    a, b = np.asarray(a) * CM, np.asarray(b) * CM
    ab = b - a
    t = np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - a - t[:, None] * ab, axis=1) - (ra + t * (rb - ra)) * CM


def bumps(p: np.ndarray, amplitude: float, scale: float, seed: int) -> np.ndarray:
    """Small-scale relief: zero-mean fractal noise of about ``amplitude`` (m)."""
    return amplitude * 2.0 * (fbm(p, scale, 3, seed=seed) - 0.5)


def polygon_distance(x: np.ndarray, y: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Signed distance from points (x, y) to a closed polygon (negative inside)."""
    d2 = np.full(len(x), np.inf)
    inside = np.zeros(len(x), dtype=bool)
    for (ax, ay), (bx, by) in zip(corners, np.roll(corners, -1, axis=0)):
        ex, ey = bx - ax, by - ay
        t = np.clip(((x - ax) * ex + (y - ay) * ey) / (ex * ex + ey * ey), 0.0, 1.0)
        d2 = np.minimum(d2, (x - ax - t * ex) ** 2 + (y - ay - t * ey) ** 2)
        crosses = (ay > y) != (by > y)
        at = ax + (y - ay) / np.where(by != ay, by - ay, 1.0) * ex
        inside ^= crosses & (x < at)
    return np.where(inside, -1.0, 1.0) * np.sqrt(d2)


def cup(p: np.ndarray) -> np.ndarray:
    height, wall, bottom, rounding = 9.5 * CM, 0.5 * CM, 0.7 * CM, 0.2 * CM
    r0, r1 = 3.7 * CM, 4.1 * CM                  # outer radius at the foot and at the rim

    def outer(z):
        return r0 + (r1 - r0) * z / height
    rho = np.hypot(p[:, 0], p[:, 1])
    z = p[:, 2]
    # the wall's cross-section through the axis (a U), shrunk by the rounding
    s = rounding
    half = np.array([[outer(s) - s, s], [outer(height - s) - s, height - s],
                     [outer(height - s) - wall + s, height - s],
                     [outer(bottom - s) - wall + s, bottom - s]])
    mirrored = half[::-1] * [-1.0, 1.0]
    profile = np.concatenate([half, mirrored])
    body = polygon_distance(rho, z, profile) - rounding
    # the handle: a torus arc in the xz plane, only outside the wall, filleted into it
    centre_x, centre_z, major, minor = 4.75 * CM, 4.9 * CM, 2.55 * CM, 0.55 * CM
    ring = np.hypot(np.hypot(p[:, 0] - centre_x, p[:, 2] - centre_z) - major, 1.25 * p[:, 1])
    handle = np.maximum(ring / 1.25 - minor, outer(z) - 0.001 - rho)
    return smooth_min(body, handle, 0.4 * CM)


def animal(p: np.ndarray) -> np.ndarray:
    parts = [
        ellipsoid(p, (0.0, 0.0, 6.6), (4.6, 2.6, 2.3)),            # body
        ellipsoid(p, (3.4, 0.0, 7.3), (2.2, 2.5, 2.5), -20.0),     # chest
        ellipsoid(p, (5.4, 0.0, 9.6), (1.9, 1.8, 1.7)),            # head
        ellipsoid(p, (7.1, 0.0, 9.1), (1.2, 0.95, 0.8), 10.0),     # muzzle
    ]
    for side in (1.0, -1.0):
        parts.append(ellipsoid(p, (4.8, side * 1.3, 11.2), (0.55, 0.35, 1.1), 15.0))   # ears
        for x in (3.3, -3.1):
            parts.append(capsule(p, (x, side * 1.45, 6.0), (x + 0.3, side * 1.55, 0.4),
                                 1.05, 0.75))                                           # legs
    parts.append(capsule(p, (-4.2, 0.0, 7.4), (-6.9, 0.0, 9.6), 0.65, 0.35))           # tail
    d = parts[0]
    for part in parts[1:]:
        d = smooth_min(d, part, 0.7 * CM)
    d = d + bumps(p, 0.0009, 0.02, 11) + bumps(p, 0.00035, 0.004, 12)
    return np.maximum(d, -p[:, 2])                                                      # flat feet


def duck(p: np.ndarray) -> np.ndarray:
    parts = [
        ellipsoid(p, (0.0, 0.0, 3.3), (5.4, 3.9, 3.2)),            # body
        ellipsoid(p, (-4.3, 0.0, 4.6), (2.0, 2.2, 1.3), -30.0),    # tail
        capsule(p, (2.6, 0.0, 4.5), (3.4, 0.0, 7.2), 1.8, 1.5),    # neck
        ellipsoid(p, (3.6, 0.0, 7.8), (2.4, 2.2, 2.2)),            # head
    ]
    d = parts[0]
    for part in parts[1:]:
        d = smooth_min(d, part, 1.0 * CM)
    beak = ellipsoid(p, (6.2, 0.0, 7.3), (1.6, 1.05, 0.45), 8.0)
    d = smooth_min(d, beak, 0.3 * CM)
    d = d + bumps(p, 0.0007, 0.025, 21) + bumps(p, 0.0003, 0.005, 22)
    return np.maximum(d, 0.4 * CM - p[:, 2]) + 0.0                                      # flat base


SHAPES: dict[str, tuple[Field, tuple[float, float, float], tuple[float, float, float]]] = {
    # name: (field, lower corner, upper corner of the region it lies in, cm)
    'cup': (cup, (-4.6, -4.6, -0.5), (8.6, 4.6, 10.0)),
    'animal': (animal, (-8.0, -3.6, -0.5), (8.8, 3.6, 12.8)),
    'duck': (duck, (-7.0, -4.6, -0.5), (8.4, 4.6, 10.6)),
}


def make(name: str) -> trimesh.Trimesh:
    """The mesh of shape ``name``: marching cubes of its field, decimated, checked."""
    field, lo, hi = SHAPES[name]
    # the grid off the shapes' flat faces (z = 0, the cup's floor): a face through a row of
    # nodes gives marching cubes slivers that the decimation turns into degenerate triangles
    lo_m, hi_m = np.asarray(lo) * CM + np.array([0.31, 0.47, 0.43]) * GRID, np.asarray(hi) * CM
    axes = [np.arange(a, b + GRID / 2, GRID) for a, b in zip(lo_m, hi_m)]
    points = np.stack(np.meshgrid(*axes, indexing='ij'), axis=-1).reshape(-1, 3)
    values = field(points).reshape(tuple(len(a) for a in axes))
    if (values[[0, -1]] <= 0).any() or (values[:, [0, -1]] <= 0).any() or (values[..., [0, -1]] <= 0).any():
        raise SystemExit(f'make_meshes: {name} touches its region; widen it')
    # no value within 2% of a grid step of zero: marching cubes would put several vertices at
    # (almost) one node, and the decimation would leave coincident vertices (a pinch)
    eps = 0.02 * GRID
    values = np.where(np.abs(values) < eps, np.where(values < 0, -eps, eps), values)
    vertices, faces = mcubes.marching_cubes(values, 0.0)
    vertices = lo_m + vertices * GRID
    vertices, faces = fast_simplification.simplify(vertices, faces.astype(np.int32),
                                                   target_count=FACES, agg=5.0)
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    if mesh.volume < 0:
        mesh.invert()
    if not (mesh.is_watertight and mesh.is_winding_consistent):
        raise SystemExit(f'make_meshes: {name} is not a closed, consistently oriented mesh')
    return mesh


def main(argv: list[str]) -> int:
    out = Path(argv[0]) if argv else DEFAULT_DIR
    out.mkdir(parents=True, exist_ok=True)
    for name in SHAPES:
        mesh = make(name)
        path = out / f'{name}.ply'
        path.write_bytes(mesh.export(file_type='ply', encoding='binary'))
        size = mesh.extents / CM
        print(f'make_meshes: {path} ({len(mesh.faces):,} triangles, {size[0]:.1f} x {size[1]:.1f} x '
              f'{size[2]:.1f} cm, {path.stat().st_size / 1e3:.0f} kB)')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
