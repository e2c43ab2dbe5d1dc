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
occupied_threshold), then ``--set NAME=VALUE``. A map with no occupied cells, only
scattered strays or cells in one plane gets one line saying why, and no part is invented
(exit code 0: the files still say so). Exit code 2 for a file that is not a map or a bad
parameter.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2

from inhand_common.cli_types import command_parser
from inhand_common.parameters import ParameterError, load_yaml_parameters, validate
from inhand_mapping.mapping_config import parse_overrides
from inhand_shape.shape_extraction import SHAPE_PARAMETERS, extract_shape, write_shape_files
from inhand_tools.drawing import UP_AXES
from inhand_tools.map_cells import load_map
from inhand_tools.shape_figure import shape_figure

__all__ = ['main', 'shape_parameters', 'write_shape_of_map']

PROG = 'extract_shape'
EXIT_BAD_INPUT = 2


def _parser() -> argparse.ArgumentParser:
    parser = command_parser(PROG, __doc__)
    parser.add_argument('map', type=Path, help='map: NPZ (or PLY) saved by occupancy/save or build_map')
    parser.add_argument('--config', action='append', default=[],
                        help='ROS parameter file with a shape_node section; repeatable, later '
                        'files override earlier ones')
    parser.add_argument('--set', action='append', default=[], metavar='NAME=VALUE',
                        help='override a parameter (repeatable)')
    parser.add_argument('--output-dir', type=Path, help="default: the map's folder")
    parser.add_argument('--name', help="file name stem (default: the map's)")
    parser.add_argument('--up', choices=sorted(UP_AXES),
                        help="the map frame's axis that points up in the picture (default: -z "
                        'for a map build_map registered in static mode, the tracker frame; else +z '
                        'in the object frame)')
    parser.add_argument('--quiet', action='store_true', help='only the summary line')
    return parser


def shape_parameters(configs: list[str], overrides: list[str]) -> dict:
    """The shape_node section of ``configs`` (later files win), then ``--set`` pairs,
    checked; ParameterError names what is refused."""
    values: dict = {}
    for path in configs:
        values.update(load_yaml_parameters(path, 'shape_node'))
    values.update(parse_overrides(overrides))
    return validate(SHAPE_PARAMETERS, values)


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
                           frame_id=cells.frame_id)
    figure = shape_figure(cells, result, f'{name}: shape of the map',
                          parameters['occupied_threshold'], up=up)
    ok, png = cv2.imencode('.png', figure)
    written = write_shape_files(result, output, name, png.tobytes() if ok else None)
    print(f'{PROG}: {result.summary()}')
    if not quiet:
        for k, part in enumerate(result.decomposition.parts):
            sq = part.superquadric
            size = ' x '.join(f'{2 * v * 100:.1f}' for v in sq.size)
            mark = '  <- graspable' if k == result.graspable else ''
            print(f'  part {k}: {size} cm, exponents {sq.shape[0]:.2f} {sq.shape[1]:.2f}, '
                  f'{len(part.cells)} cells, residual {part.residual * 1000:.1f} mm{mark}')
        seconds = ', '.join(f'{k} {v:.2f} s' for k, v in result.seconds.items())
        print(f'  took {seconds}')
    print('  wrote ' + ', '.join(str(p) for p in written))
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        parameters = shape_parameters(args.config, args.set)
    except ParameterError as error:
        print(f'{PROG}: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    name = args.name or args.map.stem
    output = args.output_dir if args.output_dir is not None else args.map.parent
    return write_shape_of_map(args.map, output, name, parameters, args.quiet, args.up)


if __name__ == '__main__':
    sys.exit(main())
