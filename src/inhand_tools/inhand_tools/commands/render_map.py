"""``render_map``: PNG pictures of a map like the paper's figures 4-8.

    render_map MAP [--bag BAG [--config config/mapping.yaml [--config config/stereo.yaml]]]
               [--truth TRUTH.npz] --output DIR
               [--thresholds 0 0.6 0.8] [--frame object|tracker] [--up z]
               [--size 480] [--top-fraction 0.1] [--first-fraction 0.1]

MAP is an NPZ (every touched cell), a PLY, or a bag with a recorded occupancy cloud (see
``map_metrics``). Written to DIR, each picture an oblique and a side view (orthographic,
scale bar in cm, the data frame's axes drawn in the corner):

  raw_points.png         fingertip positions as recorded, tracker frame (needs --bag)
  registered_points.png  the same registered into the map frame (needs --bag)
  map_above_<t>.png      the map's cells with probability > t, one per threshold, shaded
                         by probability (darker = more probable)
  map_thresholds.png     the thresholds side by side (oblique view), like the paper's fig. 5
  regions.png            most explored cells (top hit counts) and the first touched cells
  truth.png              the true surface, its explored part and the stray points (needs
                         the truth: --truth or the bag's BAG.truth.npz sidecar)
  stereo_points.png      the stereo points of the bag's first usable stereo pair in the
                         colours of the image, map frame, and the rectified left image (the
                         extracted texture; paper's fig. 6). Needs a bag with a stereo pair
                         and the rig's camera_pose (--config config/stereo.yaml)
  textured_map.png       the occupied map (cells above the highest threshold), textured
                         cells in their camera colours, the others grey; "N of M cells
                         textured" (paper's fig. 6). Needs a map with colours (build_map or
                         the occupancy node with the stereo pair)
  texture_registration.png  the stereo points over the occupied cells: they register
                         (paper's fig. 7). Needs what stereo_points.png needs
  local_maps.png         a map saved with fusion: the touch and vision local maps, the global
                         map fused from them and its per-cell entropy (paper's fig. 1)
  figure.png             every picture's oblique view in one figure (not the registration)

Each view is SIZE pixels square (two views side by side: 2 x SIZE wide). Every panel is
framed on the object, not on everything the fingertips went through (they travel far off
the object between strokes and during re-grasps): all map-frame panels show one view box,
the truth's surface with a margin (else the map's confident cells, robustly), and the raw
points their own (where most of them are); what falls outside a panel is not drawn and its
subtitle says how much ("+ 812 points outside the view"). The "up" axis of the map's
pictures is +z in the object frame (the simulator's objects stand on their +z) and -z in
the tracker frame (its z points down; also the raw points' up); --up overrides it.

--config (repeatable, later files overriding earlier ones) gives the ROS parameter files the
bag is registered and its stereo pair processed with, as build_map takes them. Stereo
pictures that the inputs do not allow are skipped with a one-line note on stderr saying
why; everything else is drawn. The paths written are printed. Exit status: 0 done, 2 bad
input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from inhand_common.cli_types import command_parser
from inhand_common.ground_truth import FRAMES, default_frame, in_frame, load_truth
from inhand_tools.bag_points import bag_mode_for_frame, map_frame_of_bag, read_bag_points
from inhand_tools.drawing import UP_AXES
from inhand_tools.map_cells import MapCells, load_local_cells, load_map
from inhand_tools.map_figures import StereoCloud, draw_all
from inhand_tools.map_quality import find_truth

__all__ = ['EXIT_BAD_INPUT', 'main']

PROG = 'render_map'
EXIT_BAD_INPUT = 2


def _parser() -> argparse.ArgumentParser:
    parser = command_parser(PROG, __doc__)
    parser.add_argument('map', type=Path, help='map: NPZ, PLY, or a bag with an occupancy cloud')
    parser.add_argument('--output', type=Path, required=True, help='folder for the PNGs')
    parser.add_argument('--bag', type=Path, help='session bag: raw and registered points')
    parser.add_argument('--truth', help='simulator truth file (default: the bag\'s sidecar '
                        'BAG.truth.npz, if there is one)')
    parser.add_argument('--thresholds', type=float, nargs='+', default=[0.0, 0.6, 0.8],
                        help='probability thresholds of the map pictures (default 0 0.6 0.8)')
    parser.add_argument('--frame', choices=FRAMES, help='frame the map is in (default: from '
                        'the truth; else object if the bag has an object sensor)')
    parser.add_argument('--up', choices=sorted(UP_AXES),
                        help='axis of the map frame that points up in the pictures (default: '
                        'z in the object frame, -z in the tracker frame or an unknown one)')
    parser.add_argument('--size', type=int, default=480, help='pixels per view (default 480)')
    parser.add_argument('--top-fraction', type=float, default=0.1,
                        help='most explored = this fraction of cells with the most hits')
    parser.add_argument('--first-fraction', type=float, default=0.1,
                        help='first touched = this fraction of cells touched earliest')
    parser.add_argument('--resolution', type=float, metavar='M',
                        help='cell size (m) of a PLY or cloud map (default: inferred)')
    parser.add_argument('--config', action='append', default=[],
                        help='ROS parameter file for the registration of --bag and its stereo '
                        'pair (e.g. config/mapping.yaml, then config/stereo.yaml for the '
                        "rig's camera_pose); repeatable, later files override earlier ones")
    return parser


def _check_options(args: argparse.Namespace) -> None:
    if not 120 <= args.size <= 4000:
        raise ValueError(f'--size {args.size}: must be between 120 and 4000 pixels')
    for threshold in args.thresholds:
        if not 0.0 <= threshold < 1.0:
            raise ValueError(f'--thresholds {threshold:g}: must be in [0, 1)')
    for option in ('top_fraction', 'first_fraction'):
        if not 0.0 < getattr(args, option) <= 1.0:
            raise ValueError(f'--{option.replace("_", "-")} must be in (0, 1]')


def _optional_truth(args: argparse.Namespace):
    """The truth if there is one (given, or the sidecar of the bag or the map bag)."""
    try:
        truth_path = find_truth(args.truth, args.bag, args.map)
    except ValueError:
        return None  # the truth is optional here
    return load_truth(truth_path)


def _stereo_cloud(bag: Path, configs: list[str], mode: str
                  ) -> tuple[StereoCloud | None, str | None]:
    """(the bag's first usable stereo shot in the map frame, None) or (None, why not)."""
    from inhand_mapping.mapping_config import load_parameters
    from inhand_tools.bag_stereo_shot import read_bag_shot, stereo_config_for_map
    registration, occupancy = load_parameters(configs, {'mode': mode})
    stereo = stereo_config_for_map(configs, registration, occupancy)
    try:
        shot, why = read_bag_shot(bag, stereo)
    except ValueError as error:  # stereo topics of another type, a damaged bag
        return None, str(error)
    if shot is None:
        return None, why or 'the bag holds no stereo pair'
    cloud = StereoCloud.of_shot(shot)
    if len(cloud.points) == 0:
        return None, 'the stereo pair gave no 3D points'
    return cloud, None


def _notes(cells: MapCells, bag: Path | None, why_no_stereo: str | None) -> list[str]:
    """One line per stereo picture that is skipped, saying why."""
    notes = []
    if bag is not None and why_no_stereo is not None:
        notes.append(f'no stereo_points.png or texture_registration.png: {why_no_stereo}')
    if not cells.has_colours:
        notes.append('no textured_map.png: the map carries no camera colours (build it from '
                     'a bag with a stereo pair with --config config/stereo.yaml)')
    return notes


def _render(args: argparse.Namespace):
    """Load the inputs and draw the pictures: (the map's cells, the paths written, notes
    on the pictures skipped)."""
    cells = load_map(args.map, args.resolution)
    truth = _optional_truth(args)
    frame = args.frame or (default_frame(truth) if truth is not None else None)
    bag_points = stereo = why_no_stereo = None
    if args.bag is not None:
        frame = frame or map_frame_of_bag(args.bag)
        mode = bag_mode_for_frame(frame)
        bag_points = read_bag_points(args.bag, mode, args.config or None)
        stereo, why_no_stereo = _stereo_cloud(args.bag, args.config, mode)
    if truth is not None:
        truth = in_frame(truth, frame or 'object')
    written = draw_all(cells, args.output, sorted(args.thresholds), bag_points, truth, frame,
                       up=args.up, size=args.size, top_fraction=args.top_fraction,
                       first_fraction=args.first_fraction,
                       name=args.map.name.rsplit('.', 1)[0] or 'map', stereo=stereo,
                       local=load_local_cells(args.map))
    return cells, written, _notes(cells, args.bag, why_no_stereo)


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    try:
        _check_options(args)
        cells, written, notes = _render(args)
    except (ValueError, OSError) as error:  # ParameterError and BagError are ValueErrors
        print(f'{PROG}: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    if cells.problem:
        print(f'{PROG}: note: {args.map} is damaged: {cells.problem}',
              file=sys.stderr)
    for note in notes:
        print(f'{PROG}: note: {note}', file=sys.stderr)
    print(f'{PROG}: {cells.describe()}')
    for path in written:
        print(path)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
