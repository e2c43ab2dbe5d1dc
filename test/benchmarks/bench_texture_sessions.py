#!/usr/bin/env python3
"""Texture of the occupied cells on touch sessions of other hands and objects.

Run from the workspace root with the workspace's environment::

    .venv/bin/python test/benchmarks/bench_texture_sessions.py [--keep DIR] [--set tune|report|bundled|all]
        [--map-view off|MIN,TOLERANCE,REACH[,AHEAD[,BLIND]]] [--why]

The map's texture (``inhand_stereo/texture.py``) is judged on what a user meets: a touch map
of a hand that hovers, trembles and lifts at an angle (``simulate_session --hand ...``),
not the simulator's default hand, on objects the texture rule was not written on, with the
camera in another place each time, and the bundled bags. Each session: ``simulate_session``
(with one stereo pair), ``build_map`` with the shipped files and the rig's own camera_pose,
then the map's cells against the truth, as ``map_metrics`` scores them:

* *seen cells*: occupied cells (p > 0.8) holding a surface sample the camera saw (or whose
  nearest sample it saw), by the truth's depth (``map_quality.seen_cells``);
* *textured*: the share of the seen cells that carry a colour (target >= 0.85);
* *area*: the same by area: of the visible true surface samples that lie in occupied cells,
  the share whose cell is textured (a cell of which the camera saw a sliver counts for its
  sliver, not as a whole cell);
* *back faces*: textured cells more than one cell from any surface the camera saw, as a
  share of the occupied cells it did not see (target <= 1 %); *unseen textured*: all
  textured cells the truth does not count as seen (most lie next to the seen surface);
* *colour error*: the median and 95th percentile distance (0-441 RGB) between a textured cell's colour and
  the truth's colour there.

Two sets of sessions: ``tune`` (the sessions the texture rule's defaults were chosen on)
and ``report`` (others, never used to choose); ``bundled``: the three bundled bags;
``validation``: the independent generator's ten touch sessions
(``../shared/data/validation_sessions``: other hands, other objects; a check, never used to
choose; skipped with a line when the folder is absent), each seen from three sides (30
degrees above, 0.42 m, azimuths -60, 30 and 120 degrees). Their bags hold no images, so each
gets a stereo pair of its own surface samples, drawn by ``point_render.py`` (point
splatting: not our simulator's renderer) with ``inhand_sim``'s plaster texture for scanned
meshes, written with the bag's poses into a copy under the scratch folder, and a truth file
in the simulator's format (the samples, the object's first pose, the pair's depth).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

WORKSPACE = Path(__file__).resolve().parents[2]
CONFIG = WORKSPACE / 'config'

HOVERING = ['--hand', 'hover_probability=0.2']
SETS = {
    'tune': {
        'duck': ['--object', 'duck', '--static', '--rate', '30', '--speed', '10', *HOVERING,
                 '--hand', 'speed_profile=bell', '--hand', 'tremor_amplitude=0.0005',
                 '--hand', 'liftoff_angle_range=0,45', '--seed', '301', '--camera-azimuth',
                 '40'],
        'animal': ['--object', 'animal', '--static', '--rate', '30', '--speed', '5', *HOVERING,
                   '--hand', 'speed_profile=bell', '--seed', '302', '--camera-elevation', '35'],
        'cup': ['--object', 'cup', '--moving', '--rate', '30', '--speed', '10', '--hand',
                'hover_probability=0.3', '--hand', 'tremor_amplitude=0.0005', '--seed', '303'],
        'mug': ['--object', 'mug', '--static', '--rate', '15', '--speed', '15', '--seed', '304',
                '--camera-azimuth', '120'],
    },
    'report': {
        'box': ['--object', 'box', '--static', '--rate', '30', '--speed', '8', '--hand',
                'hover_probability=0.25', '--hand', 'speed_profile=bell', '--hand',
                'tremor_amplitude=0.0005', '--seed', '401', '--camera-azimuth', '-30',
                '--camera-elevation', '30'],
        'large': ['--object', 'large', '--moving', '--rate', '30', '--speed', '12', *HOVERING,
                  '--hand', 'liftoff_angle_range=0,45', '--seed', '402'],
        'plate': ['--object', 'plate', '--static', '--rate', '15', '--speed', '5', *HOVERING,
                  '--seed', '403', '--camera-elevation', '50'],
        'bottle': ['--object', 'bottle', '--static', '--rate', '30', '--speed', '10', *HOVERING,
                   '--hand', 'tremor_amplitude=0.0005', '--seed', '404', '--camera-azimuth',
                   '70'],
        'cat': ['--object', 'cat', '--moving', '--rate', '30', '--speed', '15', '--hand',
                'hover_probability=0.3', '--hand', 'speed_profile=bell', '--seed', '405',
                '--camera-azimuth', '-60'],
    },
    'bundled': {'cat_static': None, 'cat_moving': None, 'bottle_static': None},
}


VALIDATION = WORKSPACE.parent / 'shared' / 'data' / 'validation_sessions'
VIEWS = (-60, 30, 120)    # camera azimuths (degrees), 30 degrees above, 0.42 m away
VIEW_ELEVATION, VIEW_DISTANCE = 30.0, 0.42


def validation_views() -> dict[str, tuple[str, int]]:
    """Session and camera azimuth of each view of the validation set, by view name."""
    names = sorted(path.name for path in VALIDATION.iterdir() if path.is_dir())
    return {f'{name}_az{azimuth}': (name, azimuth) for name in names for azimuth in VIEWS}


def validation_session(name: str, azimuth: int, folder: Path) -> Path:
    """The validation session ``name`` with a stereo pair of its object from ``azimuth``,
    as a bag and truth file under ``folder`` (made unless there)."""
    import math

    from point_render import render_samples
    from rosbags.highlevel import AnyReader

    from inhand_common.ground_truth import load_truth, write_truth
    from inhand_common.rotations import quaternion_to_matrix
    from inhand_sim.stereo_rig import StereoRig
    from inhand_sim.textures import surface_colour
    bag = folder / f'{name}_az{azimuth}'
    if bag.exists():
        return bag
    truth = load_truth(VALIDATION / f'{name}_truth.npz')
    surface, static = truth.surface_points, truth.static
    with AnyReader([VALIDATION / name]) as reader:
        first = next(reader.messages())[1]      # the pair: at the session's first stamp
        position, quaternion = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
        if not static:      # the map frame: the object sensor at its first pose
            objects = [c for c in reader.connections if c.topic.endswith('/object/pose')]
            connection, _, raw = next(reader.messages(connections=objects))
            pose = reader.deserialize(raw, connection.msgtype).pose
            position = np.array([pose.position.x, pose.position.y, pose.position.z])
            quaternion = np.array([pose.orientation.x, pose.orientation.y,
                                   pose.orientation.z, pose.orientation.w])
    placed = surface @ quaternion_to_matrix(quaternion).T + position
    up = math.radians(VIEW_ELEVATION)
    direction = (math.cos(up) * math.cos(math.radians(azimuth)),
                 math.cos(up) * math.sin(math.radians(azimuth)), -math.sin(up))
    rig = StereoRig.looking_at(target=(placed.min(axis=0) + placed.max(axis=0)) / 2,
                               direction=direction, distance=VIEW_DISTANCE)
    albedo = surface_colour('scan', surface)
    shot = render_samples(rig, placed, albedo, np.random.default_rng(1000 + azimuth))
    _copy_with_pair(VALIDATION / name, bag, shot, first)
    write_truth(Path(f'{bag}.truth.npz'), {
        'object_name': name, 'static': static, 'rate': truth.rate, 'seed': 0,
        'settings': {'validation_session': name, 'camera_azimuth_deg': azimuth},
        'surface_points': surface, 'surface_normals': truth.surface_normals,
        'contacts': truth.contacts, 'contact_times': truth.contact_times,
        'stray_points': np.zeros((0, 3)), 'stray_times': np.zeros(0),
        'object_times': np.zeros(1), 'object_positions': position[None],
        'object_quaternions': quaternion[None], 'surface_colours': albedo,
        'camera_pose': np.asarray(shot.camera_pose), 'stereo_time': np.array(0.0),
        'stereo_depth': shot.depth, 'stereo_object_mask': shot.mask,
        'stereo_focal': np.array(float(shot.focal)),
        'stereo_baseline': np.array(float(shot.baseline))})
    return bag


def _copy_with_pair(source: Path, bag: Path, shot, stamp_ns: int) -> None:
    """``source``'s messages into the bag ``bag``, the stereo pair first, at ``stamp_ns``."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from inhand_common.mcap_integrity import stamp_bag_crcs
    from inhand_sim.session import StereoConnections
    store = get_typestore(Stores.ROS2_JAZZY)
    with AnyReader([source]) as reader, \
            Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        StereoConnections(writer, store).write(shot, stamp_ns)
        connections: dict = {}
        for connection, stamp, raw in reader.messages():
            if connection.topic not in connections:
                connections[connection.topic] = writer.add_connection(
                    connection.topic, connection.msgtype, typestore=store)
            writer.write(connections[connection.topic], stamp, raw)
    stamp_bag_crcs(bag)


