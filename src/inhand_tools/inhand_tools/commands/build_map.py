"""``build_map``: the map the mapping nodes would build, from a bag.

    build_map BAG [--config config/mapping.yaml [--config config/stereo.yaml]]
                  [--output-dir maps] [--name NAME] [--set NAME=VALUE ...]

Reads a rosbag2 bag (MCAP or sqlite3) holding the driver's ``polhemus/<name>/pose``
topics, runs the same registration and occupancy code with the same parameters (the
``registration_node`` and ``occupancy_node`` sections of the YAML files, later files
overriding earlier ones, then ``--set`` overrides), and writes ``<name>.npz`` and
``<name>.ply`` as ``occupancy/save`` would. When the bag also holds a stereo pair
(``stereo/left|right/image_raw`` and their camera_info) and a ``stereo_node`` section sets
``camera_pose`` (``config/stereo.yaml``), the occupied cells are coloured from the first
usable pair as the stereo node colours them (``occupancy/textured``) and the files carry the
colours. No DDS involved. A truncated bag is reported with what could be read, and the map
of that part is still written (exit code 1); a bag without the topics is refused (exit
code 2).

A damaged bag (an MCAP chunk or data section that fails its CRC, a sqlite3 database that
fails its quick_check, a record that does not parse, a file cut short) is read without the
damaged messages, and one line names what was left out. Its map is written when the output
files do not exist yet (exit code 1, as for a truncated bag); over an existing map only
with ``--force``: without it the existing files are left as they were (exit code 2). The
summary's ``bag check`` line says what could be checked: an MCAP file without CRCs
(rosbags, and so ``bag_record``, writes none) cannot show damage inside a message.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from inhand_common.blas_threads import single_threaded_blas
from inhand_common.cli_types import command_parser
from inhand_common.parameters import ParameterError
from inhand_mapping.bag_mapping import build_map_from_bag
from inhand_mapping.global_map import GlobalMap
from inhand_mapping.map_products import MapProducts, save_map
from inhand_mapping.mapping_config import OccupancyConfig, load_parameters, parse_overrides
from inhand_mapping.node_health import outside_note
from inhand_mapping.occupancy import OccupancyGrid
from inhand_shape.shape_extraction import SHAPE_PARAMETERS
from inhand_stereo.stereo_config import STEREO_PARAMETERS, StereoConfig
from inhand_stereo.texture import CellTexture
from inhand_tools.bag_stereo_shot import read_bag_shot, stereo_config_for_map
from inhand_tools.commands.extract_shape import shape_parameters, write_shape_of_map

EXIT_TRUNCATED = 1
EXIT_BAD_INPUT = 2


def _with_vision(bag: Path, stereo: StereoConfig, occupancy: OccupancyConfig,
                 touch: OccupancyGrid) -> tuple[GlobalMap, CellTexture | None, list[str]]:
    """The map the nodes would publish (the touch map, or its fusion with the vision map
    of the bag's stereo pairs), the colours of its occupied cells from the first pair, and
    lines saying what the pairs gave. Refused pairs are reported on stderr."""
    global_map = GlobalMap.for_config(touch, occupancy)
    started = time.monotonic()
    shot, why = read_bag_shot(bag, stereo)
    if shot is None:
        return global_map, None, [] if why is None else [f'  texture: none ({why})']
    for line in shot.pairs.refused:
        print(f'build_map: {line}', file=sys.stderr)
    notes = []
    if occupancy.fusion != 'none':
        global_map.set_vision(shot.vision_log_odds())
        observed = int(np.count_nonzero(global_map.vision))
        notes.append(f'  vision: {len(shot.pairs.placed)} stereo pair(s), {observed} cells '
                     f'observed; {occupancy.fusion} fusion with touch')
    grid = global_map.grid()
    centres = grid.cells(threshold=occupancy.occupied_threshold)[0]
    # the cells the judge rescued (their layer under the threshold) hide nothing
    rescued = grid.layer_probabilities(threshold=occupancy.occupied_threshold) \
        < occupancy.occupied_threshold
    texture = shot.texture(centres, rescued)
    notes.append(f'  texture: {int(texture.textured.sum())} of {len(centres)} occupied cells '
                 f'seen by the stereo pair at {shot.texture_stamp:.3f} s '
                 f'({time.monotonic() - started:.2f} s)')
    return global_map, texture, notes


def _parser() -> argparse.ArgumentParser:
    parser = command_parser('build_map', __doc__, epilog_from=2)
    parser.add_argument('bag', type=Path, help='bag folder, or .mcap / .db3 file')
    parser.add_argument('--config', action='append', default=[],
                        help='ROS parameter file with registration_node and occupancy_node '
                        '(and stereo_node) sections, e.g. config/mapping.yaml; repeatable, '
                        'later files override earlier ones')
    parser.add_argument('--output-dir', type=Path, default=Path('maps'))
    parser.add_argument('--name', help='file name stem (default: the bag name)')
    parser.add_argument('--set', action='append', default=[], metavar='NAME=VALUE',
                        help='override a parameter (repeatable)')
    parser.add_argument('--quiet', action='store_true', help='no progress line')
    parser.add_argument('--shape', action='store_true',
                        help="also the map's surface mesh, superquadric parts and grasps, as "
                        'extract_shape writes them (its shape_node section of --config)')
    parser.add_argument('--force', action='store_true',
                        help='write over an existing map a map from a damaged or truncated '
                        'bag, or an empty map (either otherwise leaves the existing map '
                        'alone)')
    return parser


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    single_threaded_blas()     # as the nodes it stands for
    try:
        overrides = parse_overrides(args.set)
        registration, occupancy = load_parameters(
            args.config, overrides, also_known={spec.name for spec in STEREO_PARAMETERS}
            | {spec.name for spec in SHAPE_PARAMETERS})
        shape_names = {spec.name for spec in SHAPE_PARAMETERS}
        shape = shape_parameters(args.config, [pair for pair in args.set if pair.partition('=')[0].strip()
                                               in shape_names]) if args.shape else None
        stereo = stereo_config_for_map(args.config, registration, occupancy, overrides)
        if not args.bag.exists():
            raise ValueError(f'{args.bag}: no such bag')
        start = time.monotonic()
        result = build_map_from_bag(args.bag, registration, occupancy, progress=not args.quiet)
    except (ParameterError, ValueError, OSError) as error:
        print(f'build_map: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    elapsed = time.monotonic() - start
    grid, registrar, report = result['grid'], result['registrar'], result['report']
    threshold = occupancy.occupied_threshold
    touch = grid
    global_map, texture, stereo_notes = _with_vision(args.bag, stereo, occupancy, touch)
    grid = global_map.grid()
    name = args.name or args.bag.name.rsplit('.', 1)[0] or 'map'
    existing = args.output_dir / f'{name}.npz'
    outputs = [path for path in (existing, args.output_dir / f'{name}.ply',
                                 args.output_dir / f'{name}_object_centric.ply') if path.exists()]
    if report['truncated'] and outputs and not args.force:
        # A damaged bag must not silently cost a good map either.
        print(f'build_map: {args.bag} is damaged: {report["truncated"]}. Refusing to write its '
              f'map over the existing {", ".join(str(p) for p in outputs)}, left as they '
              'were (--force writes it anyway)', file=sys.stderr)
        return EXIT_BAD_INPUT
    if not grid.touched_mask().any() and existing.exists() and not args.force:
        # An unreadable bag must not cost a good map.
        print(f'build_map: nothing could be mapped from {args.bag} ({report["messages"]} '
              f'messages read{"; " + str(report["truncated"]) if report["truncated"] else ""}'
              f'); {existing} and its PLYs are left as they were (--force writes the empty map '
              'over them)', file=sys.stderr)
        return EXIT_TRUNCATED
    paths = save_map(grid, args.output_dir, name, threshold, occupancy.frames.map_frame,
                     extra={'bag': str(args.bag), 'truncated': report['truncated'],
                            'fusion': occupancy.fusion if global_map.fusing else 'none',
                            'registration_mode': registration.mode},
                     colours=None if texture is None else texture.colours,
                     textured=None if texture is None else texture.textured,
                     local_maps=global_map.local_maps())
    stats = registrar.stats
    span = ((report['bag_end'] or 0) - (report['bag_start'] or 0)) * 1e-9
    products = MapProducts(grid, threshold)
    touched, occupied = products.cells()
    frame = products.object_frame()
    print(f'build_map: {report["messages"]} messages, {span:.1f} s of data in {elapsed:.2f} s '
          f'({span / elapsed if elapsed > 0 else float("inf"):.1f}x real time)')
    print(f'  registration ({registration.mode}): {stats.registered} of '
          f'{stats.received} fingertip positions; dropped {stats.dropped_gap} (object pose '
          f'gap), {stats.dropped_before_object} (before the first object pose), '
          f'{stats.dropped_invalid} (invalid)')
    if registrar.pad_normals is not None:
        print(f'  {registrar.pad_normals.summary()}')
    print(f'  map: {grid.counts.integrated} points integrated, {grid.counts.outside} outside '
          f'the workspace, {grid.counts.invalid} invalid; {len(touched)} cells touched, '
          f'{len(occupied)} above {threshold:g}')
    if grid.counts.outside:
        on_faces = products.occupied_on_faces(occupied)
        print(f"  {'warning: ' if on_faces else ''}"
              f"{outside_note(grid.counts.outside, stats.registered, on_faces, '')}",
              file=sys.stderr if on_faces else sys.stdout)
    for note in stereo_notes:
        print(note)
    if frame is not None:
        print('  centre of mass (object frame): '
              + ', '.join(f'{v:+.4f}' for v in frame.centre_of_mass) + ' m')
    if report.get('checked'):
        print('  bag check: ' + '; '.join(report['checked']))
    print('  wrote ' + ', '.join(str(p) for p in paths))
    if shape is not None:
        write_shape_of_map(existing, args.output_dir, name, shape, quiet=True)
    if report['truncated']:
        print(f'build_map: the bag is truncated or damaged: {report["truncated"]}. The map '
              f'above is built from the {report["messages"]} messages that could be read.',
              file=sys.stderr)
        return EXIT_TRUNCATED
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
