"""``map_metrics``: how close a map (and the registered points) is to the true surface.

    map_metrics MAP [--truth TRUTH.npz] [--bag BAG] [--threshold 0.8 ...]
                    [--frame object|tracker] [--explored-radius 0.005] [--json OUT]

MAP is one of
  * an NPZ saved by the occupancy node (``occupancy/save``) or ``build_map``: every touched
    cell with its probability, so any threshold can be evaluated;
  * a PLY saved beside it (only the cells above the threshold it was saved with);
  * a bag holding a recorded ``occupancy/cloud`` (every touched cell) or
    ``occupancy/occupied`` cloud: the last message is used.

TRUTH is the simulator's ``<bag folder>.truth.npz``; it defaults to the sidecar of
``--bag`` (or of MAP when MAP is a bag). ``--bag`` also gives the registered raw points:
the bag's fingertip poses through the same registration as ``build_map`` (tracked for a
map in the object frame, static for one in the tracker frame; ``--config`` for its
parameters). The frame defaults to the tracker frame for static sessions and the object
frame otherwise. The metric definitions are in ``inhand_tools/metrics.py``.

Exit status: 0 done, 2 bad input (missing or foreign file, bad option).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from inhand_tools.ground_truth import (FRAMES, GroundTruth, default_frame, in_frame, load_truth,
                                       truth_path_for_bag)
from inhand_tools.metrics import (METRIC_LABELS, Lattice, SurfaceTruth, infer_lattice,
                                  map_metrics, point_metrics)

__all__ = ['MapCells', 'load_map', 'is_bag', 'bag_topics', 'BagPoints', 'read_bag_points',
           'bag_mode_for_frame', 'find_truth', 'evaluate', 'main', 'EXIT_BAD_INPUT']

EXIT_BAD_INPUT = 2
CLOUD_TOPICS = ('occupancy/cloud', 'occupancy/occupied')


@dataclass
class MapCells:
    """Cells of a map from any of the supported files, in the map's frame."""

    centres: np.ndarray         # (n, 3) float64, m
    probabilities: np.ndarray   # (n,)
    hits: np.ndarray            # (n,) (zeros if the file has none)
    first_touch: np.ndarray     # (n,) seconds since the map's earliest touch, NaN if never hit
    lattice: Lattice
    kind: str                   # 'npz', 'ply', 'bag cloud'
    source: str                 # what was read, for people
    complete: bool              # every touched cell (True) or only those above a threshold
    frame_id: str = 'object'
    metadata: dict = field(default_factory=dict)

    def describe(self) -> str:
        which = 'every touched cell' if self.complete else 'only the cells it was saved with'
        return (f'{self.source}: {len(self.centres)} cells ({which}), cell '
                f'{self.lattice.resolution * 1000:g} mm, frame {self.frame_id}')


def is_bag(path: Path) -> bool:
    path = Path(path)
    if path.is_dir():
        return (path / 'metadata.yaml').exists() or any(path.glob('*.mcap')) or \
            any(path.glob('*.db3'))
    return path.suffix in ('.mcap', '.db3')


def _relative(first_touch) -> np.ndarray:
    first_touch = np.asarray(first_touch, dtype=float)
    finite = first_touch[np.isfinite(first_touch)]
    return first_touch - finite.min() if finite.size else first_touch


def _structured_cells(cells: np.ndarray, source: str, kind: str, complete: bool,
                      resolution: float | None, frame_id: str) -> MapCells:
    names = cells.dtype.names or ()
    missing = [name for name in ('x', 'y', 'z', 'intensity') if name not in names]
    if missing:
        raise ValueError(f'{source}: not a map cloud: no {", ".join(missing)} field(s) '
                         f'(has {", ".join(names) or "none"})')
    centres = np.stack([cells[a] for a in 'xyz'], axis=1).astype(np.float64)
    if len(centres) == 0:
        raise ValueError(f'{source}: the map has no cells')
    lattice = infer_lattice(centres, resolution)
    hits = cells['hits'].astype(np.int64) if 'hits' in names else np.zeros(len(cells), np.int64)
    first = cells['first_touch'] if 'first_touch' in names else np.full(len(cells), np.nan)
    return MapCells(centres, cells['intensity'].astype(np.float64), hits, _relative(first),
                    lattice, kind, source, complete, frame_id)