def session(name: str, options: list[str] | None, folder: Path) -> Path:
    """The session's bag (simulated into ``folder`` unless there, or bundled)."""
    if options is None:
        return WORKSPACE / 'bags' / name
    bag = folder / name
    if not bag.exists():
        from inhand_sim.commands.simulate_session import main as simulate
        simulate([*options, '--duration', '90', '--stereo', '--output', str(bag), '--quiet'])
    return bag


def camera_file(bag: Path, truth, folder: Path) -> Path:
    """The rig's camera_pose as its calibration would give it (the truth's)."""
    path = folder / f'{bag.name}_camera.yaml'
    path.write_text('/**/stereo_node:\n  ros__parameters:\n    camera_pose: ['
                    + ', '.join(f'{float(v):.9f}' for v in truth.stereo.camera_pose) + ']\n')
    return path


def scores(bag: Path, folder: Path, explain: bool = False) -> dict:
    from scipy.spatial import cKDTree

    from inhand_common.cell_lattice import cells_holding
    from inhand_common.ground_truth import in_frame, load_truth
    from inhand_tools.bag_stereo_shot import read_configured_shot
    from inhand_tools.commands.build_map import main as build_map
    from inhand_tools.map_cells import load_map
    from inhand_tools.map_quality import colour_metrics, seen_cells, surface_truth
    from inhand_tools.stereo_quality import principal_point, visible_samples
    truth = load_truth(f'{bag}.truth.npz')
    configs = [str(CONFIG / ('mapping_static.yaml' if truth.static else 'mapping.yaml')),
               str(CONFIG / 'stereo.yaml'), str(camera_file(bag, truth, folder))]
    out = folder / 'maps'
    with contextlib.redirect_stdout(io.StringIO()):
        build_map([str(bag), *[a for c in configs for a in ('--config', c)], '--output-dir',
                   str(out), '--quiet', '--force'])
    cells = load_map(out / f'{bag.name}.npz', None)
    shot, why = read_configured_shot(bag, configs)
    if shot is None:
        raise SystemExit(f'{bag}: {why}')
    truth = in_frame(truth, 'tracker' if truth.static else 'object')
    surface = surface_truth(truth, 0.005)
    resolution = cells.lattice.resolution
    visible = visible_samples(truth, principal_point(shot), resolution)
    occupied = cells.probabilities > 0.8
    seen = seen_cells(cells.centres[occupied], cells.lattice, surface, visible)
    textured = cells.textured[occupied]
    far, _ = cKDTree(truth.surface_points[visible]).query(cells.centres[occupied])
    colour = colour_metrics(cells.centres, cells.probabilities, cells.lattice, cells.colours,
                            cells.textured, surface, truth.surface_colours, visible)
    unseen = int(np.count_nonzero(~seen))
    # the seen surface by area: the visible true samples (area-uniform) in occupied cells
    owner = cells_holding(truth.surface_points[visible], cells.centres[occupied], cells.lattice)
    held = owner[owner >= 0]
    result = {'seen': int(seen.sum()), 'textured': int(np.count_nonzero(seen & textured)),
              'area': len(held), 'area_textured': int(np.count_nonzero(textured[held])),
              'unseen': unseen, 'unseen_textured': int(np.count_nonzero(textured & ~seen)),
              'back': int(np.count_nonzero(textured & ~seen & (far > resolution))),
              'colour': colour['colour_error_median'], 'p95': colour['colour_error_p95']}
    if explain:
        result.update(_why_untextured(cells, occupied, seen, visible, owner, truth, surface,
                                      shot))
    return result


