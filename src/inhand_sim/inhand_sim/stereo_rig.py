"""A calibrated virtual stereo rig that renders image pairs of the simulated objects.

The images are ray-cast against the objects' signed distance functions (exact for the
unions of primitives of :mod:`inhand_sim.objects`; a mesh's distance grid, within a fraction
of a millimetre of its triangles, for :mod:`inhand_sim.mesh_objects`) and painted with their
procedural textures (:mod:`inhand_sim.textures`), so every pixel has an exact truth: which
surface it sees, how far away, at what disparity, in what colour.

Conventions
-----------
* Frames. ``polhemus_source`` (the tracker): x forward, y right, z down. The camera optical
  frame ``stereo_left_optical``: z forward (along the optical axis), x right, y down in the
  image. Poses are (position, quaternion x, y, z, w) with ``p_parent = R p_child + t``:
  ``StereoRig.camera_pose`` = ``[x, y, z, qx, qy, qz, qw]`` is the stereo node's
  ``camera_pose`` parameter, the pose of the left camera in the tracker frame; the object
  pose is the object frame in the tracker frame, as in :mod:`inhand_sim.session`
  (``p_tracker = R_o p_object + t_o``).
* The stereo frame. ``camera_pose`` is the pose of the RECTIFIED left camera (the frame in
  which disparities become 3D points). The right camera's rectified frame has the same axes,
  its centre ``baseline`` metres along the left camera's +x. When a camera's CameraInfo ``R``
  (raw -> rectified rotation) is not the identity, its raw frame is turned by ``R^T`` from
  that: ``p_rectified = R p_raw``.
* Pixels. OpenCV's: pixel (column u, row v) has its centre at (u, v); (0, 0) is the centre of
  the top-left pixel. Images are (H, W, 3) uint8 RGB (``rgb8``), row 0 at the top.
* Cameras. :class:`inhand_stereo.camera_model.CameraModel` with CameraInfo's fields: ``K`` of
  the raw image, ``D`` plumb_bob (k1, k2, t1, t2, k3), ``R`` raw -> rectified, ``P`` of the
  rectified image; the right camera's ``P[0, 3] = -fx * baseline``. By default the images are
  already rectified: ``D = 0``, ``R = I``, ``P = [K | t]``. With ``distortion`` the raw images
  are what a camera with that lens sees: each raw pixel's ray is found by inverting the
  distortion exactly (to 1e-12) and cast; rectifying them with the CameraInfo (OpenCV's
  ``initUndistortRectifyMap(K, D, R, P)``) gives the undistorted images.
* Truth (:class:`RenderedPair`) is given in the RECTIFIED left image (identical to the left image
  when it is already rectified): ``depth`` = z in the left rectified camera frame (m) of the
  surface each pixel centre's ray meets first (object, table or backdrop: every ray meets
  something), ``disparity`` = ``fx * baseline / depth`` (px; ``x_left - x_right`` of that
  surface point, as DisparityImage defines it with equal principal points), ``mask`` = the
  pixel sees the object, ``surface`` = which surface (``BACKDROP``, ``TABLE``, ``OBJECT``),
  ``albedo`` = the surface's true colour there (unshaded, :func:`surface_colour`).

The scene
---------
The object at its pose; a backdrop plane (a printed wallpaper) facing the camera
``backdrop_distance`` behind the object's centre along the optical axis (every ray meets it);
optionally the table the object stands on in a static session (the plane of the object's
``table_z``, a green cutting mat). One point light near the camera (``light``, left camera
frame; by default 16 cm up and to the left of the left camera). Shading: Lambert plus
ambient, Phong highlights on glossy surfaces (glass, glaze: they differ between the two
cameras, as real highlights do), soft shadows cast by the object (on the table, the backdrop
and itself). One ray per pixel centre, and ``edge_samples``^2 rays averaged at the pixels
where the surface seen changes (silhouettes, occlusions: the textures themselves are
band-limited, see :mod:`inhand_sim.textures`); ``supersample`` > 1 averages that many^2 rays
everywhere instead (a reference render). Camera effects, in the raw image: Gaussian blur
(``blur_sigma`` px, the lens and the sensor's pixel area), Gaussian pixel noise
(``noise_sigma`` grey levels, per channel) from ``rng``, rounding to uint8. No gamma curve:
grey levels are albedo times shading.

Speed: the sphere tracing (and the shadow rays, and the shading) run in compiled kernels
(numba) over a packed copy of the object's primitives (or of a mesh's distance grid, the
same trilinear arithmetic), whose distances equal the object's ``sdf`` (a test holds them to
1e-12); rays march only inside the object's bounding box, skipping primitives whose bounding
sphere is farther than the nearest so far, and stop within 10 um of the surface. The hits
are then evaluated with the object's own ``sdf_grad`` (normals, and the residual |sdf|
reported in ``RenderedPair.max_sdf_residual``).
A 640 x 480 pair takes about 0.7-1 s on one core (the first call in a fresh cache compiles
the kernels: 10-20 s, then cached beside the module).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple, TypeVar, cast

import numba
import numpy as np
from scipy.ndimage import gaussian_filter

from inhand_common.rotations import (
    euler_zyx_to_quaternion,
    matrix_to_quaternion,
    quaternion_multiply,
    quaternion_normalize,
    quaternion_to_matrix,
)
from inhand_sim.catalogue import load_object
from inhand_sim.mesh_objects import MeshObject
from inhand_sim.objects import ArcTube, Ellipsoid, ObjectModel, RevolvedBox, RoundCone, SolidObject, Sphere
from inhand_sim.textures import SHININESS, backdrop_colour, surface_appearance, table_colour
from inhand_stereo.camera_model import CameraModel

__all__ = [
    'BACKDROP',
    'DEFAULT_DISTANCE',
    'DEFAULT_TARGET',
    'DEFAULT_VIEW_DIRECTION',
    'OBJECT',
    'TABLE',
    'Plane',
    'RenderedPair',
    'StereoRig',
    'compiled_sdf',
    'distort_normalized',
    'look_at_pose',
    'render_pair',
    'static_object_pose',
    'table_plane',
    'undistort_normalized',
]

BACKDROP, TABLE, OBJECT = 0, 1, 2

DEFAULT_TARGET = (0.25, 0.0, 0.05)          # the static object's centre, tracker frame
DEFAULT_VIEW_DIRECTION = (0.15, -0.8, -0.55)  # target -> camera: from the side, 34 degrees up
DEFAULT_DISTANCE = 0.42                     # m
DEFAULT_LIGHT = (-0.1, -0.12, 0.0)          # point light, left camera frame: left of and above it


# --- poses ---------------------------------------------------------------------------------

def look_at_pose(target, direction, distance: float, roll_deg: float = 0.0) -> tuple[float, ...]:
    """Camera pose ``(x, y, z, qx, qy, qz, qw)`` in the tracker frame of a camera placed at
    ``target + distance * direction / |direction|`` looking at ``target`` (all tracker
    frame), with the image's "down" (+y) along the tracker's down (+z) as far as the view
    allows (tracker +x when looking straight up or down), then turned by ``roll_deg`` about
    the optical axis."""
    target = np.asarray(target, dtype=float)
    d = np.asarray(direction, dtype=float)
    if not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0.0 or not distance > 0:
        raise ValueError('look_at_pose: need a non-zero direction and a positive distance')
    d = d / np.linalg.norm(d)
    z = -d
    down = np.array([0.0, 0.0, 1.0])
    y = down - (down @ z) * z
    if np.linalg.norm(y) < 1e-6:
        down = np.array([1.0, 0.0, 0.0])
        y = down - (down @ z) * z
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    rotation = np.stack([x, y, z], axis=1)
    roll = math.radians(roll_deg)
    turn = np.array([[math.cos(roll), -math.sin(roll), 0.0], [math.sin(roll), math.cos(roll), 0.0],
                     [0.0, 0.0, 1.0]])
    q = matrix_to_quaternion(rotation @ turn)
    position = target + distance * d
    return tuple(float(v) for v in (*position, *q))


def static_object_pose(obj: SolidObject | str, centre=DEFAULT_TARGET, yaw_deg: float = 0.0
                       ) -> tuple[np.ndarray, np.ndarray]:
    """The pose (position, quaternion xyzw) of a static session's object (the formula of
    ``inhand_sim.session``): upright (object +z = tracker -z), its bounding-box centre at
    ``centre``, turned by ``yaw_deg`` about the vertical."""
    obj = load_object(obj) if isinstance(obj, str) else obj
    q = quaternion_normalize(quaternion_multiply(
        euler_zyx_to_quaternion(math.radians(yaw_deg), 0.0, 0.0),
        euler_zyx_to_quaternion(0.0, 0.0, math.pi)))
    position = np.asarray(centre, dtype=float) - quaternion_to_matrix(q) @ obj.centre
    return position, q


class Plane(NamedTuple):
    """A plane in the tracker frame: a point on it and its normal (towards the viewer)."""
    point: np.ndarray
    normal: np.ndarray


def table_plane(obj: SolidObject, object_pose) -> Plane:
    """The table the object stands on (the plane ``z = table_z`` of the object frame) in the
    tracker frame, normal up out of the table. Meaningful for an upright, static object."""
    position, q = _pose(object_pose)
    rotation = quaternion_to_matrix(q)
    foot = np.array([obj.centre[0], obj.centre[1], obj.table_z])
    return Plane(rotation @ foot + position, rotation[:, 2].copy())


def _pose(object_pose) -> tuple[np.ndarray, np.ndarray]:
    position, q = object_pose
    position = np.asarray(position, dtype=float).reshape(3)
    q = quaternion_normalize(np.asarray(q, dtype=float).reshape(4))
    return position, q


# --- the rig -------------------------------------------------------------------------------

_DEFAULT_POSE = look_at_pose(DEFAULT_TARGET, DEFAULT_VIEW_DIRECTION, DEFAULT_DISTANCE)


@dataclass(frozen=True)
class StereoRig:
    """Two identical pinhole cameras side by side, ``baseline`` apart along the left camera's
    x; ``focal``, ``cx``, ``cy`` in pixels; ``camera_pose`` the left (rectified) camera in
    the tracker frame, ``[x, y, z, qx, qy, qz, qw]``. The default looks at the static object
    centre [0.25, 0, 0.05] from 0.42 m, from the tracker's left (-y) and 34 degrees above."""

    width: int = 640
    height: int = 480
    focal: float = 600.0
    cx: float = 321.7
    cy: float = 238.2
    baseline: float = 0.07
    camera_pose: tuple = field(default=_DEFAULT_POSE)

    def __post_init__(self):
        problems = []
        if self.width < 8 or self.height < 8:
            problems.append(f'image size {self.width}x{self.height} is too small')
        if not self.focal > 0:
            problems.append(f'focal {self.focal} must be > 0')
        if not self.baseline > 0:
            problems.append(f'baseline {self.baseline} must be > 0')
        pose = np.asarray(self.camera_pose, dtype=float)
        if pose.shape != (7,) or not np.all(np.isfinite(pose)) or np.linalg.norm(pose[3:]) < 1e-9:
            problems.append('camera_pose must be 7 finite numbers [x, y, z, qx, qy, qz, qw]')
        if problems:
            raise ValueError('StereoRig: ' + '; '.join(problems))
        object.__setattr__(self, 'camera_pose', tuple(float(v) for v in pose))

    @classmethod
    def looking_at(cls, target=DEFAULT_TARGET, direction=DEFAULT_VIEW_DIRECTION,
                   distance: float = DEFAULT_DISTANCE, roll_deg: float = 0.0, **fields) -> StereoRig:
        """A rig whose left camera looks at ``target`` from ``distance`` along ``direction``
        (target -> camera, tracker frame); see :func:`look_at_pose`."""
        return cls(camera_pose=look_at_pose(target, direction, distance, roll_deg), **fields)

    @property
    def position(self) -> np.ndarray:
        """The left camera's optical centre, tracker frame."""
        return np.array(self.camera_pose[:3])

    @property
    def rotation(self) -> np.ndarray:
        """Left (rectified) camera axes in the tracker frame (columns: x, y, z = optical axis)."""
        return quaternion_to_matrix(np.array(self.camera_pose[3:]))

    @property
    def right_position(self) -> np.ndarray:
        """The right camera's optical centre, tracker frame."""
        return self.position + self.baseline * self.rotation[:, 0]

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.focal, 0.0, self.cx], [0.0, self.focal, self.cy], [0.0, 0.0, 1.0]])

    def cameras(self, distortion=None, rectification=None) -> tuple[CameraModel, CameraModel]:
        """The left and right CameraInfo (see the module docstring). ``distortion``: None, one
        plumb_bob (k1, k2, t1, t2, k3) for both cameras, or a pair of them; ``rectification``:
        None or a pair of 3x3 rotations (CameraInfo R, raw -> rectified)."""
        d_left, d_right = _per_camera_distortion(distortion)
        r_left, r_right = _per_camera_rotation(rectification)
        K = self.K
        out = []
        for name, d, r, shift in (('left', d_left, r_left, 0.0),
                                  ('right', d_right, r_right, -self.focal * self.baseline)):
            P = np.hstack([K, np.array([[shift], [0.0], [0.0]])])
            model = CameraModel(self.width, self.height, K.copy(), d, r, P, 'plumb_bob', name)
            model.check()
            out.append(model)
        return out[0], out[1]

    def project(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Tracker-frame points (N, 3) -> (u_left, v, u_right, z) in the RECTIFIED images:
        pixel coordinates (OpenCV convention) and the depth z in the left camera frame;
        ``u_left - u_right = focal * baseline / z``."""
        p = (np.asarray(points, dtype=float).reshape(-1, 3) - self.position) @ self.rotation
        z = p[:, 2]
        u = self.focal * p[:, 0] / z + self.cx
        v = self.focal * p[:, 1] / z + self.cy
        return u, v, u - self.focal * self.baseline / z, z


def _per_camera_distortion(distortion) -> tuple[np.ndarray, np.ndarray]:
    if distortion is None:
        return np.zeros(5), np.zeros(5)
    d = np.asarray(distortion, dtype=float)
    if d.shape == (5,):
        return d.copy(), d.copy()
    if d.shape == (2, 5):
        return d[0].copy(), d[1].copy()
    raise ValueError('distortion must be (k1, k2, t1, t2, k3) or a pair of them')


def _per_camera_rotation(rectification) -> tuple[np.ndarray, np.ndarray]:
    if rectification is None:
        return np.eye(3), np.eye(3)
    r = np.asarray(rectification, dtype=float)
    if r.shape != (2, 3, 3):
        raise ValueError('rectification must be a pair of 3x3 rotations (left R, right R)')
    for m in r:
        if not np.allclose(m @ m.T, np.eye(3), atol=1e-9) or np.linalg.det(m) < 0:
            raise ValueError('rectification: each R must be a rotation')
    return r[0].copy(), r[1].copy()


# --- plumb_bob -------------------------------------------------------------------------------

def distort_normalized(x, y, D) -> tuple[np.ndarray, np.ndarray]:
    """plumb_bob: ideal normalised coordinates -> distorted ones (OpenCV's model)."""
    k1, k2, t1, t2, k3 = (float(v) for v in np.asarray(D, dtype=float)[:5])
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * t1 * x * y + t2 * (r2 + 2.0 * x * x)
    yd = y * radial + t1 * (r2 + 2.0 * y * y) + 2.0 * t2 * x * y
    return xd, yd


def undistort_normalized(xd, yd, D, tolerance: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`distort_normalized` by Newton's method on the 2x2 system (a few steps
    for lenses like real ones); ValueError if some point does not converge (a distortion
    too strong to invert over the image)."""
    xd = np.asarray(xd, dtype=float)
    yd = np.asarray(yd, dtype=float)
    k1, k2, t1, t2, k3 = (float(v) for v in np.asarray(D, dtype=float)[:5])
    x, y = xd.copy(), yd.copy()
    for _ in range(50):
        fx, fy = distort_normalized(x, y, D)
        ex, ey = fx - xd, fy - yd
        if max(float(np.max(np.abs(ex), initial=0.0)), float(np.max(np.abs(ey), initial=0.0))) < tolerance:
            return x, y
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)         # d radial / d r2
        jxx = radial + 2.0 * x * x * dradial + 2.0 * t1 * y + 6.0 * t2 * x
        jxy = 2.0 * x * y * dradial + 2.0 * t1 * x + 2.0 * t2 * y
        jyx = 2.0 * x * y * dradial + 2.0 * t1 * x + 2.0 * t2 * y
        jyy = radial + 2.0 * y * y * dradial + 6.0 * t1 * y + 2.0 * t2 * x
        det = jxx * jyy - jxy * jyx
        x = x - (jyy * ex - jxy * ey) / det
        y = y - (-jyx * ex + jxx * ey) / det
    raise ValueError('undistort_normalized: the distortion cannot be inverted over the image '
                     '(too strong for plumb_bob at the corners?)')


# --- compiled sphere tracing -----------------------------------------------------------------

_Function = TypeVar('_Function', bound=Callable[..., object])


def _compiled(function: _Function) -> _Function:
    """``numba.njit(cache=True, nogil=True)``, keeping the Python signature."""
    return cast(_Function, numba.njit(cache=True, nogil=True)(function))


_SPHERE, _ROUND_CONE, _ELLIPSOID, _REVOLVED_BOX, _ARC_TUBE, _GRID = range(6)
_HIT_EPS = 1e-5          # m: sphere tracing stops this close to the surface
_GRAZING = 1e-4          # m: a ray out of steps this close counts as a hit
_MAX_STEPS = 1000
_BOX_MARGIN = 0.002      # m around the object's bounding box
_PENUMBRA = 12.0         # soft shadows: visibility min(_PENUMBRA * sdf / t) along the shadow ray
_SHADOW_REACH = 0.05     # m around the object where its penumbra is computed (t up to 0.6 m)
_PARAMS = 24          # per primitive: its own up to 17, then a bounding sphere at 20..23


def _pack(obj: SolidObject) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The object as (kinds (P,), params (P, 24), grid) for the compiled kernels: each
    primitive's quantities that its numpy ``sdf_grad`` uses and a bounding sphere (centre,
    radius) at 20..23; a mesh as one ``_GRID`` entry (the distance grid's origin, spacing,
    shape and the mesh's box) with its grid values (a 1 x 1 x 1 dummy for primitives)."""
    if isinstance(obj, MeshObject):
        grid = obj.grid
        row = np.zeros((1, _PARAMS))
        row[0, 0:3], row[0, 3], row[0, 4:7] = grid.origin, grid.spacing, grid.values.shape
        row[0, 7:10], row[0, 10:13] = grid.box[0], grid.box[1]
        row[0, 20:23], row[0, 23] = obj.centre, 0.0
        return np.array([_GRID], dtype=np.int64), row, np.ascontiguousarray(grid.values)
    if not isinstance(obj, ObjectModel):
        raise TypeError(f'stereo_rig cannot ray-cast a {type(obj).__name__}')
    kinds = np.zeros(len(obj.primitives), dtype=np.int64)
    params = np.zeros((len(obj.primitives), _PARAMS))
    for i, prim in enumerate(obj.primitives):
        row = params[i]
        if isinstance(prim, Sphere):
            kinds[i] = _SPHERE
            row[0:3], row[3] = prim.centre, prim.radius
        elif isinstance(prim, RoundCone):
            kinds[i] = _ROUND_CONE
            row[0:3], row[3:6], row[6:9] = prim.a, prim.b, prim.axis
            row[9:14] = prim.r1, prim.r2, prim.s, prim.c, prim.length
        elif isinstance(prim, Ellipsoid):
            kinds[i] = _ELLIPSOID
            row[0:3], row[3:6], row[6:15] = prim.centre, prim.radii, prim.rotation.reshape(9)
            row[15] = prim.min_radius
        elif isinstance(prim, RevolvedBox):
            kinds[i] = _REVOLVED_BOX
            rr = prim.rounding
            if prim.r_in > 0.0:
                centre_r, half_r = 0.5 * (prim.r_in + prim.r_out), 0.5 * (prim.r_out - prim.r_in)
            else:
                centre_r, half_r = 0.0, prim.r_out
            row[0:3], row[3:12] = prim.origin, prim.rotation.reshape(9)
            row[12:17] = (centre_r, 0.5 * (prim.z0 + prim.z1), max(half_r - rr, 0.0),
                          max(0.5 * (prim.z1 - prim.z0) - rr, 0.0), rr)
        elif isinstance(prim, ArcTube):
            kinds[i] = _ARC_TUBE
            row[0:3], row[3:12] = prim.centre, prim.rotation.reshape(9)
            row[12:15] = prim.ra, prim.rb, prim.alpha
        else:
            raise TypeError(f'stereo_rig cannot ray-cast a {type(prim).__name__}: add it to _pack '
                            'and _primitive_sdf')
        box = prim.bounds()
        row[20:23] = box.mean(axis=0)
        row[23] = 0.5 * np.linalg.norm(box[1] - box[0])
    return kinds, params, np.zeros((1, 1, 1))


@_compiled
def _grid_sdf(q, grid, x, y, z):
    """The distance grid's value at a point (DistanceGrid.evaluate's arithmetic, in the same
    order, so that the two agree to the last bits): trilinear inside, the lower bound
    outside."""
    h = q[3]
    u = ((x - q[0]) / h, (y - q[1]) / h, (z - q[2]) / h)
    c = np.empty(3)
    f = np.empty(3)
    index = np.empty(3, dtype=np.int64)
    away2 = 0.0
    for axis in range(3):
        top = q[4 + axis] - 1.0
        c[axis] = min(max(u[axis], 0.0), top)
        index[axis] = min(int(math.floor(c[axis])), int(top) - 1)
        f[axis] = c[axis] - index[axis]
        away2 += ((u[axis] - c[axis]) * h) ** 2
    i, j, k = index[0], index[1], index[2]
    fx, fy, fz = f[0], f[1], f[2]
    c00 = grid[i, j, k] + fz * (grid[i, j, k + 1] - grid[i, j, k])
    c01 = grid[i, j + 1, k] + fz * (grid[i, j + 1, k + 1] - grid[i, j + 1, k])
    c10 = grid[i + 1, j, k] + fz * (grid[i + 1, j, k + 1] - grid[i + 1, j, k])
    c11 = grid[i + 1, j + 1, k] + fz * (grid[i + 1, j + 1, k + 1] - grid[i + 1, j + 1, k])
    c0 = c00 + fy * (c01 - c00)
    c1 = c10 + fy * (c11 - c10)
    d = c0 + fx * (c1 - c0)
    if away2 > 0.0:
        lower = d - math.sqrt(away2)
        bx = x - min(max(x, q[7]), q[10])
        by = y - min(max(y, q[8]), q[11])
        bz = z - min(max(z, q[9]), q[12])
        box = math.sqrt(bx * bx + by * by + bz * bz)
        d = box if box > lower else lower
    return d


@_compiled
def _primitive_sdf(kind, q, grid, x, y, z):
    if kind == 5:    # a mesh's distance grid
        return _grid_sdf(q, grid, x, y, z)
    if kind == 0:    # Sphere
        return math.sqrt((x - q[0]) ** 2 + (y - q[1]) ** 2 + (z - q[2]) ** 2) - q[3]
    if kind == 1:    # RoundCone
        ax, ay, az = x - q[0], y - q[1], z - q[2]
        along = ax * q[6] + ay * q[7] + az * q[8]
        rx, ry, rz = ax - along * q[6], ay - along * q[7], az - along * q[8]
        radial = math.sqrt(rx * rx + ry * ry + rz * rz)
        w = along * q[12] - radial * q[11]
        if w < 0.0:
            return math.sqrt(ax * ax + ay * ay + az * az) - q[9]
        if w > q[13] * q[12]:
            return math.sqrt((x - q[3]) ** 2 + (y - q[4]) ** 2 + (z - q[5]) ** 2) - q[10]
        return along * q[11] + radial * q[12] - q[9]
    if kind == 2:    # Ellipsoid: local = (p - centre) @ rotation
        vx, vy, vz = x - q[0], y - q[1], z - q[2]
        k0 = 0.0
        k1 = 0.0
        for j in range(3):
            local = vx * q[6 + j] + vy * q[9 + j] + vz * q[12 + j]
            r = q[3 + j]
            k0 += (local / r) ** 2
            k1 += (local / (r * r)) ** 2
        k0 = math.sqrt(k0)
        k1 = math.sqrt(k1)
        if k0 > 1.0:
            return k0 * (k0 - 1.0) / max(k1, 1e-300)
        return q[15] * (k0 - 1.0)
    if kind == 3:    # RevolvedBox
        vx, vy, vz = x - q[0], y - q[1], z - q[2]
        l0 = vx * q[3] + vy * q[6] + vz * q[9]
        l1 = vx * q[4] + vy * q[7] + vz * q[10]
        l2 = vx * q[5] + vy * q[8] + vz * q[11]
        qx = abs(math.hypot(l0, l1) - q[12]) - q[14]
        qz = abs(l2 - q[13]) - q[15]
        return math.hypot(max(qx, 0.0), max(qz, 0.0)) + min(max(qx, qz), 0.0) - q[16]
    # ArcTube
    vx, vy, vz = x - q[0], y - q[1], z - q[2]
    l0 = vx * q[3] + vy * q[6] + vz * q[9]
    l1 = vx * q[4] + vy * q[7] + vz * q[10]
    l2 = vx * q[5] + vy * q[8] + vz * q[11]
    ra, alpha = q[12], q[14]
    theta = math.atan2(l1, l0)
    if abs(theta) <= alpha:
        nx, ny = ra * math.cos(theta), ra * math.sin(theta)
    else:
        ex, ey = ra * math.cos(alpha), ra * math.sin(alpha)
        dp = math.sqrt((l0 - ex) ** 2 + (l1 - ey) ** 2 + l2 * l2)
        dm = math.sqrt((l0 - ex) ** 2 + (l1 + ey) ** 2 + l2 * l2)
        nx, ny = (ex, ey) if dp <= dm else (ex, -ey)
    return math.sqrt((l0 - nx) ** 2 + (l1 - ny) ** 2 + l2 * l2) - q[13]


@_compiled
def _union_sdf(kinds, params, grid, x, y, z):
    best = math.inf
    for i in range(kinds.shape[0]):
        d = _primitive_sdf(kinds[i], params[i], grid, x, y, z)
        if d < best:
            best = d
    return best


@_compiled
def _union_bound(kinds, params, grid, x, y, z):
    """A lower bound of the distance to the union, for sphere tracing: primitives whose
    bounding sphere is farther than the best so far are skipped (their distance is at least
    that far). Near the surface it is the union SDF itself."""
    best = math.inf
    for i in range(kinds.shape[0]):
        q = params[i]
        reach = math.sqrt((x - q[20]) ** 2 + (y - q[21]) ** 2 + (z - q[22]) ** 2) - q[23]
        if reach >= best:
            continue
        d = _primitive_sdf(kinds[i], q, grid, x, y, z)
        if d < best:
            best = d
    return best


@_compiled
def _sdf_points(points, kinds, params, grid, out):
    for i in range(points.shape[0]):
        out[i] = _union_sdf(kinds, params, grid, points[i, 0], points[i, 1], points[i, 2])


@_compiled
def _box_interval(ox, oy, oz, dx, dy, dz, lo, hi):
    """Entry and exit t of a ray through an axis-aligned box (exit < entry: missed)."""
    t_near, t_far = -math.inf, math.inf
    for o, d, a, b in ((ox, dx, lo[0], hi[0]), (oy, dy, lo[1], hi[1]), (oz, dz, lo[2], hi[2])):
        if abs(d) < 1e-300:
            if o < a or o > b:
                return 1.0, 0.0
            continue
        t1, t2 = (a - o) / d, (b - o) / d
        t_near = max(t_near, min(t1, t2))
        t_far = min(t_far, max(t1, t2))
    return t_near, t_far


@_compiled
def _march(ox, oy, oz, dx, dy, dz, t, t_end, kinds, params, grid):
    """Sphere tracing of a unit-direction ray from ``t`` to ``t_end``: the first t with
    sdf < _HIT_EPS (inf if none). A ray that runs out of steps still close to the surface
    (a grazing ray, sdf < _GRAZING) counts as a hit there."""
    h = math.inf
    for _ in range(_MAX_STEPS):
        if t > t_end:
            return math.inf
        h = _union_bound(kinds, params, grid, ox + t * dx, oy + t * dy, oz + t * dz)
        if h < _HIT_EPS:
            return t
        t += h
    return t if h < _GRAZING else math.inf


@_compiled
def _to_object(rot, pos, x, y, z):
    """Tracker -> object frame of a point (``R^T (p - t)``); pass pos = 0 for a vector."""
    x, y, z = x - pos[0], y - pos[1], z - pos[2]
    return (x * rot[0, 0] + y * rot[1, 0] + z * rot[2, 0],
            x * rot[0, 1] + y * rot[1, 1] + z * rot[2, 1],
            x * rot[0, 2] + y * rot[1, 2] + z * rot[2, 2])


@_compiled
def _trace(origin, dirs, rot, pos, lo, hi, kinds, params, grid, plane_points, plane_normals,
           plane_labels, t_out, label_out):
    """First surface along each unit ray from ``origin`` (tracker frame): the object (sphere
    tracing inside its bounding box) or one of the planes. inf and label 255: nothing."""
    zero = np.zeros(3)
    ox, oy, oz = _to_object(rot, pos, origin[0], origin[1], origin[2])
    for i in range(dirs.shape[0]):
        dx, dy, dz = _to_object(rot, zero, dirs[i, 0], dirs[i, 1], dirs[i, 2])
        best, label = math.inf, 255
        t_in, t_exit = _box_interval(ox, oy, oz, dx, dy, dz, lo, hi)
        t_in = max(t_in, 0.0)
        if t_exit > t_in:
            best = _march(ox, oy, oz, dx, dy, dz, t_in, t_exit, kinds, params, grid)
            if best < math.inf:
                label = 2
        for k in range(plane_points.shape[0]):
            denom = (dirs[i, 0] * plane_normals[k, 0] + dirs[i, 1] * plane_normals[k, 1]
                     + dirs[i, 2] * plane_normals[k, 2])
            if abs(denom) < 1e-12:
                continue
            tp = ((plane_points[k, 0] - origin[0]) * plane_normals[k, 0]
                  + (plane_points[k, 1] - origin[1]) * plane_normals[k, 1]
                  + (plane_points[k, 2] - origin[2]) * plane_normals[k, 2]) / denom
            if 0.0 < tp < best:
                best, label = tp, plane_labels[k]
        t_out[i] = best
        label_out[i] = label


@_compiled
def _shade_kernel(points, normals, labels, albedo, gloss, shininess, eye, light, rot, pos, lo,
                  hi, kinds, params, grid, ambient, diffuse, specular, shadows, out):
    """Lambert + ambient, Phong highlights (white), soft shadows cast by the object (the
    usual SDF penumbra ``min(k sdf / t)`` along the segment to the light): grey levels."""
    zero = np.zeros(3)
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        lx, ly, lz = light[0] - px, light[1] - py, light[2] - pz
        dist = math.sqrt(lx * lx + ly * ly + lz * lz)
        lx, ly, lz = lx / dist, ly / dist, lz / dist
        lit = nx * lx + ny * ly + nz * lz
        vis = 1.0
        highlight = 0.0
        if lit <= 0.0:
            lit = 0.0
        else:
            lit = min(lit, 1.0)
            if shadows:
                ox, oy, oz = _to_object(rot, pos, px + 1e-4 * nx, py + 1e-4 * ny, pz + 1e-4 * nz)
                dx, dy, dz = _to_object(rot, zero, lx, ly, lz)
                t, t_end = _box_interval(ox, oy, oz, dx, dy, dz, lo, hi)
                t = max(t, 1e-3 if labels[i] == 2 else 1e-4)
                t_end = min(t_end, dist)
                for _ in range(400):
                    if t > t_end:
                        break
                    h = _union_bound(kinds, params, grid, ox + t * dx, oy + t * dy, oz + t * dz)
                    if h < 1e-6:
                        vis = 0.0
                        break
                    vis = min(vis, _PENUMBRA * h / t)
                    t += max(h, 2e-4)
            vx, vy, vz = eye[0] - px, eye[1] - py, eye[2] - pz
            vn = math.sqrt(vx * vx + vy * vy + vz * vz)
            hx, hy, hz = lx + vx / vn, ly + vy / vn, lz + vz / vn
            hn = max(math.sqrt(hx * hx + hy * hy + hz * hz), 1e-12)
            n_dot_h = max((nx * hx + ny * hy + nz * hz) / hn, 0.0)
            highlight = specular * gloss[i] * n_dot_h ** shininess[i]
        shade = ambient + diffuse * lit * vis
        for c in range(3):
            out[i, c] = albedo[i, c] * shade + 255.0 * highlight * vis


def compiled_sdf(obj: SolidObject, points) -> np.ndarray:
    """The object's SDF by the compiled kernel the renderer uses (equal to ``obj.sdf``)."""
    kinds, params, grid = _pack(obj)
    p = np.ascontiguousarray(np.asarray(points, dtype=float).reshape(-1, 3))
    out = np.empty(len(p))
    _sdf_points(p, kinds, params, grid, out)
    return out


# --- the scene and its ray caster --------------------------------------------------------

@dataclass
class _Scene:
    obj: SolidObject
    position: np.ndarray       # object pose
    rotation: np.ndarray
    planes: list               # (label, Plane)
    light: np.ndarray          # tracker frame
    kinds: np.ndarray = field(init=False)
    params: np.ndarray = field(init=False)
    grid: np.ndarray = field(init=False)

    def __post_init__(self):
        self.kinds, self.params, self.grid = _pack(self.obj)
        self.lo = self.obj.bounds[0] - _BOX_MARGIN
        self.hi = self.obj.bounds[1] + _BOX_MARGIN
        self.plane_points = np.array([p.point for _, p in self.planes], dtype=float).reshape(-1, 3)
        self.plane_normals = np.array([p.normal for _, p in self.planes], dtype=float).reshape(-1, 3)
        self.plane_labels = np.array([label for label, _ in self.planes], dtype=np.uint8)


class _Cast(NamedTuple):
    t: np.ndarray          # (N,) distance along the unit ray
    label: np.ndarray      # (N,) uint8 BACKDROP / TABLE / OBJECT
    points: np.ndarray     # (N, 3) tracker frame
    normals: np.ndarray    # (N, 3) tracker frame, towards the viewer
    albedo: np.ndarray     # (N, 3) uint8
    gloss: np.ndarray      # (N,)
    residual: float        # max |sdf| at the object hits


def _cast(scene: _Scene, origin: np.ndarray, dirs: np.ndarray) -> _Cast:
    """What each unit ray from ``origin`` (tracker frame) meets first, and its surface."""
    n = len(dirs)
    t = np.empty(n)
    label = np.empty(n, dtype=np.uint8)
    _trace(np.asarray(origin, dtype=float), dirs, scene.rotation, scene.position, scene.lo,
           scene.hi, scene.kinds, scene.params, scene.grid, scene.plane_points, scene.plane_normals,
           scene.plane_labels, t, label)
    if np.any(label == 255):
        raise ValueError('a ray meets nothing: the backdrop must face the cameras')
    points = origin + t[:, None] * dirs
    normals = np.empty((n, 3))
    albedo = np.empty((n, 3), dtype=np.uint8)
    gloss = np.zeros(n)
    residual = 0.0
    on_object = np.flatnonzero(label == OBJECT)
    if on_object.size:
        p_obj = (points[on_object] - scene.position) @ scene.rotation
        sdf, grad = scene.obj.sdf_grad(p_obj)
        residual = float(np.max(np.abs(sdf)))
        n_obj = grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-300)
        normals[on_object] = n_obj @ scene.rotation.T
        albedo[on_object], gloss[on_object] = surface_appearance(scene.obj.texture, p_obj)
    for plane_label, plane in scene.planes:
        sel = np.flatnonzero(label == plane_label)
        if not sel.size:
            continue
        normals[sel] = plane.normal
        if plane_label == TABLE:
            albedo[sel] = table_colour(points[sel])
            gloss[sel] = 0.05
        else:
            albedo[sel] = backdrop_colour(points[sel])
            gloss[sel] = 0.0
    # Normals towards the viewer (planes seen from behind, the inside of thin parts).
    flip = np.einsum('ij,ij->i', normals, dirs) > 0.0
    normals[flip] *= -1.0
    return _Cast(t, label, points, normals, albedo, gloss, residual)


def _shade(scene: _Scene, cast_: _Cast, eye: np.ndarray, *, ambient: float, diffuse: float,
           specular: float, shadows: bool) -> np.ndarray:
    """Linear RGB in grey levels (N, 3) float (see _shade_kernel)."""
    shininess = np.where(cast_.label == OBJECT, SHININESS[scene.obj.texture], 10.0)
    out = np.empty((len(cast_.t), 3))
    # The penumbra reaches beyond the object: the shadow rays test a box padded by the
    # distance where 12 sdf / t reaches 1 for t up to _SHADOW_REACH * 12.
    pad = _SHADOW_REACH - _BOX_MARGIN
    _shade_kernel(cast_.points, cast_.normals, cast_.label, cast_.albedo, cast_.gloss, shininess,
                  np.asarray(eye, dtype=float), scene.light, scene.rotation, scene.position,
                  scene.lo - pad, scene.hi + pad, scene.kinds, scene.params, scene.grid, float(ambient),
                  float(diffuse),
                  float(specular), bool(shadows), out)
    return out


# --- rendering ---------------------------------------------------------------------------

@dataclass
class RenderedPair:
    """One rendered pair and its exact truth (see the module docstring for conventions)."""

    left: np.ndarray                  # (H, W, 3) uint8 RGB, raw left image
    right: np.ndarray                 # (H, W, 3) uint8 RGB, raw right image
    left_camera: CameraModel
    right_camera: CameraModel
    depth: np.ndarray                 # (H, W) float64, m: z in the rectified left frame
    disparity: np.ndarray             # (H, W) float64, px: fx * baseline / depth
    mask: np.ndarray                  # (H, W) bool: the pixel sees the object
    surface: np.ndarray               # (H, W) uint8: BACKDROP, TABLE or OBJECT
    albedo: np.ndarray                # (H, W, 3) uint8: true unshaded colour of what it sees
    camera_pose: np.ndarray           # (7,) left camera in the tracker frame
    object_pose: tuple                # (position (3,), quaternion xyzw (4,)) in the tracker frame
    object_name: str
    baseline: float
    max_sdf_residual: float           # max |sdf| at the object hits of the truth rays, m
    seconds: float                    # wall time of the render

    @property
    def focal(self) -> float:
        return float(self.left_camera.P[0, 0])

    def points(self, frame: str = 'tracker') -> np.ndarray:
        """(H, W, 3) the true 3D point of every rectified-left pixel, from ``depth``, in the
        ``'camera'`` (rectified left), ``'tracker'`` or ``'object'`` frame."""
        P = self.left_camera.P
        h, w = self.depth.shape
        v, u = np.mgrid[0:h, 0:w].astype(float)
        z = self.depth
        cam = np.stack([(u - P[0, 2]) / P[0, 0] * z, (v - P[1, 2]) / P[1, 1] * z, z], axis=-1)
        if frame == 'camera':
            return cam
        rotation = quaternion_to_matrix(self.camera_pose[3:])
        tracker = cam @ rotation.T + self.camera_pose[:3]
        if frame == 'tracker':
            return tracker
        if frame == 'object':
            position, q = _pose(self.object_pose)
            return (tracker - position) @ quaternion_to_matrix(q)
        raise ValueError(f"frame must be 'camera', 'tracker' or 'object', not {frame!r}")


def _pixel_grid(width: int, height: int, supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample positions (u, v) flattened in (row, sub-row, column, sub-column) order."""
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    us = (np.arange(width)[:, None] + offsets[None, :]).reshape(-1)
    vs = (np.arange(height)[:, None] + offsets[None, :]).reshape(-1)
    v, u = np.meshgrid(vs, us, indexing='ij')
    return u.reshape(-1), v.reshape(-1)


def _geometric_edges(label: np.ndarray, t: np.ndarray, jump: float = 0.02) -> np.ndarray:
    """(H, W) bool: pixels whose 4-neighbour sees another surface, or the same one at a
    distance more than ``jump`` (relative) different (an occlusion, a grazing surface)."""
    edges = np.zeros(label.shape, dtype=bool)
    for axis in (0, 1):
        a = [slice(None), slice(None)]
        b = [slice(None), slice(None)]
        a[axis], b[axis] = slice(1, None), slice(None, -1)
        ta, tb = t[tuple(a)], t[tuple(b)]
        change = (label[tuple(a)] != label[tuple(b)]) | (np.abs(ta - tb) > jump * np.minimum(ta, tb))
        edges[tuple(a)] |= change
        edges[tuple(b)] |= change
    return edges


def _render_camera(rig: StereoRig, scene: _Scene, camera: CameraModel, index: int, shading: dict,
                   supersample: int, edge_samples: int) -> tuple[np.ndarray, _Cast]:
    """Linear (H, W, 3) image of one camera before the camera effects, and the cast of its
    rays (pixel centres when ``supersample`` is 1)."""
    w, h, s = rig.width, rig.height, supersample
    u, v = _pixel_grid(w, h, s)
    origin, dirs = _rays(rig, camera, index, u, v, rectified=False)
    hit = _cast(scene, origin, dirs)
    rgb = _shade(scene, hit, origin, **shading).reshape(h, s, w, s, 3).mean(axis=(1, 3))
    if s == 1 and edge_samples > 1:
        edges = np.flatnonzero(_geometric_edges(hit.label.reshape(h, w), hit.t.reshape(h, w)))
        if edges.size:
            k = edge_samples
            offsets = (np.arange(k) + 0.5) / k - 0.5
            du, dv = (g.reshape(-1) for g in np.meshgrid(offsets, offsets))
            uu = (u[edges, None] + du[None, :]).reshape(-1)
            vv = (v[edges, None] + dv[None, :]).reshape(-1)
            origin, dirs = _rays(rig, camera, index, uu, vv, rectified=False)
            sub = _shade(scene, _cast(scene, origin, dirs), origin, **shading)
            rgb.reshape(-1, 3)[edges] = sub.reshape(edges.size, k * k, 3).mean(axis=1)
    return rgb, hit


def _rays(rig: StereoRig, camera: CameraModel, index: int, u: np.ndarray, v: np.ndarray,
          rectified: bool) -> tuple[np.ndarray, np.ndarray]:
    """Tracker-frame origin and unit directions of the rays through pixel positions (u, v)
    of camera ``index`` (0 left, 1 right): of its rectified image, or of its raw image."""
    if rectified:
        P = camera.P
        x = (u - P[0, 2]) / P[0, 0]
        y = (v - P[1, 2]) / P[1, 1]
        turn = rig.rotation
    else:
        K = camera.K
        xd = (u - K[0, 2]) / K[0, 0]
        yd = (v - K[1, 2]) / K[1, 1]
        x, y = undistort_normalized(xd, yd, camera.D) if np.any(camera.D) else (xd, yd)
        turn = rig.rotation @ camera.R          # raw camera -> rectified -> tracker
    # Column by column: an (N, 3) @ (3, 3) product goes through BLAS, slow for this shape.
    dirs = np.empty((len(x), 3))
    for row in range(3):
        dirs[:, row] = turn[row, 0] * x + turn[row, 1] * y + turn[row, 2]
    dirs /= np.sqrt(np.einsum('ij,ij->i', dirs, dirs))[:, None]
    return (rig.right_position if index else rig.position), dirs


def _camera_effects(image: np.ndarray, rng: np.random.Generator, blur_sigma: float,
                    noise_sigma: float) -> np.ndarray:
    out = image.astype(np.float32)
    if blur_sigma > 0:
        # scipy's filter, not OpenCV's: OpenCV picks SIMD code by CPU, and the bundled bags
        # must come out the same on every machine (make_bags.sh).
        out = gaussian_filter(out, sigma=(blur_sigma, blur_sigma, 0.0), mode='reflect')
    if noise_sigma > 0:
        out = out + rng.normal(0.0, noise_sigma, out.shape).astype(np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def render_pair(rig: StereoRig, obj: SolidObject | str, object_pose, rng: np.random.Generator, *,
                distortion=None, rectification=None, table: bool | Plane = False,
                backdrop: Plane | None = None, backdrop_distance: float = 0.25,
                light: Sequence[float] = DEFAULT_LIGHT, ambient: float = 0.35,
                diffuse: float = 0.7, specular: float = 0.6, shadows: bool = True,
                blur_sigma: float = 0.6, noise_sigma: float = 2.0, supersample: int = 1,
                edge_samples: int = 3) -> RenderedPair:
    """Render the left and right images of ``obj`` (a model or its name) at ``object_pose``
    = (position, quaternion xyzw) of the object frame in the tracker frame.

    ``rng`` draws the pixel noise (left image first), so the same inputs and seed give the
    same bytes. ``distortion`` / ``rectification``: see :meth:`StereoRig.cameras`.
    ``table``: True for the plane the object stands on in a static session
    (:func:`table_plane`), or any :class:`Plane`. ``backdrop``: a :class:`Plane`, by default
    facing the camera ``backdrop_distance`` m behind the object's centre along the optical
    axis. ``light``: a point light's position in the left camera frame (m).
    ``supersample``: rays per pixel along each axis, everywhere (a reference render: the
    time grows with its square). ``edge_samples``: with ``supersample`` 1, rays per pixel
    along each axis at the pixels where the surface seen changes (silhouettes, occlusions:
    the only hard edges, the textures being band-limited); 1 for none."""
    started = time.perf_counter()
    obj = load_object(obj) if isinstance(obj, str) else obj
    position, q = _pose(object_pose)
    rotation = quaternion_to_matrix(q)
    if int(supersample) < 1 or int(edge_samples) < 1:
        raise ValueError('supersample and edge_samples must be >= 1')
    supersample, edge_samples = int(supersample), int(edge_samples)
    cam_rotation, cam_position = rig.rotation, rig.position
    if backdrop is None:
        axis = cam_rotation[:, 2]
        backdrop = Plane(rotation @ obj.centre + position + backdrop_distance * axis, -axis)
    planes: list = [(BACKDROP, Plane(np.asarray(backdrop.point, float), _unit(backdrop.normal)))]
    if table is True:
        planes.append((TABLE, table_plane(obj, (position, q))))
    elif isinstance(table, Plane):
        planes.append((TABLE, Plane(np.asarray(table.point, float), _unit(table.normal))))
    scene = _Scene(obj, position, rotation, planes,
                   cam_rotation @ np.asarray(light, dtype=float) + cam_position)
    left_camera, right_camera = rig.cameras(distortion, rectification)
    shading = {'ambient': ambient, 'diffuse': diffuse, 'specular': specular, 'shadows': shadows}

    w, h, s = rig.width, rig.height, supersample
    images = []
    left_cast = None
    for index, camera in enumerate((left_camera, right_camera)):
        rgb, hit = _render_camera(rig, scene, camera, index, shading, s, edge_samples)
        if index == 0:
            left_cast = hit
        images.append(rgb)
    left = _camera_effects(images[0], rng, blur_sigma, noise_sigma)
    right = _camera_effects(images[1], rng, blur_sigma, noise_sigma)

    # Truth at the rectified left image's pixel centres.
    raw_is_rectified = left_camera.is_rectified_input and s == 1
    if raw_is_rectified:
        truth, truth_dirs = left_cast, None
    else:
        uc, vc = _pixel_grid(w, h, 1)
        origin, truth_dirs = _rays(rig, left_camera, 0, uc, vc, rectified=True)
        truth = _cast(scene, origin, truth_dirs)
    depth = ((truth.points - cam_position) @ cam_rotation[:, 2]).reshape(h, w)
    disparity = left_camera.P[0, 0] * rig.baseline / depth
    surface = truth.label.reshape(h, w)
    return RenderedPair(
        left=left, right=right, left_camera=left_camera, right_camera=right_camera,
        depth=depth, disparity=disparity, mask=surface == OBJECT, surface=surface,
        albedo=truth.albedo.reshape(h, w, 3), camera_pose=np.array(rig.camera_pose),
        object_pose=(position, q), object_name=obj.name, baseline=rig.baseline,
        max_sdf_residual=truth.residual, seconds=time.perf_counter() - started)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float).reshape(3)
    return v / np.linalg.norm(v)
