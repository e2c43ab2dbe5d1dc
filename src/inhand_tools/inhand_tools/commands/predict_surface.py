"""predict_surface: the completed surface of a map with its uncertainty, and where to touch next.

Reads a map (NPZ from occupancy/save or build_map, or its PLY) and writes, in ``--output-dir``
(default: the map's folder):

* ``NAME_predicted.ply``: the predicted surface (a Gaussian process implicit surface through
  the occupied cells, falling back to their superquadric where nothing was touched) as a
  triangle mesh with a per-vertex ``std`` property (m): how far the true surface may be;
* ``NAME_next_touch.yaml``: ``suggestions``, best first, each with ``position`` [x, y, z] on
  the predicted surface and ``approach`` [x, y, z] (unit, into the surface) in the map's frame,
  its expected ``gain`` (the share of the surface's summed variance one touch there removes)
  and ``std``; nothing is suggested below a static object's support;
* ``NAME_uncertainty.png``: the map, the surface coloured by its standard deviation, and the
  next touches as arrows.

Parameters come from the ``exploration_node`` section of ``--config`` files, then ``--set
NAME=VALUE`` (docs/exploration.md lists them). ``--mode static`` (or a map made in static mode,
which build_map and occupancy_node record) keeps the suggestions off the support the object
stands on. Exit code 2 for a
file that is not a map or a bad parameter; a map with too few occupied cells gets one line
saying so, and no surface file.
"""

from __future__ import annotations

import sys

import cv2

from inhand_common.parameters import ParameterError
from inhand_shape.touch_guidance import GUIDANCE_PARAMETERS, guide, write_guidance_files
from inhand_tools.drawing import UP_AXES
from inhand_tools.guidance_figure import guidance_figure
from inhand_tools.map_cells import load_map
from inhand_tools.map_command import map_command_parser, output_of, print_report, section_parameters
from inhand_tools.shape_figure import map_up

__all__ = ['guidance_parameters', 'main']

PROG = 'predict_surface'
EXIT_BAD_INPUT = 2
NODE_SECTION = 'exploration_node'


def guidance_parameters(configs: list[str], overrides: list[str]) -> dict:
    """The exploration_node section of ``configs`` (later files win), then ``--set`` pairs,
    checked; ParameterError names what is refused."""
    return section_parameters(configs, overrides, NODE_SECTION, GUIDANCE_PARAMETERS)


def main(argv: list[str] | None = None) -> int:
    parser = map_command_parser(PROG, __doc__, NODE_SECTION)
    parser.add_argument('--mode', choices=('static', 'tracked'),
                        help='the registration mode the map was made in: static, the object stands '
                        'on a support below its lowest cell where nothing is suggested (default: '
                        'what the map records: build_map and occupancy_node record the graph\'s '
                        'mode; a map without it has nothing excluded)')
    args = parser.parse_args(argv)
    try:
        parameters = guidance_parameters(args.config, args.set)
    except ParameterError as error:
        print(f'{PROG}: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        cells = load_map(args.map)
    except ValueError as error:
        print(f'{PROG}: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    output, name = output_of(args)
    up_axis = args.up or map_up(cells)
    # build_map records the registration mode: a static object stands on a support
    mode = args.mode or ((cells.metadata or {}).get('extra') or {}).get('registration_mode')
    guidance = guide(cells.centres, cells.probabilities, cells.lattice.resolution, parameters,
                     up=UP_AXES[up_axis][2], on_support=mode == 'static', frame_id=cells.frame_id)
    figure = guidance_figure(cells, guidance, f'{name}: where to touch next',
                             parameters['occupied_threshold'], up=up_axis)
    ok, png = cv2.imencode('.png', figure)
    written = write_guidance_files(guidance, output, name, png.tobytes() if ok else None)
    details = [f'{rank}. at ({", ".join(f"{v * 100:.1f}" for v in touch.position)}) cm, approach '
               f'({", ".join(f"{v:+.2f}" for v in touch.approach)}), gain {100 * touch.gain:.1f} %, '
               f'std {touch.std * 1000:.1f} mm' for rank, touch in enumerate(guidance.suggestions, 1)]
    print_report(PROG, guidance.summary(), details, guidance.seconds, written, args.quiet)
    return 0


if __name__ == '__main__':
    sys.exit(main())