WHY_TOLERANCES = (0.001, 0.002, 0.003)   # m: the truth's visibility, tighter than a cell


def _why_untextured(cells, occupied, seen, visible, owner, truth, surface, shot) -> dict:
    """Where the seen cells left untextured are (``--why``), in counts that add up over a
    set: those the map's own cells hide at their centre's pixel (another occupied cell more
    than ``MapView.ahead`` nearer: what texture_cells' second rule reads), the visible true
    surface samples in the untextured and in the textured seen cells, those of the
    untextured cells' samples whose pixel has no stereo depth, and the seen cells and the
    textured ones among them were the truth's visibility tighter (:data:`WHY_TOLERANCES`)
    than its one cell (``visible``: the samples :func:`scores` counts as seen; ``owner``: the
    occupied cell each of them lies in, -1 for none)."""
    from inhand_stereo.texture import MAP_VIEW, depth_holes, project_cells
    from inhand_stereo.texture_kernels import map_depth
    from inhand_tools.map_quality import seen_cells
    from inhand_tools.stereo_quality import principal_point, visible_samples
    resolution = cells.lattice.resolution
    centres, textured = cells.centres[occupied], cells.textured[occupied]
    left = shot.placed.shot
    camera = np.asarray(shot.config.camera_pose, dtype=float)
    placed = (shot.placed.object_pose[:3], shot.placed.object_pose[3:])
    pose = (camera[:3], camera[3:])

    def pixels(points):
        projection = project_cells(points, left.left_camera, left.rectifier.R_left, pose, placed)
        height, width = left.depth.shape
        column = np.clip(np.floor(projection.u + 0.5).astype(int), 0, width - 1)
        row = np.clip(np.floor(projection.v + 0.5).astype(int), 0, height - 1)
        return projection, row, column

    projection, row, column = pixels(centres)
    front = np.empty(left.depth.shape)
    map_depth(projection.u, projection.v, projection.z,
              np.asarray(left.left_camera.P, dtype=float), float(resolution), front)
    left_out = seen & ~textured
    hidden = front[row, column] < projection.z - MAP_VIEW.ahead * resolution
    points = truth.surface_points[visible]
    counts = np.bincount(owner[owner >= 0], minlength=len(centres))
    mine = (owner >= 0) & left_out[np.maximum(owner, 0)]
    _, sample_row, sample_column = pixels(points[mine])
    measured = left.depth[sample_row, sample_column]
    no_depth = ~(np.isfinite(measured) & (measured > 0))
    holes = depth_holes(left.depth)[sample_row, sample_column]
    result = {'left_out': int(left_out.sum()), 'left_hidden': int((left_out & hidden).sum()),
              'left_samples': int(counts[left_out].sum()),
              'textured_samples': int(counts[seen & textured].sum()),
              'left_no_depth': int(no_depth.sum()), 'left_holes': int((no_depth & holes).sum())}
    for tolerance in WHY_TOLERANCES:
        tight = seen_cells(centres, cells.lattice, surface,
                           visible_samples(truth, principal_point(shot), tolerance))
        result[f'seen_{tolerance}'] = int(tight.sum())
        result[f'textured_{tolerance}'] = int((tight & textured).sum())
    return result