def _read_bag_cloud(bag: Path, resolution: float | None) -> MapCells:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    from inhand_common.point_cloud import from_point_cloud2
    store = get_typestore(Stores.ROS2_JAZZY)
    try:
        reader = AnyReader([bag], default_typestore=store)
        reader.open()
    except Exception as error:  # rosbags raises several kinds for unreadable bags
        raise ValueError(f'{bag}: cannot open as a rosbag2 bag (MCAP or sqlite3): '
                         f'{error}') from None
    try:
        topics = {c.topic.lstrip('/'): c for c in reader.connections}
        topic = next((t for t in CLOUD_TOPICS if t in topics), None)
        if topic is None:
            raise ValueError(f'{bag}: no map cloud ({" or ".join(CLOUD_TOPICS)}) in this bag; '
                             f'it has {sorted(topics) or "no topics"}')
        connection = topics[topic]
        if connection.msgtype != 'sensor_msgs/msg/PointCloud2':
            raise ValueError(f'{bag}: {topic} is {connection.msgtype}, expected '
                             'sensor_msgs/msg/PointCloud2')
        last = None
        for _, _, raw in reader.messages(connections=[connection]):
            last = raw
        if last is None:
            raise ValueError(f'{bag}: {topic} has no messages')
        message = store.deserialize_cdr(last, connection.msgtype)
        cells = np.array(from_point_cloud2(message))  # a copy: the message buffer goes away
        frame_id = message.header.frame_id or 'object'
    finally:
        reader.close()
    return _structured_cells(cells, f'{bag} [{topic}, last message]', 'bag cloud',
                             topic == 'occupancy/cloud', resolution, frame_id)


def load_map(path, resolution: float | None = None) -> MapCells:
    """The cells of the map at ``path`` (NPZ, PLY or a bag with a map cloud).

    ``resolution`` overrides the cell size inferred from a PLY or a cloud. ValueError with
    the reason for anything else.
    """
    path = Path(path)
    if not path.exists():
        raise ValueError(f'{path}: no such map file or bag')
    if is_bag(path):
        return _read_bag_cloud(path, resolution)
    with open(path, 'rb') as stream:
        head = stream.read(4)
    if head[:3] == b'ply':
        from inhand_mapping.map_io import read_ply
        cells = read_ply(path)
        return _structured_cells(np.array(cells), str(path), 'ply', False, resolution, 'object')
    if head == b'PK\x03\x04' or path.suffix == '.npz':
        from inhand_mapping.map_io import load_npz
        try:
            with np.load(path, allow_pickle=False) as archive:
                is_truth = 'surface_points' in archive.files and 'log_odds' not in archive.files
        except Exception:  # not an archive at all: load_npz says so below
            is_truth = False
        if is_truth:
            raise ValueError(f'{path}: this is a ground-truth file, not a map: give it with '
                             '--truth')
        grid, metadata = load_npz(path)
        centres, probabilities, hits, first_touch = grid.cells()
        if len(centres) == 0:
            raise ValueError(f'{path}: the map has no touched cells')
        lattice = Lattice(grid.spec.resolution, tuple(float(v) for v in grid.spec.origin))
        return MapCells(centres, np.asarray(probabilities, dtype=float),
                        hits.astype(np.int64), _relative(first_touch), lattice, 'npz',
                        str(path), True, metadata.get('frame_id', 'object'), metadata)
    raise ValueError(f'{path}: not a map: expected an NPZ saved by occupancy/save or '
                     'build_map, a PLY, or a bag with an occupancy cloud')


@dataclass
class BagPoints:
    """Fingertip positions of a bag: raw (tracker frame) and registered (map frame)."""

    raw: np.ndarray          # (n, 3) tracker frame
    raw_fingers: np.ndarray  # (n,) index into finger_names
    registered: np.ndarray   # (m, 3) map frame
    registered_fingers: np.ndarray
    registered_times: np.ndarray
    finger_names: list
    mode: str
    stats: object = None


def read_bag_points(bag, mode: str, config: str | None = None) -> BagPoints:
    """Raw and registered fingertip positions, registered exactly as ``build_map`` does
    (same parameters, same Registrar, same feeding order), in ``mode`` static/tracked."""
    from inhand_mapping.build_map import BagRegistration, load_parameters
    bag = Path(bag)
    if not bag.exists():
        raise ValueError(f'{bag}: no such bag')
    values, _ = load_parameters(config, {'mode': mode})
    registration = BagRegistration(bag, values, keep_raw=True)
    batches = [batch for batch in registration if len(batch[0])]
    if batches:
        points, times, finger_ids = (np.concatenate([b[k] for b in batches]) for k in range(3))
    else:
        points, times, finger_ids = np.empty((0, 3)), np.empty(0), np.empty(0, np.int64)
    raw = registration.raw
    return BagPoints(np.concatenate([r[0] for r in raw]) if raw else np.empty((0, 3)),
                     np.concatenate([r[1] for r in raw]).astype(np.int64) if raw
                     else np.empty(0, np.int64),
                     points, finger_ids.astype(np.int64), times, list(values['finger_names']),
                     mode, registration.registrar.stats)


