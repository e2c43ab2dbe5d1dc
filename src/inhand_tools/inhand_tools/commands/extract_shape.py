"""extract_shape: the surface mesh, superquadric parts, graspable part and grasps of a map.

Reads a map (NPZ from occupancy/save or build_map, or its PLY) and writes beside it, in
``--output-dir`` (default: the map's folder):

* ``NAME_surface.ply``, ``.obj``, ``.stl``: the surface through the occupied cells as a
  triangle mesh, open where the map has no evidence (its holes are counted, never closed);
* ``NAME_parts.yaml``: ``parts`` (each: size [a1, a2, a3] m, exponents [e1, e2], position
  and orientation [x, y, z, w] in the map's frame, the cells it explains, its residual and
  graspable score), ``graspable_part``, ``grasps`` (two contacts, width, approach, margin
  inside the friction cones) and the surface's triangles, holes and area;
* ``NAME_shape.png``: the map, the mesh and the parts with the graspable part and the
  grasps drawn (like the paper's Fig. 1).

Parameters come from the ``shape_node`` section of ``--config`` files (friction, max_parts,
occupied_threshold), then ``--set NAME=VALUE``. A map made in static mode (build_map and
occupancy_node record the graph's mode) stands on a support: its parts may be held upright
on it (docs/shape.md, "Upright on a support"). A map with no occupied cells, only
scattered strays or cells in one plane gets one line saying why, and no part is invented
(exit code 0: the files still say so). Exit code 2 for a file that is not a map or a bad
parameter.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2

from inhand_common.parameters import ParameterError
from inhand_shape.shape_extraction import (
    SHAPE_PARAMETERS,
    extract_shape,
    support_normal,
    write_shape_files,
)
from inhand_tools.map_cells import load_map
from inhand_tools.map_command import map_command_parser, output_of, print_report, section_parameters
from inhand_tools.shape_figure import shape_figure

__all__ = ['main', 'shape_parameters', 'write_shape_of_map']

PROG = 'extract_shape'
EXIT_BAD_INPUT = 2


def shape_parameters(configs: list[str], overrides: list[str]) -> dict:
    """The shape_node section of ``configs`` (later files win), then ``--set`` pairs,
    checked; ParameterError names what is refused."""
    return section_parameters(configs, overrides, 'shape_node', SHAPE_PARAMETERS)


def write_shape_of_map(map_path: Path, output: Path, name: str, parameters: dict,
                       quiet: bool = False, up: str | None = None) -> int:
    """Extract the shape of the map at ``map_path``, write its files in ``output`` as
    ``name``, print the summary; the exit code (2: not a map). Also build_map --shape."""
    try:
        cells = load_map(map_path)
    except ValueError as error:
        print(f'{PROG}: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    result = extract_shape(cells.centres, cells.probabilities, cells.hits, cells.first_touch,
                           resolution=cells.lattice.resolution, origin=cells.lattice.origin,
                           threshold=parameters['occupied_threshold'],
                           friction=parameters['friction'], max_parts=parameters['max_parts'],
                           frame_id=cells.frame_id, surface_points=cells.contact_centroids,
                           up=support_normal(cells.registration_mode), layer=cells.layer)
    figure = shape_figure(cells, result, f'{name}: shape of the map',
                          parameters['occupied_threshold'], up=up)
    ok, png = cv2.imencode('.png', figure)
    written = write_shape_files(result, output, name, png.tobytes() if ok else None)
    details = []
    for k, part in enumerate(result.decomposition.parts):
        sq = part.superquadric
        size = ' x '.join(f'{2 * v * 100:.1f}' for v in sq.size)
        mark = '  <- graspable' if k == result.graspable else ''
        details.append(f'part {k}: {size} cm, exponents {sq.shape[0]:.2f} {sq.shape[1]:.2f}, '
                       f'{len(part.cells)} cells, residual {part.residual * 1000:.1f} mm{mark}')
    print_report(PROG, result.summary(), details, result.seconds, written, quiet)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = map_command_parser(PROG, __doc__, 'shape_node').parse_args(argv)
    try:
        parameters = shape_parameters(args.config, args.set)
    except ParameterError as error:
        print(f'{PROG}: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    output, name = output_of(args)
    return write_shape_of_map(args.map, output, name, parameters, args.quiet, args.up)


if __name__ == '__main__':
    sys.exit(main())
