"""Surface colours of the simulated objects and of the scene around them, procedural and exact.

Every colour is a pure function of a position (metres): the objects' in their OBJECT frame
(:mod:`inhand_sim.objects`), the backdrop's and the table's in the tracker frame
``polhemus_source``. No random state: the patterns are hashed lattice value noise (an integer
hash of the lattice corner, smoothly interpolated; compiled with numba, about 20 ns a point)
and simple geometry, so the same point always gets the same colour, on any machine (the hash
is integer arithmetic; the rest is a handful of float operations). The ground truth stores
:func:`surface_colour` of every surface sample; the stereo rig (:mod:`inhand_sim.stereo_rig`)
paints its images with the same functions, so an image pixel and the truth agree on what
colour the surface is.

What the objects look like (designed for stereo: texture where a real object has it, and
some surfaces nearly uniform, where block matching is expected to struggle):

* ``cat``: carved light wood (beech-like) with growth rings and fine streaks along the body
  (strong texture), partly painted like a calico cat: ginger and charcoal patches, white
  socks and belly (paint is smooth: weakly textured), a red collar, amber eyes with slit
  pupils, a pink nose and pink inner ears.
* ``bottle``: dark green glass, nearly uniform (weak texture, glossy), a cream paper front
  label (border, a title in large letters, a red crest, lines of small print: strong
  texture), a small back label, and a burgundy foil capsule over the neck's top.
* ``mug``: cream glaze with faint specks (weak texture, glossy), printed cobalt flowers in a
  staggered pattern between two blue bands on the outside (strong texture), a plain inside
  (weak texture), and an unglazed tan foot ring underneath.
* the shipped meshes (:mod:`inhand_sim.catalogue`; solid textures in their frames, centred on
  their bounding boxes): ``cup`` celadon glaze, mottled where it pools, with iron specks, a
  dark band under the rim and a bare clay foot; ``animal`` oiled walnut (grain, late-wood
  bands, pores); ``duck`` yellow paint with brush marks, an orange beak, dark eyes, a grey
  base; and ``scan``, any other mesh: mottled, speckled plaster.

The patterns are band-limited so that images sampled at one ray per pixel do not alias: noise
blobs are at least about 1.5 mm across (a couple of pixels at 0.4 m with a 600 px focal
length) and every outline (paint, print, lines, letters) is a linear ramp 0.8 mm wide (the
coverage of a box-filtered edge) rather than a step.

``surface_gloss`` gives the specular weight (0 matte paper .. 1 glass) for the renderer's
highlights; ``backdrop_colour`` and ``table_colour`` paint the scene's planes.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = [
    'SHININESS',
    'backdrop_colour',
    'fbm',
    'surface_appearance',
    'surface_colour',
    'surface_gloss',
    'table_colour',
    'value_noise',
]

# Phong exponent of each object's glossy parts (the highlight's tightness).
SHININESS = {'cat': 12.0, 'bottle': 70.0, 'mug': 40.0, 'cup': 45.0, 'animal': 15.0, 'duck': 25.0,
             'scan': 8.0}

_M32 = _MASK32 = np.uint64(0xFFFFFFFF)
_PRIMES = (np.uint64(0x8DA6B343), np.uint64(0xD8163841), np.uint64(0xCB1AB31F),
           np.uint64(0x165667B1))
_MIX1 = np.uint64(0x85EBCA6B)
_MIX2 = np.uint64(0xC2B2AE35)
_P0, _P1, _P2, _P3 = _PRIMES                 # the same constants as plain globals, for numba
_X1, _X2 = _MIX1, _MIX2
_S13, _S16 = np.uint64(13), np.uint64(16)
_EDGE = 0.0008   # m: width of the soft outlines (about a pixel at 0.45 m with f = 600 px)


# --- noise ---------------------------------------------------------------------------------

def _hash(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """A float in [0, 1) for every integer lattice point (int64 arrays), per ``seed``.

    Integer arithmetic only (uint64, wrapping; murmur3's 32-bit finaliser), so the result is
    the same everywhere."""
    with np.errstate(over='ignore'):
        h = (ix.astype(np.uint64) * _PRIMES[0] + iy.astype(np.uint64) * _PRIMES[1]
             + iz.astype(np.uint64) * _PRIMES[2] + np.uint64(seed) * _PRIMES[3]) & _MASK32
        h ^= h >> np.uint64(16)
        h = (h * _MIX1) & _MASK32
        h ^= h >> np.uint64(13)
        h = (h * _MIX2) & _MASK32
        h ^= h >> np.uint64(16)
    return h.astype(np.float64) * (1.0 / 4294967296.0)


@numba.njit(cache=True, nogil=True)
def _hash_scalar(ix, iy, iz, seed):
    """:func:`_hash` for one lattice point (the same integers, the same result)."""
    h = (np.uint64(ix) * _P0 + np.uint64(iy) * _P1 + np.uint64(iz) * _P2 + np.uint64(seed) * _P3) & _M32
    h ^= h >> _S16
    h = (h * _X1) & _M32
    h ^= h >> _S13
    h = (h * _X2) & _M32
    h ^= h >> _S16
    return np.float64(h) * (1.0 / 4294967296.0)


@numba.njit(cache=True, nogil=True)
def _value_noise_kernel(points, inv_scale, seed, out):
    for i in range(points.shape[0]):
        qx = points[i, 0] * inv_scale[0]
        qy = points[i, 1] * inv_scale[1]
        qz = points[i, 2] * inv_scale[2]
        fx, fy, fz = math.floor(qx), math.floor(qy), math.floor(qz)
        ix, iy, iz = np.int64(fx), np.int64(fy), np.int64(fz)
        tx, ty, tz = qx - fx, qy - fy, qz - fz
        ux = tx * tx * tx * (tx * (tx * 6.0 - 15.0) + 10.0)    # quintic fade: C2 across cells
        uy = ty * ty * ty * (ty * (ty * 6.0 - 15.0) + 10.0)
        uz = tz * tz * tz * (tz * (tz * 6.0 - 15.0) + 10.0)
        total = 0.0
        for dx in range(2):
            wx = ux if dx else 1.0 - ux
            for dy in range(2):
                wy = wx * (uy if dy else 1.0 - uy)
                for dz in range(2):
                    w = wy * (uz if dz else 1.0 - uz)
                    total += w * _hash_scalar(ix + dx, iy + dy, iz + dz, seed)
        out[i] = total


def value_noise(points: np.ndarray, scale, seed: int = 0) -> np.ndarray:
    """Smooth lattice value noise in [0, 1] at points (N, 3); ``scale`` (metres, a number or
    one per axis for anisotropic noise) is the lattice spacing: the size of its blobs.
    Hashed values at the lattice corners, blended with quintic weights (compiled)."""
    p = np.ascontiguousarray(np.asarray(points, dtype=float).reshape(-1, 3))
    inv = 1.0 / np.broadcast_to(np.asarray(scale, dtype=float), (3,))
    out = np.empty(len(p))
    _value_noise_kernel(p, np.ascontiguousarray(inv), np.int64(seed), out)
    return out


def fbm(points: np.ndarray, scale, octaves: int = 3, seed: int = 0) -> np.ndarray:
    """Fractal sum of ``octaves`` value noises (each half the size and weight of the one
    before), normalised to [0, 1] (mean 0.5)."""
    total = np.zeros(len(points))
    weight_sum = 0.0
    for k in range(octaves):
        weight = 0.5 ** k
        total += weight * value_noise(points, np.asarray(scale, dtype=float) / 2 ** k, seed + 101 * k)
        weight_sum += weight
    return total / weight_sum


def _cell_random(cell: np.ndarray, seed: int) -> np.ndarray:
    return _hash(cell[:, 0], cell[:, 1], cell[:, 2], seed)


def _smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _mix(a: np.ndarray, b, t: np.ndarray) -> np.ndarray:
    """Blend colours (N, 3) or (3,) with weights (N,): ``a`` at 0, ``b`` at 1."""
    a = np.broadcast_to(np.asarray(a, dtype=float), (len(t), 3))
    b = np.broadcast_to(np.asarray(b, dtype=float), (len(t), 3))
    return a + (b - a) * t[:, None]


def _cover(signed_distance: np.ndarray) -> np.ndarray:
    """Coverage in [0, 1] of a shape from the signed distance to its outline (negative
    inside): a linear ramp _EDGE wide, the box-filtered edge. Soft outlines keep the
    patterns band-limited, so images sampled at one ray per pixel do not alias."""
    return np.clip(0.5 - signed_distance / _EDGE, 0.0, 1.0)


def _paint(colour: np.ndarray, coverage, paint) -> None:
    """``colour`` blended towards ``paint`` (a colour (3,) or colours (N, 3)) by
    ``coverage`` (N,) in [0, 1] (booleans allowed), in place."""
    alpha = np.asarray(coverage, dtype=float)
    if not np.any(alpha):
        return
    colour[:] = _mix(colour, paint, alpha)


def _glyphs(s: np.ndarray, h: np.ndarray, cell_w: float, cell_h: float, seed: int,
            fill: float = 0.55) -> np.ndarray:
    """Pseudo-text: ink coverage in [0, 1]. Characters on a grid of ``cell_w`` x ``cell_h``
    (metres, s along the line, h up); each character a random 3 x 5 bitmap in the inner
    0.75 x 0.8 of its cell, some cells blank (word gaps). The bitmap is interpolated
    bilinearly between stroke centres (soft strokes, no aliasing)."""
    col = np.floor(s / cell_w).astype(np.int64)
    row = np.floor(h / cell_h).astype(np.int64)
    fs = s / cell_w - col          # position in the character cell, [0, 1)
    fh = 1.0 - (h / cell_h - row)  # from the top of the cell
    gx = (fs - 0.125) / 0.75 * 3.0 - 0.5
    gy = (fh - 0.1) / 0.8 * 5.0 - 0.5
    ix, iy = np.floor(gx).astype(np.int64), np.floor(gy).astype(np.int64)
    tx, ty = gx - ix, gy - iy
    blank = _hash(col, row, np.zeros_like(col), seed + 7) < 0.17
    ink = np.zeros(len(s))
    for dx in (0, 1):
        for dy in (0, 1):
            bx, by = ix + dx, iy + dy
            inside = (bx >= 0) & (bx < 3) & (by >= 0) & (by < 5)
            bit = _hash(col * 16 + bx, row * 16 + by, np.ones_like(col), seed) < fill
            weight = (tx if dx else 1.0 - tx) * (ty if dy else 1.0 - ty)
            ink += weight * (inside & bit)
    return np.where(blank, 0.0, _smoothstep(0.25, 0.75, ink))


def _box(*signed_distances: np.ndarray) -> np.ndarray:
    """Signed distance (approximately) of the intersection of shapes: their maximum."""
    return np.maximum.reduce([np.asarray(d, dtype=float) for d in signed_distances])


# --- the objects ---------------------------------------------------------------------------

_WOOD_LIGHT = np.array([222.0, 186.0, 138.0])
_WOOD_DARK = np.array([160.0, 108.0, 62.0])
# Axes of the log the cat is carved from (columns: grain direction, two across), object frame.
_LOG_FRAME = np.linalg.qr(np.array([[1.0, -0.1, 0.3], [0.12, 1.0, 0.0], [-0.3, 0.05, 1.0]]).T)[0]


def _cat(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    # Wood: the figure carved from a log whose axis runs roughly along the body, tilted and
    # well off to the side, so growth rings show as curved bands crossing the body at a
    # slant; their radius wanders (fbm), their spacing varies, fine streaks and pores run
    # along the grain.
    g = p @ _LOG_FRAME                                        # log frame: grain along g[:, 0]
    wobble = fbm(p, 0.018, 3, seed=11) - 0.5
    r = np.hypot(g[:, 1] - 0.10, g[:, 2] + 0.07) + 0.006 * wobble
    ring = (r / 0.0034 + 1.5 * value_noise(p, 0.03, seed=18)) % 1.0
    late = _smoothstep(0.45, 0.7, ring) * (1.0 - _smoothstep(0.82, 0.98, ring))
    streaks = value_noise(g, (0.008, 0.0015, 0.0015), seed=12)
    colour = _mix(_WOOD_LIGHT, _WOOD_DARK, 0.6 * late + 0.4 * streaks)
    pores = _smoothstep(0.76, 0.84, value_noise(g, (0.004, 0.0012, 0.0012), seed=19))
    _paint(colour, 0.6 * pores, _WOOD_DARK * 0.8)
    colour *= (0.9 + 0.2 * fbm(p, 0.03, 2, seed=13))[:, None]
    gloss = np.full(len(p), 0.12)

    # Paint (smooth, nearly uniform: weak texture): calico patches, white belly and socks.
    faint = (0.985 + 0.03 * fbm(p, 0.012, 2, seed=14))[:, None]
    patch = _smoothstep(0.54, 0.555, fbm(p, 0.034, 3, seed=15))
    ginger = value_noise(p, 0.05, seed=16) > 0.55
    patch_colour = np.where(ginger[:, None], [[192.0, 88.0, 34.0]], [[58.0, 50.0, 46.0]]) * faint
    _paint(colour, patch, patch_colour)
    socks = _cover(z - (-0.0135 + 0.002 * (value_noise(p, 0.01, seed=17) - 0.5)))
    belly = _cover(_box(z - 0.004, np.abs(x) - 0.03, np.abs(y) - 0.02))
    white = np.maximum(socks, belly)
    _paint(colour, white, np.array([236.0, 232.0, 222.0]) * faint)
    gloss += 0.13 * np.maximum(patch, white)

    # Red collar round the neck (with a little gold bell at the front).
    a, b = np.array([0.031, 0.0, 0.029]), np.array([0.041, 0.0, 0.044])
    axis = (b - a) / np.linalg.norm(b - a)
    centre = a + 0.45 * (b - a)
    along = (p - centre) @ axis
    radial = np.linalg.norm((p - centre) - along[:, None] * axis, axis=1)
    collar = _cover(_box(np.abs(along) - 0.0032, radial - 0.0185))
    _paint(colour, collar, [178.0, 28.0, 38.0])
    bell = _cover(_box(np.linalg.norm(p - (centre + np.array([0.0135, 0.0, -0.0065])), axis=1) - 0.0035,
                       radial - 0.0185))
    _paint(colour, bell, [212.0, 170.0, 60.0])
    gloss += 0.23 * np.maximum(collar, bell)

    # Face: on the head ellipsoid (centre, radii from objects.make_cat).
    head_c, head_r = np.array([0.044, 0.0, 0.051]), np.array([0.019, 0.020, 0.0175])
    for side in (1.0, -1.0):
        q = np.array([0.74, 0.44 * side, 0.5])
        eye = head_c + head_r * q / np.linalg.norm(q)
        d = p - eye
        dist = np.linalg.norm(d, axis=1)
        _paint(colour, _cover(dist - 0.0042), [30.0, 28.0, 24.0])            # dark rim
        _paint(colour, _cover(dist - 0.0034), [196.0, 160.0, 40.0])          # amber iris
        slit = _box(np.abs(d[:, 2]) - 0.0028, np.abs(d[:, 0] * 0.6 + d[:, 1] * side * 0.8) - 0.0009,
                    dist - 0.0034)
        _paint(colour, _cover(slit), [12.0, 12.0, 12.0])                     # pupil
        gloss += 0.48 * _cover(dist - 0.0042)
        # Inner ear: the front face of each ear cone.
        ear_a = np.array([0.041, 0.011 * side, 0.062])
        ear_b = np.array([0.039, 0.0145 * side, 0.076])
        ear_axis = (ear_b - ear_a) / np.linalg.norm(ear_b - ear_a)
        t = np.clip((p - ear_a) @ ear_axis / np.linalg.norm(ear_b - ear_a), 0.0, 1.0)
        off = p - (ear_a + t[:, None] * (ear_b - ear_a))
        inner = _box(0.064 - z, 0.0035 - 0.003 * t - off[:, 0], np.abs(off[:, 1]) - (0.004 - 0.003 * t))
        _paint(colour, _cover(inner), [214.0, 140.0, 140.0])
    muzzle_c, muzzle_r = np.array([0.0595, 0.0, 0.046]), np.array([0.0075, 0.010, 0.0065])
    q = np.array([0.86, 0.0, 0.5])
    nose = muzzle_c + muzzle_r * q / np.linalg.norm(q)
    nose_d = np.linalg.norm((p - nose) * [1.0, 0.8, 1.3], axis=1) - 0.0032
    _paint(colour, _cover(nose_d), [205.0, 112.0, 120.0])
    return colour, gloss


_GLASS = np.array([26.0, 50.0, 30.0])
_PAPER = np.array([238.0, 229.0, 206.0])
_INK = np.array([38.0, 30.0, 28.0])
_WINE_RED = np.array([140.0, 22.0, 36.0])
_GOLD = np.array([176.0, 140.0, 62.0])


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def _bottle(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Bottle coordinates (objects.make_bottle): the axis is vertical at x = -3.75 cm, y = 0,
    # the bottom at z = -14 cm; height above the bottom 0 .. 30 cm.
    bx, by = p[:, 0] + 0.0375, p[:, 1]
    height = p[:, 2] + 0.14
    phi = np.arctan2(by, bx)                                  # 0: towards the sensor (+x)
    radius = 0.0375
    on_body = np.hypot(bx, by) > 0.030
    # Glass: nearly uniform; a faint tint wobble only (weak texture).
    colour = _GLASS * (0.97 + 0.06 * fbm(p, 0.05, 2, seed=21))[:, None]
    gloss = np.full(len(p), 0.85)

    # Front label facing +y (phi = 90 degrees), 9.5 cm tall, 145 degrees round.
    ds = _wrap(phi - 0.5 * math.pi) * radius                  # arc length from its centre
    h0, h1, half_w = 0.045, 0.140, math.radians(72.5) * radius
    front = _cover(_box(np.abs(ds) - half_w, np.abs(height - 0.5 * (h0 + h1)) - 0.5 * (h1 - h0)))
    front = np.where(on_body, front, 0.0)
    sel = np.flatnonzero(front > 0.0)
    if sel.size:
        c = _front_label(p[sel], ds[sel], height[sel] - h0, half_w, h1 - h0)
        colour[sel] = _mix(colour[sel], c, front[sel])
        gloss[sel] = _mix_scalar(gloss[sel], 0.03, front[sel])
    # Back label: small print only.
    ds_back = _wrap(phi + 0.5 * math.pi) * radius
    back = _cover(_box(np.abs(ds_back) - 0.022, np.abs(height - 0.08) - 0.02))
    back = np.where(on_body, back, 0.0)
    sel = np.flatnonzero(back > 0.0)
    if sel.size:
        pb = p[sel]
        c = _PAPER * (0.96 + 0.06 * value_noise(pb, 0.002, seed=22))[:, None]
        s, h = ds_back[sel] + 0.022, height[sel] - 0.06
        area = _cover(_box(np.abs(s - 0.022) - 0.019, np.abs(h - 0.02) - 0.016))
        _paint(c, area * _glyphs(s - 0.003, h, 0.0024, 0.0045, seed=23), _INK)
        colour[sel] = _mix(colour[sel], c, back[sel])
        gloss[sel] = _mix_scalar(gloss[sel], 0.03, back[sel])
    # Foil capsule over the top of the neck, with crinkles and a gold band.
    foil = _cover(0.248 - height)
    sel = np.flatnonzero(foil > 0.0)
    if sel.size:
        pf = p[sel]
        crinkle = fbm(pf, (0.004, 0.004, 0.0025), 2, seed=24)
        c = _WINE_RED * (0.8 + 0.45 * crinkle)[:, None]
        _paint(c, _cover(np.abs(height[sel] - 0.2525) - 0.0018), _GOLD)
        colour[sel] = _mix(colour[sel], c, foil[sel])
        gloss[sel] = _mix_scalar(gloss[sel], 0.5, foil[sel])
    return colour, gloss


def _mix_scalar(a: np.ndarray, b: float, t: np.ndarray) -> np.ndarray:
    return a + (b - a) * t


def _front_label(p: np.ndarray, ds: np.ndarray, h: np.ndarray, half_w: float, height: float
                 ) -> np.ndarray:
    """Colour of the front label in its own 2D coordinates: ``ds`` across (0 at the
    middle), ``h`` up from its lower edge."""
    colour = _PAPER * (0.95 + 0.07 * fbm(p, 0.003, 2, seed=25))[:, None]
    s = ds + half_w                                           # 0 .. width, left to right
    width = 2.0 * half_w
    edge = np.minimum(np.minimum(s, width - s), np.minimum(h, height - h))
    _paint(colour, _cover(np.abs(edge - 0.00375) - 0.00075), _GOLD)       # gold frame
    _paint(colour, _cover(np.abs(edge - 0.00585) - 0.00045), _WINE_RED)
    # A crest: a red disc with a gold ring and a pale chevron, in the upper middle.
    cx, ch = 0.5 * width, height - 0.022
    rr = np.hypot(s - cx, h - ch)
    _paint(colour, _cover(rr - 0.0105), _WINE_RED)
    _paint(colour, _cover(np.abs(rr - 0.00815) - 0.00075), _GOLD)
    chevron = _box(rr - 0.0065, np.abs(np.abs(s - cx) - (ch - h) * 0.9 - 0.001) - 0.0013)
    _paint(colour, _cover(chevron), _PAPER)
    # Title: large letters in a line below the crest.
    title_w, title_h = 0.0052, 0.0085
    base = height - 0.047
    line = _cover(_box(np.abs(h - base - 0.5 * title_h) - 0.5 * title_h, np.abs(s - cx) - (cx - 0.011)))
    _paint(colour, line * _glyphs(s - 0.011, h - base, title_w, title_h, seed=26, fill=0.6), _INK)
    # Lines of small print below it, and a wine-red vintage band.
    top = height - 0.058
    small = _cover(_box(np.abs(h - 0.5 * (0.012 + top)) - 0.5 * (top - 0.012), np.abs(s - cx) - (cx - 0.012)))
    _paint(colour, small * _glyphs(s - 0.012, h - 0.012, 0.0026, 0.0052, seed=27), _INK)
    _paint(colour, _cover(_box(np.abs(h - 0.009) - 0.0015, np.abs(s - cx) - 0.012)), _WINE_RED)
    return colour


_GLAZE = np.array([240.0, 235.0, 222.0])
_COBALT = np.array([34.0, 62.0, 150.0])


def _mug(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Mug coordinates (objects.make_mug): axis along z through the origin, bottom at z = 0,
    # rim at 9.5 cm, wall between radii 3.6 and 4.0 cm, handle towards +x.
    rho = np.hypot(p[:, 0], p[:, 1])
    z = p[:, 2]
    phi = np.arctan2(p[:, 1], p[:, 0])
    colour = _GLAZE * (0.975 + 0.04 * fbm(p, 0.02, 2, seed=32))[:, None]
    specks = _smoothstep(0.9, 0.96, value_noise(p, 0.0018, seed=31))
    _paint(colour, 0.5 * specks, [150.0, 120.0, 95.0])
    gloss = np.full(len(p), 0.55)

    outer = (rho > 0.0385) & (rho < 0.04 + 1e-4) & (z > 0.0025) & (z < 0.0935)
    if outer.any():
        s, zo = phi[outer] * 0.04, z[outer]                   # s: arc length round the wall
        c = colour[outer]
        bands = np.minimum(np.abs(zo - 0.0825) - 0.0022, np.abs(zo - 0.0135) - 0.0015)
        _paint(c, _cover(bands), _COBALT)
        # Flowers on a staggered lattice (spacing 16 mm round, 14 mm up), five petals, sizes
        # and turns hashed per flower; none under the handle (|phi| < 35 degrees).
        row = np.floor((zo - 0.02) / 0.014).astype(np.int64)
        shift = np.where(row % 2 == 0, 0.0, 0.008)
        col = np.floor((s + shift) / 0.016).astype(np.int64)
        cell = np.stack([col, row, np.zeros_like(col)], axis=1)
        size = 0.0045 + 0.002 * _cell_random(cell, 33)
        turn = 2.0 * math.pi * _cell_random(cell, 34)
        du = s + shift - (col + 0.5) * 0.016
        dv = zo - 0.02 - (row + 0.5) * 0.014
        r, ang = np.hypot(du, dv), np.arctan2(dv, du)
        allowed = (row >= 0) & (row <= 3) & (np.abs(phi[outer]) > math.radians(35.0))
        petals = _cover(r - size * (0.55 + 0.45 * np.abs(np.cos(2.5 * (ang + turn)))))
        _paint(c, allowed * petals, _COBALT)
        _paint(c, allowed * _cover(r - 0.28 * size), [210.0, 170.0, 60.0])
        colour[outer] = c
    foot = _cover(z - 0.0018)
    sel = np.flatnonzero(foot > 0.0)
    if sel.size:
        clay = np.array([196.0, 162.0, 122.0]) * (0.9 + 0.2 * fbm(p[sel], 0.004, 2, seed=35))[:, None]
        colour[sel] = _mix(colour[sel], clay, foot[sel])
        gloss[sel] = _mix_scalar(gloss[sel], 0.05, foot[sel])
    return colour, gloss


# The meshes (inhand_sim.catalogue): object frame at the centre of the mesh's bounding box,
# so the patterns are solid textures that need no more of the shape than that.
_CELADON = np.array([150.0, 178.0, 160.0])
_FOOT_CLAY = np.array([190.0, 150.0, 112.0])


def _cup(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Celadon glaze, darker where it pools (fbm), iron specks, a dark band near the rim
    # (cup.ply: 9.5 cm tall, the rim at z = +4.76 cm) and the bare clay foot under 1 cm.
    z = p[:, 2]
    colour = _CELADON * (0.86 + 0.28 * fbm(p, 0.012, 3, seed=61))[:, None]
    specks = _smoothstep(0.88, 0.95, value_noise(p, 0.0016, seed=62))
    _paint(colour, 0.7 * specks, [70.0, 58.0, 44.0])
    _paint(colour, 0.8 * _cover(np.abs(z - 0.0395) - 0.0025), [62.0, 92.0, 84.0])
    gloss = np.full(len(p), 0.55)
    foot = _cover(z - (-0.0376 + 0.0015 * (fbm(p, 0.01, 2, seed=63) - 0.5)))
    sel = np.flatnonzero(foot > 0.0)
    if sel.size:
        clay = _FOOT_CLAY * (0.88 + 0.24 * fbm(p[sel], 0.003, 2, seed=64))[:, None]
        colour[sel] = _mix(colour[sel], clay, foot[sel])
        gloss[sel] = _mix_scalar(gloss[sel], 0.05, foot[sel])
    return colour, gloss


def _animal(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Oiled walnut: grain along the body (x), darker late wood, pores; a little shine.
    streaks = value_noise(p, (0.012, 0.0016, 0.0016), seed=71)
    bands = (p[:, 2] / 0.004 + 3.0 * fbm(p, 0.03, 2, seed=72)) % 1.0
    late = _smoothstep(0.5, 0.75, bands) * (1.0 - _smoothstep(0.85, 0.98, bands))
    colour = _mix([168.0, 118.0, 78.0], [92.0, 58.0, 36.0], 0.55 * late + 0.45 * streaks)
    pores = _smoothstep(0.78, 0.86, value_noise(p, (0.005, 0.0012, 0.0012), seed=73))
    _paint(colour, 0.5 * pores, [60.0, 38.0, 24.0])
    colour *= (0.9 + 0.2 * fbm(p, 0.025, 2, seed=74))[:, None]
    return colour, np.full(len(p), 0.2)


def _duck(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Yellow paint with brush marks, an orange beak (duck.ply: the part beyond x = +5 cm above
    # z = +1.2 cm), dark eyes on the head (centre about (2.8, 0, 2.6) cm), a grey base.
    x, z = p[:, 0], p[:, 2]
    colour = np.array([236.0, 196.0, 52.0]) * (0.84 + 0.32 * fbm(p, 0.008, 3, seed=81))[:, None]
    strokes = value_noise(p, (0.02, 0.003, 0.003), seed=82)
    colour *= (0.93 + 0.14 * strokes)[:, None]
    beak = _cover(_box(0.050 - x, 0.012 - z))
    _paint(colour, beak, np.array([226.0, 110.0, 30.0]) * (0.9 + 0.2 * fbm(p, 0.004, 2, seed=83))[:, None])
    for side in (1.0, -1.0):
        eye = np.array([0.0393, 0.0162 * side, 0.0375])
        _paint(colour, _cover(np.linalg.norm(p - eye, axis=1) - 0.0045), [24.0, 22.0, 20.0])
        _paint(colour, _cover(np.linalg.norm(p - eye - [0.0012, 0.0, 0.0013], axis=1) - 0.0012),
               [240.0, 240.0, 236.0])
    base = _cover(z - (-0.0465))
    _paint(colour, base, [120.0, 110.0, 96.0])
    return colour, np.full(len(p), 0.35)


def _scan(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Any other mesh: plaster-like, mottled (fbm) with fine grey specks: texture everywhere.
    colour = np.array([214.0, 204.0, 186.0]) * (0.8 + 0.4 * fbm(p, 0.01, 3, seed=91))[:, None]
    specks = _smoothstep(0.86, 0.93, value_noise(p, 0.0015, seed=92))
    _paint(colour, 0.6 * specks, [96.0, 92.0, 88.0])
    return colour, np.full(len(p), 0.1)


_OBJECTS = {'cat': _cat, 'bottle': _bottle, 'mug': _mug, 'cup': _cup, 'animal': _animal,
            'duck': _duck, 'scan': _scan}


def surface_appearance(texture: str, points, normals=None) -> tuple[np.ndarray, np.ndarray]:
    """Colour (N, 3) uint8 RGB and specular weight (N,) in [0, 1] of the surface painted
    ``texture`` (an object's ``texture``: its name for the built-in objects and the shipped
    meshes, ``scan`` for other meshes) at object-frame points (N, 3) (see
    :func:`surface_colour`)."""
    try:
        paint = _OBJECTS[texture]
    except KeyError:
        raise ValueError(f'no texture {texture!r}: choose one of {", ".join(_OBJECTS)}') from None
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros((0, 3), np.uint8), np.zeros(0)
    colour, gloss = paint(p)
    return _to_uint8(colour), np.clip(gloss, 0.0, 1.0)


def surface_colour(texture: str, points, normals=None) -> np.ndarray:
    """True colour (N, 3) uint8 RGB of the surface painted ``texture`` at points (N, 3) in
    its OBJECT frame (metres). A pure function of the position: ``normals`` is accepted so that
    callers with normals can pass them, and is not needed by the current textures. Points
    off the surface get the colour of the pattern there (the patterns are solid textures)."""
    return surface_appearance(texture, points, normals)[0]


def surface_gloss(texture: str, points, normals=None) -> np.ndarray:
    """Specular weight (N,) in [0, 1] at object-frame points: glass and glaze shine, paper
    and bare clay do not. The highlight's exponent is ``SHININESS[texture]``."""
    return surface_appearance(texture, points, normals)[1]


def _to_uint8(colour: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(colour), 0, 255).astype(np.uint8)


# --- the scene -----------------------------------------------------------------------------

_PALETTE = np.array([[196.0, 72.0, 58.0], [58.0, 110.0, 168.0], [222.0, 184.0, 70.0],
                     [72.0, 140.0, 92.0], [120.0, 80.0, 140.0], [232.0, 228.0, 214.0]])


def backdrop_colour(points) -> np.ndarray:
    """Colour (N, 3) uint8 of the backdrop (a printed wallpaper) at tracker-frame points:
    pale colour clouds, a mottled print and scattered rings and dots of a six-colour palette.
    A solid texture, so any plane cut through it is textured everywhere."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    clouds = fbm(p, 0.09, 2, seed=41)
    colour = _mix([186.0, 172.0, 150.0], [128.0, 146.0, 164.0], _smoothstep(0.3, 0.7, clouds))
    colour *= (0.78 + 0.44 * fbm(p, 0.009, 2, seed=42))[:, None]
    # Motifs: one per 3D cell of 3 cm, a sphere (kept inside its cell) whose cut is a disc
    # or a ring.
    spacing = 0.03
    cell = np.floor(p / spacing).astype(np.int64)
    offset = np.stack([_cell_random(cell, 43 + k) for k in range(3)], axis=1)
    centre = (cell + 0.35 + 0.3 * offset) * spacing
    dist = np.linalg.norm(p - centre, axis=1)
    radius = spacing * (0.12 + 0.19 * _cell_random(cell, 46))
    kind = _cell_random(cell, 47)
    pick = np.minimum((_cell_random(cell, 48) * len(_PALETTE)).astype(np.int64), len(_PALETTE) - 1)
    disc = np.where(kind < 0.45, _cover(dist - radius), 0.0)
    ring = np.where((kind >= 0.45) & (kind < 0.8), _cover(np.abs(dist - radius) - 0.0022), 0.0)
    _paint(colour, 0.9 * np.maximum(disc, ring), _PALETTE[pick])
    return _to_uint8(colour)


def table_colour(points) -> np.ndarray:
    """Colour (N, 3) uint8 of the table (a green cutting mat) at tracker-frame points: a
    mottled green with light grid lines every 1 cm and bolder ones every 5 cm, in the
    tracker's x and y (the table is level in the tracker frame)."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    colour = np.array([44.0, 92.0, 78.0]) * (0.8 + 0.4 * fbm(p, 0.006, 2, seed=51))[:, None]
    x, y = p[:, 0], p[:, 1]

    def lines(v, period, half_width):
        return _cover(np.abs((v + 0.5 * period) % period - 0.5 * period) - half_width)

    _paint(colour, 0.7 * np.maximum(lines(x, 0.01, 0.0007), lines(y, 0.01, 0.0007)), [120.0, 170.0, 150.0])
    _paint(colour, 0.9 * np.maximum(lines(x, 0.05, 0.0013), lines(y, 0.05, 0.0013)), [200.0, 226.0, 214.0])
    return _to_uint8(colour)
