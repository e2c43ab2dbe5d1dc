"""Which object a name means: a built-in union of primitives, a shipped mesh, or a mesh file.

Why one place: the command line, the sessions and the stereo rig all take an object by
name, and the ground truth records that name (``object_name``), so the same text must
always give the same object. Names are tried in this order:

* the built-in objects of :mod:`inhand_sim.objects` (``cat``, ``bottle``, ``mug``);
* the meshes this package ships (``src/inhand_sim/meshes/``, installed to
  ``share/inhand_sim/meshes``; made by ``launch_scripts/make_meshes.py``): ``cup``,
  ``animal``, ``duck``, each with its grips and texture;
* otherwise a path to a mesh file (OBJ, STL, PLY), with the defaults of
  :mod:`inhand_sim.mesh_objects` (grips at the top, the bottom and both ends; a plain
  plaster texture).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from inhand_sim.mesh_objects import (
    MESH_SUFFIXES,
    GripSpec,
    MeshError,
    load_mesh_object,
)
from inhand_sim.objects import OBJECT_NAMES, SolidObject, get_object

__all__ = ['MESH_NAMES', 'ShippedMesh', 'load_object', 'mesh_folder', 'object_choices']


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


def mesh_folder() -> Path:
    """Where the shipped meshes are: beside the package's source (a checkout, an editable
    install), else in the install prefix's ``share/inhand_sim/meshes`` (colcon installs the
    module in ``<prefix>/lib/pythonX.Y/site-packages/inhand_sim/``)."""
    here = Path(__file__).resolve()
    source = here.parents[1] / 'meshes'
    installed = here.parents[4] / 'share' / 'inhand_sim' / 'meshes'
    return installed if not source.is_dir() and installed.is_dir() else source


def object_choices() -> tuple[str, ...]:
    """The names that need no path: the built-in objects and the shipped meshes."""
    return OBJECT_NAMES + MESH_NAMES


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
    path = Path(name)
    if path.suffix.lower() in MESH_SUFFIXES or path.exists():
        if not path.is_file():
            raise MeshError(f'{name}: no such mesh file')
        return load_mesh_object(path, scale=scale, up=up)
    raise ValueError(f'unknown object {name!r}: choose one of {", ".join(object_choices())}, '
                     f'or give a mesh file ({", ".join(MESH_SUFFIXES)})')