def bag_topics(bag) -> dict[str, str]:
    """Topic name (no leading slash) -> message type of every connection in a bag."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    try:
        reader = AnyReader([Path(bag)], default_typestore=get_typestore(Stores.ROS2_JAZZY))
        reader.open()
    except Exception as error:  # rosbags raises several kinds for unreadable bags
        raise ValueError(f'{bag}: cannot open as a rosbag2 bag (MCAP or sqlite3): '
                         f'{error}') from None
    try:
        return {c.topic.lstrip('/'): c.msgtype for c in reader.connections}
    finally:
        reader.close()


def bag_mode_for_frame(frame: str) -> str:
    """Registration mode of the map frame: tracked maps are in the object frame."""
    return 'tracked' if frame == 'object' else 'static'


def find_truth(truth: str | None, bag: Path | None, map_path: Path) -> Path:
    if truth:
        return Path(truth)
    for candidate in ([bag] if bag else []) + ([map_path] if is_bag(map_path) else []):
        sidecar = truth_path_for_bag(candidate)
        if sidecar.exists():
            return sidecar
    raise ValueError('no ground truth: give --truth TRUTH.npz (or --bag BAG with its '
                     'BAG.truth.npz beside it)')


def evaluate(cells: MapCells, truth: GroundTruth, thresholds, explored_radius: float = 0.005,
             points: np.ndarray | None = None) -> dict:
    """Metrics of the map at each threshold (and of the points, if given) against
    ``truth``, which must already be in the map's frame."""
    surface = SurfaceTruth(truth.surface_points, truth.contacts, truth.surface_normals,
                           truth.stray_points, explored_radius)
    results = {'map': {}, 'points': None}
    for threshold in thresholds:
        results['map'][f'{threshold:g}'] = map_metrics(
            cells.centres, cells.probabilities, cells.lattice, surface, threshold)
    if points is not None:
        results['points'] = point_metrics(points, surface)
    return results


def _format(key: str, value) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return 'n/a'
    label_format = METRIC_LABELS[key][1]
    return label_format.format(int(value) if label_format.endswith('d}') else value)


def _table(results: dict, column_names: list[str]) -> list[str]:
    map_keys = ['occupied_cells', 'explored_cells', 'iou', 'cell_precision', 'cell_recall',
                'cell_fscore', 'precision_at_5mm', 'recall_at_5mm', 'fscore_at_5mm',
                'chamfer_mm', 'map_to_surface_mm', 'surface_to_map_mm', 'normal_offset_mm',
                'com_error_mm', 'stray_cells', 'off_surface_cells']
    columns = list(results['map'].values())
    width = max(len(METRIC_LABELS[k][0]) for k in METRIC_LABELS) + 2
    lines = [f'{"metric":<{width}}' + ''.join(f'{name:>12}' for name in column_names)]
    lines.append('-' * len(lines[0]))
    for key in map_keys:
        lines.append(f'{METRIC_LABELS[key][0]:<{width}}'
                     + ''.join(f'{_format(key, column[key]):>12}' for column in columns))
    points = results.get('points')
    if points is not None:
        lines.append('')
        lines.append(f'{"registered raw points":<{width}}{"points":>12}')
        lines.append('-' * (width + 12))
        for key in ('points', 'precision_at_5mm', 'recall_at_5mm', 'fscore_at_5mm',
                    'chamfer_mm', 'points_to_surface_mm', 'median_to_surface_mm',
                    'p95_to_surface_mm', 'surface_to_points_mm'):
            lines.append(f'{METRIC_LABELS[key][0]:<{width}}{_format(key, points[key]):>12}')
    return lines


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    return value


