"""Which object a name means: a built-in union of primitives, a shipped mesh, or a mesh file.

Why one place: the command line, the sessions and the stereo rig all take an object by
name, and the ground truth records that name (``object_name``), so the same text must
always give the same object. Names are tried in this order:

* the built-in objects of :mod:`inhand_sim.objects` (``cat``, ``bottle``, ``mug``);
* the meshes this package ships (``src/inhand_sim/meshes/``, installed to
  ``share/inhand_sim/meshes``; made by ``launch_scripts/make_meshes.py``): ``cup``,
  ``animal``, ``duck``, each with its grips and texture;
* shapes trimesh makes when asked (:data:`SHAPES`): ``plate`` (2 cm thin), ``rod`` (20 cm
  long and thin), ``box`` (sharp edges), ``large`` (20 cm);
* otherwise a path to a mesh file (OBJ, STL, PLY), with the defaults of
  :mod:`inhand_sim.mesh_objects` (grips at the top, the bottom and both ends; a plain
  plaster texture).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from inhand_sim.mesh_objects import (
    MESH_SUFFIXES,
    GripSpec,
    MeshError,
    load_mesh_object,
    mesh_object,
)
from inhand_sim.objects import OBJECT_NAMES, SolidObject, get_object

__all__ = ['MESH_NAMES', 'SHAPE_NAMES', 'Shape', 'ShippedMesh', 'load_object', 'mesh_folder',
           'object_choices']


@dataclass(frozen=True)
class ShippedMesh:
    """A mesh this package ships: its file in :func:`mesh_folder`, and how it is held."""
    file: str
    description: str
    static_grip: GripSpec
    moving_grips: tuple[GripSpec, ...]


SHIPPED = {
    'cup': ShippedMesh(
        'cup.ply', 'cup: tapered wall 5 mm thick, 7 mm bottom, rounded rim, handle (concave, '
        'two-sided: explored inside and out)',
        GripSpec('rim, far side', (0.02, 0.5, 1.0), 0.06),
        (GripSpec('handle', (0.94, 0.5, 0.51), 0.07),
         GripSpec('bottom and far side', (0.09, 0.5, 0.1), 0.12))),
    'animal': ShippedMesh(
        'animal.ply', 'dog-like carved figure (scanned look): body, head, muzzle, ears, four '
        'legs, tail',
        GripSpec('back', (0.47, 0.5, 0.75), 0.08),
        (GripSpec('back', (0.47, 0.5, 0.75), 0.08),
         GripSpec('belly and legs', (0.45, 0.5, 0.2), 0.12),
         GripSpec('rear and tail', (0.1, 0.5, 0.6), 0.08))),
    'duck': ShippedMesh(
        'duck.ply', 'duck-like hand-made figure (scanned look): body on a flat base, raised '
        'tail, neck, head, flat beak',
        GripSpec('back', (0.44, 0.5, 0.7), 0.08),
        (GripSpec('base', (0.45, 0.5, 0.0), 0.12),
         GripSpec('tail', (0.05, 0.5, 0.45), 0.07),
         GripSpec('head', (0.72, 0.5, 0.95), 0.07))),
}
MESH_NAMES = tuple(SHIPPED)


@dataclass(frozen=True)
class Shape:
    """A shape made by trimesh.creation when asked for (nothing shipped): the shapes a touch
    map finds hard (thin, long, sharp-edged, large), with how it is held."""
    description: str
    make: Callable[[], Any]
    static_grip: GripSpec
    moving_grips: tuple[GripSpec, ...]


def _box(x: float, y: float, z: float):
    import trimesh
    return trimesh.creation.box(extents=(x, y, z))


def _lying_rod(length: float, radius: float):
    import trimesh
    rod = trimesh.creation.cylinder(radius=radius, height=length, sections=48)
    rod.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, (0.0, 1.0, 0.0)))
    return rod


def _ellipsoid(x: float, y: float, z: float):
    import trimesh
    body = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    body.apply_scale((x / 2, y / 2, z / 2))
    return body


SHAPES = {
    'plate': Shape('thin plate, 14 x 9 cm and 2 cm thick, sharp edges: both faces and the rim',
                   lambda: _box(0.14, 0.09, 0.02),
                   GripSpec('one corner', (0.0, 0.0, 1.0), 0.05),
                   (GripSpec('one end', (0.0, 0.5, 0.5), 0.08),
                    GripSpec('other end', (1.0, 0.5, 0.5), 0.08))),
    'rod': Shape('long thin rod lying on the table: 20 cm long, 2.5 cm across',
                 lambda: _lying_rod(0.20, 0.0125),
                 GripSpec('one end', (0.0, 0.5, 0.5), 0.10),
                 (GripSpec('one end', (0.0, 0.5, 0.5), 0.12),
                  GripSpec('other end', (1.0, 0.5, 0.5), 0.12))),
    'box': Shape('box, 8 x 6 x 5 cm, sharp edges and corners',
                 lambda: _box(0.08, 0.06, 0.05),
                 GripSpec('top', (0.5, 0.5, 1.0), 0.08),
                 (GripSpec('bottom', (0.5, 0.5, 0.0), 0.12),
                  GripSpec('one end', (0.0, 0.5, 0.5), 0.10))),
    'large': Shape('large smooth body, 20 x 14 x 12 cm (an ellipsoid): minutes to explore',
                   lambda: _ellipsoid(0.20, 0.14, 0.12),
                   GripSpec('top', (0.5, 0.5, 1.0), 0.06),
                   (GripSpec('bottom', (0.5, 0.5, 0.0), 0.10),
                    GripSpec('one end', (0.0, 0.5, 0.5), 0.08))),
}
SHAPE_NAMES = tuple(SHAPES)


def mesh_folder() -> Path:
    """Where the shipped meshes are: beside the package's source (a checkout, an editable
    install), else in the install prefix's ``share/inhand_sim/meshes`` (colcon installs the
    module in ``<prefix>/lib/pythonX.Y/site-packages/inhand_sim/``)."""
    here = Path(__file__).resolve()
    source = here.parents[1] / 'meshes'
    installed = here.parents[4] / 'share' / 'inhand_sim' / 'meshes'
    return installed if not source.is_dir() and installed.is_dir() else source


def object_choices() -> tuple[str, ...]:
    """The names that need no path: the built-in objects, the shipped meshes and the
    shapes."""
    return OBJECT_NAMES + MESH_NAMES + SHAPE_NAMES


def load_object(name: str, scale: float = 1.0, up: str = 'z') -> SolidObject:
    """The object ``name`` means (see the module docstring). ``scale`` and ``up`` apply to
    meshes (shipped ones are in metres, z up). ValueError (MeshError for a mesh that cannot
    be an object) naming the problem."""
    if name in OBJECT_NAMES:
        if scale != 1.0 or up != 'z':
            raise ValueError(f'{name} is a built-in object: a mesh scale or up axis applies to '
                             'meshes only')
        return get_object(name)
    if name in SHIPPED:
        spec = SHIPPED[name]
        return load_mesh_object(mesh_folder() / spec.file, name=name, scale=scale, up=up,
                                texture=name, description=spec.description,
                                static_grip=spec.static_grip, moving_grips=spec.moving_grips)
    if name in SHAPES:
        shape = SHAPES[name]
        return mesh_object(shape.make(), name, name, scale=scale, up=up, texture='scan',
                           description=shape.description, static_grip=shape.static_grip,
                           moving_grips=shape.moving_grips)
    path = Path(name)
    if path.suffix.lower() in MESH_SUFFIXES or path.exists():
        if not path.is_file():
            raise MeshError(f'{name}: no such mesh file')
        return load_mesh_object(path, scale=scale, up=up)
    raise ValueError(f'unknown object {name!r}: choose one of {", ".join(object_choices())}, '
                     f'or give a mesh file ({", ".join(MESH_SUFFIXES)})')
