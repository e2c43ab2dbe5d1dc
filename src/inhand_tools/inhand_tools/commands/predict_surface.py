"""predict_surface: the completed surface of a map with its uncertainty, and where to touch next.

Reads a map (NPZ from occupancy/save or build_map, or its PLY) and writes, in ``--output-dir``
(default: the map's folder):

* ``NAME_predicted.ply``: the predicted surface (a Gaussian process implicit surface through
  the occupied cells, falling back to their superquadric where nothing was touched) as a
  triangle mesh with a per-vertex ``std`` property (m): how far the true surface may be;
* ``NAME_completed.ply``: the completed surface, the part of it within ``completed_reach``
  (7.5 mm) of the touched cells: the touched surface with the gaps between strokes bridged,
  the same property; farther out the prediction is a guess to be touched, not a surface;
* ``NAME_next_touch.yaml``: ``suggestions``, best first, each with ``position`` [x, y, z] on
  the predicted surface and ``approach`` [x, y, z] (unit, into the surface) in the map's frame,
  its expected ``gain`` (the share of the surface's summed variance one touch there removes)
  and ``std``; nothing is suggested below a static object's support;
* ``NAME_uncertainty.png``: the map, the surface coloured by its standard deviation, and the
  next touches as arrows.

``--bag BAG`` (the session the map was built from) adds what the camera saw: the object's
points of every usable stereo pair of the bag (placed and segmented as ``build_map`` and the
stereo node place them, from the ``stereo_node`` and ``registration_node`` sections of the
same ``--config`` files: ``--config config/mapping.yaml --config config/stereo.yaml``) make
the cells holding them surface too, so the completed surface follows the seen side where no
finger went. A bag without images adds nothing, with one line saying so. The contact times
are the map's own (its first-touch times).

Parameters come from the ``exploration_node`` section of ``--config`` files, then ``--set
NAME=VALUE`` (docs/exploration.md lists them). ``--mode static`` (or a map made in static mode,
which build_map and occupancy_node record) keeps the suggestions off the support the object
stands on. Exit code 2 for a
file that is not a map or a bad parameter; a map with too few occupied cells gets one line
saying so, and no surface file.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from inhand_common.parameters import ParameterError
from inhand_shape.touch_guidance import GUIDANCE_PARAMETERS, guide, write_guidance_files
from inhand_tools.bag_stereo_shot import read_configured_shot
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
    parser.add_argument('--bag', type=Path,
                        help='the session bag: the object points of its stereo pairs are surface '
                        'too (with --config config/stereo.yaml for the camera)')
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
    mode = args.mode or cells.registration_mode
    seen = None
    if args.bag is not None:
        try:
            seen, note = camera_points(args.bag, args.config, mode)
        except (ValueError, OSError) as error:   # ParameterError and BagError are ValueErrors
            print(f'{PROG}: {error}', file=sys.stderr)
            return EXIT_BAD_INPUT
        if not args.quiet:
            print(f'{PROG}: {note}')
    guidance = guide(cells.centres, cells.probabilities, cells.lattice.resolution, parameters,
                     up=UP_AXES[up_axis][2], on_support=mode == 'static', frame_id=cells.frame_id,
                     seen=None if seen is None else seen[0], seen_from=None if seen is None else seen[1])
    figure = guidance_figure(cells, guidance, f'{name}: where to touch next',
                             parameters['occupied_threshold'], up=up_axis)
    ok, png = cv2.imencode('.png', figure)
    written = write_guidance_files(guidance, output, name, png.tobytes() if ok else None)
    details = [f'{rank}. at ({", ".join(f"{v * 100:.1f}" for v in touch.position)}) cm, approach '
               f'({", ".join(f"{v:+.2f}" for v in touch.approach)}), gain {100 * touch.gain:.1f} %, '
               f'std {touch.std * 1000:.1f} mm' for rank, touch in enumerate(guidance.suggestions, 1)]
    print_report(PROG, guidance.summary(), details, guidance.seconds, written, args.quiet)
    return 0


def camera_points(bag: Path, configs: list[str], mode: str | None
                  ) -> tuple[tuple[np.ndarray, np.ndarray] | None, str]:
    """The object's points (K, 3, map frame) of the bag's stereo pairs and where the camera
    was for each, placed as build_map places them (``mode``: the map's registration mode,
    else the files'), and one line saying what was read; None when there are none."""
    shot, why = read_configured_shot(bag, configs, None if mode is None else {'mode': mode})
    if shot is None:
        return None, f'{bag}: {why or "no stereo pair in the bag"}; the touch map alone'
    points, cameras = shot.object_points()
    return (points, cameras), (f'{bag}: {len(shot.pairs.placed)} stereo pair(s), '
                               f'{len(points):,} points of the object: the cells holding them '
                               'are surface, those in front of them free')


if __name__ == '__main__':
    sys.exit(main())