def frame_check(cells: MapCells, truth: GroundTruth, threshold: float) -> str | None:
    """A warning when the map and the truth seem to be in different frames."""
    keep = cells.probabilities > threshold
    if not keep.any() or len(truth.contacts) == 0:
        return None
    offset = np.linalg.norm(cells.centres[keep].mean(axis=0) - truth.contacts.mean(axis=0))
    extent = np.linalg.norm(np.ptp(truth.surface_points, axis=0))
    if offset > max(0.5 * extent, 0.03):
        other = 'tracker' if truth.frame == 'object' else 'object'
        return (f'the occupied cells are {offset * 100:.1f} cm from the true contacts: are the '
                f'map and the truth in the same frame? (compared in the {truth.frame} frame; '
                f'try --frame {other})')
    return None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='map_metrics', description=__doc__.split('\n\n')[0],
                                     epilog=__doc__.split('\n\n', 1)[1],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('map', type=Path, help='map: NPZ, PLY, or a bag with an occupancy cloud')
    parser.add_argument('--truth', help='simulator truth file (default: the bag\'s sidecar '
                        'BAG.truth.npz)')
    parser.add_argument('--bag', type=Path, help='session bag: registered raw points are '
                        'scored too')
    parser.add_argument('--threshold', type=float, nargs='+', default=[0.8],
                        help='occupied = probability above this (several give several '
                        'columns; default 0.8)')
    parser.add_argument('--frame', choices=FRAMES, help='frame the map is in (default: '
                        'tracker for a static session, object otherwise)')
    parser.add_argument('--explored-radius', type=float, default=0.005, metavar='M',
                        help='surface within this distance (m) of a true contact counts as '
                        'explored (default 0.005)')
    parser.add_argument('--resolution', type=float, metavar='M',
                        help='cell size (m) of a PLY or cloud map (default: inferred)')
    parser.add_argument('--config', help='ROS parameter file for the registration of --bag '
                        '(registration_node section; default: the node defaults)')
    parser.add_argument('--json', type=Path, metavar='OUT', help='also write the results here')
    args = parser.parse_args(argv)
    try:
        for threshold in args.threshold:
            if not 0.0 <= threshold < 1.0:
                raise ValueError(f'--threshold {threshold:g}: must be in [0, 1)')
        if not args.explored_radius > 0:
            raise ValueError('--explored-radius must be positive')
        if args.resolution is not None and not args.resolution > 0:
            raise ValueError('--resolution must be positive')
        cells = load_map(args.map, args.resolution)
        truth_path = find_truth(args.truth, args.bag, args.map)
        truth = load_truth(truth_path)
        frame = args.frame or default_frame(truth)
        truth = in_frame(truth, frame)
        points = None
        if args.bag is not None:
            points = read_bag_points(args.bag, bag_mode_for_frame(frame), args.config)
    except (ValueError, OSError) as error:  # ParameterError is a ValueError
        print(f'map_metrics: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    results = evaluate(cells, truth, args.threshold, args.explored_radius,
                       None if points is None else points.registered)
    explored = next(iter(results['map'].values()))
    print(f'map:   {cells.describe()}')
    print(f'truth: {truth_path}: object {truth.object_name!r}, '
          f'{"static" if truth.static else "tracked"} session, '
          f'{len(truth.surface_points)} surface samples, {len(truth.contacts)} contacts, '
          f'{len(truth.stray_points)} stray points; compared in the {frame} frame')
    print(f'explored surface: {explored["explored_samples"]} of {explored["surface_samples"]} '
          f'samples ({explored["explored_samples"] / explored["surface_samples"]:.1%}) within '
          f'{args.explored_radius * 1000:g} mm of a true contact; '
          f'{explored["explored_cells"]} cells')
    if points is not None:
        stats = points.stats
        print(f'bag:   {args.bag}: {len(points.registered)} of {len(points.raw)} fingertip '
              f'positions registered ({points.mode})'
              + (f'; dropped {stats.dropped_gap} (object pose gap), '
                 f'{stats.dropped_before_object} (before the first object pose)'
                 if points.mode == 'tracked' else ''))
    warning = frame_check(cells, truth, min(args.threshold))
    if warning:
        print(f'map_metrics: warning: {warning}', file=sys.stderr)
    lowest = float(cells.probabilities.min())
    incomplete = [t for t in args.threshold if not cells.complete and t < lowest]
    if incomplete:
        print(f'map_metrics: note: the {cells.kind} holds only the cells it was saved with '
              f'(lowest probability {lowest:.3f}); threshold(s) '
              f'{", ".join(f"{t:g}" for t in incomplete)} see those cells only', file=sys.stderr)
    print()
    print('\n'.join(_table(results, [f'map > {t:g}' for t in args.threshold])))
    if args.json:
        document = {'map': str(args.map), 'map_kind': cells.kind, 'truth': str(truth_path),
                    'frame': frame, 'bag': None if args.bag is None else str(args.bag),
                    'explored_radius_mm': args.explored_radius * 1000,
                    'thresholds': results['map'], 'points': results['points']}
        try:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(_jsonable(document), indent=2) + '\n')
        except OSError as error:
            print(f'map_metrics: cannot write {args.json}: {error}', file=sys.stderr)
            return EXIT_BAD_INPUT
        print(f'\nwrote {args.json}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