def _why_line(total: dict) -> str:
    """The ``--why`` summary of a set (the sums of :func:`_why_untextured`)."""
    left = max(total['left_out'], 1)
    tight = ', '.join(f"{1000 * t:.0f} mm {total[f'textured_{t}'] / max(total[f'seen_{t}'], 1):.3f}"
                      for t in WHY_TOLERANCES)
    return (f"  why: {total['left_out']} seen cells untextured; {total['left_hidden'] / left:.0%} "
            f"of them hidden at their centre by the map's cells in front; visible samples per cell "
            f"{total['left_samples'] / left:.1f} (textured seen cells "
            f"{total['textured_samples'] / max(total['textured'], 1):.1f}); "
            f"{total['left_no_depth'] / max(total['left_samples'], 1):.0%} of their samples' pixels "
            f"without stereo depth ({total['left_holes'] / max(total['left_samples'], 1):.0%} "
            f"in holes); textured share with the truth's visibility within {tight}")


KEYS = ('seen', 'textured', 'unseen', 'back', 'unseen_textured', 'area', 'area_textured')


def _row(result: dict) -> str:
    unseen = max(int(result['unseen']), 1)
    colour = (f" {result['colour']:6.1f} / {result['p95']:5.1f}" if 'colour' in result
              else '')
    return (f"{result['seen']:5d} {result['textured'] / result['seen']:9.3f} "
            f"{result['area_textured'] / max(result['area'], 1):6.3f} "
            f"{result['back']:5d} ({result['back'] / unseen:6.2%}) "
            f"{result['unseen_textured']:5d} ({result['unseen_textured'] / unseen:6.2%})"
            f'{colour}')


