"""A stereo pair of a surface given only as samples: point splatting, for benchmarks.

The validation sessions (``../shared/data/validation_sessions``) carry their object as
60,000 surface samples, without a mesh, colours or images. To judge the map's texture on
those hands and objects, ``bench_texture_sessions.py --set validation`` renders a pair of
them with this renderer: it shares nothing with ``inhand_sim.stereo_rig``'s ray caster but
the rig's geometry (a scene we did not draw with our own renderer either).

Each sample is a disc in its tangent plane, of radius (as seen) 1.2 times its mean distance
to its three nearest samples (so neighbouring discs overlap and the surface is closed; 0.8-3
px), drawn into a depth buffer: at each pixel centre, the disc whose plane the pixel's ray
meets first wins. Shading: ambient 0.35 plus a
two-sided Lambert term (0.7) of a point light 16 cm up and to the left of the left camera,
with each sample's normal from its 12 nearest samples (principal components). Behind the
object, a fronto-parallel backdrop 0.25 m beyond its median depth, printed with
``inhand_sim.textures.backdrop_colour`` at 0.9 of its albedo. Then a Gaussian blur of 0.6 px
and pixel noise of 2 grey levels, as the ray caster's camera effects. The truth: the depth of
the left image (the backdrop's where no sample is) and the object's pixels.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

NEIGHBOURS = 12          # samples giving a sample's normal
DISC = 1.2               # disc radius / the mean distance to the 3 nearest samples
DISC_PX = (0.8, 3.0)     # px, at least (no pixel centre between discs), at most (a lone sample)
LIGHT = np.array([-0.16, -0.16, 0.0])   # left camera frame, m: up and to the left
AMBIENT, DIFFUSE, BACKDROP_LIGHT = 0.35, 0.7, 0.9
BLUR_PX, NOISE = 0.6, 2.0


def normals_and_spacing(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each sample's unit normal (up to sign) and mean distance to its 3 nearest samples."""
    distances, neighbours = cKDTree(points).query(points, k=NEIGHBOURS)
    around = points[neighbours] - points[neighbours].mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum('nki,nkj->nij', around, around))
    return vectors[:, :, 0], distances[:, 1:4].mean(axis=1)


def depth_buffer(local: np.ndarray, normals: np.ndarray, radius: np.ndarray, rig
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Discs of ``radius`` px around the samples ``local`` (N, 3, camera frame), each in its
    tangent plane (``normals``, camera frame): per pixel the nearest one's depth (inf where
    none) and index (-1). A pixel's depth on a disc is where its ray meets the disc's plane
    (within ``radius``'s worth of depth of the sample's own, at grazing angles)."""
    width, height, focal = rig.width, rig.height, rig.focal
    z = local[:, 2]
    safe = np.where(z > 0, z, 1.0)
    u, v = focal * local[:, 0] / safe + rig.cx, focal * local[:, 1] / safe + rig.cy
    reach = int(np.ceil(radius.max())) if len(radius) else 0
    column, row = np.floor(u + 0.5).astype(np.intp), np.floor(v + 0.5).astype(np.intp)
    facing = np.sum(normals * local, axis=1)          # n . p: the plane n . x = n . p
    pixels, depths, owners = [], [], []
    for dx in range(-reach, reach + 1):
        for dy in range(-reach, reach + 1):
            c, r = column + dx, row + dy
            inside = ((c - u) ** 2 + (r - v) ** 2 <= radius ** 2) & (c >= 0) & (c < width) \
                & (r >= 0) & (r < height) & (z > 0)
            k = np.flatnonzero(inside)
            ray = np.column_stack([(c[k] - rig.cx) / focal, (r[k] - rig.cy) / focal,
                                   np.ones(len(k))])
            along = np.sum(normals[k] * ray, axis=1)
            on_plane = facing[k] / np.where(np.abs(along) > 1e-9, along, 1e-9)
            slack = radius[k] * z[k] / focal                # the disc's radius in metres
            pixels.append(r[k] * width + c[k])
            depths.append(np.clip(on_plane, z[k] - slack, z[k] + slack))
            owners.append(k)
    pixel, depth, owner = (np.concatenate(a) for a in (pixels, depths, owners))
    order = np.lexsort((depth, pixel))                       # by pixel, nearest first
    first = order[np.unique(pixel[order], return_index=True)[1]]
    nearest = np.full(width * height, np.inf)
    who = np.full(width * height, -1, dtype=np.intp)
    nearest[pixel[first]] = depth[first]
    who[pixel[first]] = owner[first]
    return nearest.reshape(height, width), who.reshape(height, width)


def _render(points, normals, spacing, albedo, rotation, position, rig, backdrop_z, light,
            rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One camera (axes ``rotation``'s columns, centre ``position``): image, depth, mask."""
    from inhand_sim.textures import backdrop_colour
    local = (points - position) @ rotation
    safe = np.where(local[:, 2] > 0, local[:, 2], 1.0)
    radius = np.clip(DISC * rig.focal * spacing / safe, *DISC_PX)
    depth, who = depth_buffer(local, normals @ rotation, radius, rig)
    mask = who >= 0
    columns, rows = np.meshgrid(np.arange(rig.width), np.arange(rig.height))
    rays = np.stack([(columns - rig.cx) / rig.focal, (rows - rig.cy) / rig.focal,
                     np.ones(columns.shape)], axis=-1)
    on_backdrop = (rays * backdrop_z) @ rotation.T + position
    image = backdrop_colour(on_backdrop.reshape(-1, 3)).reshape(rig.height, rig.width, 3) \
        * BACKDROP_LIGHT
    seen = who[mask]
    to_light = light - points[seen]
    to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
    shade = AMBIENT + DIFFUSE * np.abs(np.sum(normals[seen] * to_light, axis=1))
    image[mask] = albedo[seen] * shade[:, None]
    image = ndimage.gaussian_filter(image, (BLUR_PX, BLUR_PX, 0)) \
        + rng.normal(0.0, NOISE, image.shape)
    depth = np.where(mask, depth, backdrop_z)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8), depth, mask


def render_samples(rig, points: np.ndarray, albedo: np.ndarray, rng: np.random.Generator,
                   backdrop_offset: float = 0.25) -> SimpleNamespace:
    """A pair of the surface ``points`` (N, 3, tracker frame) of colours ``albedo`` (N, 3)
    by ``rig`` (an ``inhand_sim.stereo_rig.StereoRig``): what ``inhand_sim.session``'s
    bag writer and truth need of a rendered pair (``left``, ``right``, their cameras,
    ``depth``, ``mask``, ``focal``, ``baseline``, ``camera_pose``)."""
    points = np.asarray(points, dtype=float)
    normals, spacing = normals_and_spacing(points)
    rotation, position = rig.rotation, rig.position
    backdrop_z = float(np.median((points - position) @ rotation[:, 2])) + backdrop_offset
    light = position + rotation @ LIGHT
    colours = np.asarray(albedo, dtype=float)
    left, depth, mask = _render(points, normals, spacing, colours, rotation, position, rig,
                                backdrop_z, light, rng)
    right, _, _ = _render(points, normals, spacing, colours, rotation, rig.right_position,
                          rig, backdrop_z, light, rng)
    left_camera, right_camera = rig.cameras()
    return SimpleNamespace(left=left, right=right, left_camera=left_camera,
                           right_camera=right_camera, depth=depth.astype(np.float32),
                           mask=mask, focal=rig.focal, baseline=rig.baseline,
                           camera_pose=rig.camera_pose)