def _sessions(set_name: str, folder: Path):
    """(name, a call making and returning its bag) of each session of the set."""
    if set_name == 'validation':
        return [(view, lambda pair=pair: validation_session(*pair, folder))
                for view, pair in validation_views().items()]
    return [(name, lambda name=name, options=options: session(name, options, folder))
            for name, options in SETS[set_name].items()]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--keep', type=Path, help='keep (and reuse) the sessions here')
    parser.add_argument('--set', choices=[*SETS, 'validation', 'all'], default='all')
    parser.add_argument('--map-view', metavar='off|MIN,TOLERANCE,REACH[,AHEAD[,BLIND]]',
                        help="texture_cells' second rule instead of its default (MapView): off, "
                        'or its min_samples, tolerance (cells), reach (px), ahead (cells) '
                        'and blind (on, off)')
    parser.add_argument('--why', action='store_true',
                        help='also where the seen cells left untextured are (hidden by the '
                        "map's cells, without stereo depth, few visible samples) and the share "
                        "with a tighter visibility of the truth")
    args = parser.parse_args()
    if args.map_view:
        from inhand_stereo.texture import MapView, texture_cells
        fields = args.map_view.split(',')
        try:
            view = None if args.map_view == 'off' else MapView(
                min_samples=int(fields[0]), tolerance=float(fields[1]), reach=float(fields[2]),
                ahead=float(fields[3]) if len(fields) > 3 else MapView().ahead,
                blind=fields[4] == 'on' if len(fields) > 4 else MapView().blind)
        except (IndexError, ValueError):
            parser.error(f'--map-view: off, or MIN,TOLERANCE,REACH[,AHEAD[,on|off]], got '
                         f'{args.map_view!r}')
        # every caller (build_map's stereo node path included) uses the default
        assert texture_cells.__kwdefaults__ is not None
        texture_cells.__kwdefaults__['map_view'] = view
        print(f'texture_cells map_view={view}')
    names = [*SETS, 'validation'] if args.set == 'all' else [args.set]
    with tempfile.TemporaryDirectory() as scratch:
        folder = args.keep or Path(scratch)
        folder.mkdir(parents=True, exist_ok=True)
        # the validation set's views are named after their sessions: a wider first column
        width = 34 if 'validation' in names else 14
        print(f'{"session":{width}s} {"seen":>5s} {"textured":>9s} {"area":>6s} {"back faces":>16s} '
              f'{"unseen textured":>17s} {"colour error median / p95":>14s}', flush=True)
        for set_name in names:
            if set_name == 'validation' and not VALIDATION.is_dir():
                print(f'validation: skipped: no {VALIDATION} (the shared data beside the '
                      'workspace)\n', flush=True)
                continue
            total = np.zeros(len(KEYS), dtype=np.int64)
            reasons: dict = {}
            for name, bag in _sessions(set_name, folder):
                started = time.monotonic()
                result = scores(bag(), folder, explain=args.why)
                total += [result[key] for key in KEYS]
                for key, value in result.items():
                    if key not in KEYS and key not in ('colour', 'p95'):
                        reasons[key] = reasons.get(key, 0) + value
                print(f'{name:{width}s} {_row(result)}   ({time.monotonic() - started:.0f} s)',
                      flush=True)
            seen, textured, unseen, back = total[:4]
            verdict = 'PASS' if textured / seen >= 0.85 and back / unseen <= 0.01 else 'FAIL'
            print(f'{set_name + " (all)":{width}s} {_row(dict(zip(KEYS, total)))}   targets >= '
                  f'0.85 textured, <= 1 % back faces: {verdict}', flush=True)
            if args.why:
                print(_why_line({**reasons, 'textured': int(textured)}), flush=True)
            print(flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
