"""``map_metrics``: how close a map (and the registered points) is to the true surface.

    map_metrics MAP [--truth TRUTH.npz] [--bag BAG] [--threshold 0.8 ...]
                    [--frame object|tracker] [--explored-radius 0.005] [--json OUT]
                    [--config config/mapping.yaml [--config config/stereo.yaml]]

A map saved with fusion (its NPZ keeps the touch and vision local maps) also gets the three
maps side by side (inhand_tools/fusion_quality.py), at the highest threshold.

MAP is one of
  * an NPZ saved by the occupancy node (``occupancy/save``) or ``build_map``: every touched
    cell with its probability, so any threshold can be evaluated;
  * a PLY saved beside it (only the cells above the threshold it was saved with);
  * a bag holding a recorded ``occupancy/cloud`` (every touched cell) or
    ``occupancy/occupied`` cloud: the last message is used.

TRUTH is the simulator's ``<bag folder>.truth.npz``, or the plainer ``<bag folder>_truth.npz``
of other session generators (surface samples and true contacts, as
``../shared/data/validation_sessions`` holds; ``inhand_common/ground_truth.py``); it defaults
to the sidecar of ``--bag`` (or of MAP when MAP is a bag). The explored surface is the
surface within ``--explored-radius`` of a true contact: by default 5 mm for the simulator's
truth and 1 cm for the plainer format, as its README defines it. ``--bag`` also gives the
registered raw points: the bag's fingertip poses through the same registration as
``build_map`` (tracked for a map in the object frame, static for one in the tracker frame;
``--config`` for its parameters). The frame defaults to the tracker frame for static
sessions and the object frame otherwise.

Sessions with a stereo pair: a map with colours (``build_map ... --config
config/stereo.yaml``) and a truth with the stereo keys give the map's colour scores (how
many occupied cells are textured, of those the camera saw, paint on cells it did not see,
the colour error against the true albedo). ``--bag`` with a ``stereo_node`` ``camera_pose``
among the ``--config`` files (``config/stereo.yaml``) gives the bag's first usable stereo
shot, placed as ``build_map`` places it: its disparity against the true disparity, its
points against the true surface, and the principal point that decides which cells the
camera saw. A missing input leaves its rows out with one line saying why.

The metric definitions are in ``inhand_tools/map_quality.py`` (the map, the points, the
colours) and ``inhand_tools/stereo_quality.py`` (the stereo shot, the visible surface).

Exit status: 0 done, 2 bad input (missing or foreign file, bad option).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from inhand_common.cli_types import command_parser
from inhand_common.ground_truth import FRAMES, GroundTruth, default_frame, in_frame, load_truth
from inhand_tools.bag_points import BagPoints, bag_mode_for_frame, read_bag_points
from inhand_tools.bag_stereo_shot import BagShot, read_configured_shot
from inhand_tools.fusion_quality import fusion_scores, fusion_table
from inhand_tools.map_cells import MapCells, load_map
from inhand_tools.map_quality import (
    SurfaceTruth,
    evaluate,
    find_truth,
    frame_check,
    label_width,
    metrics_table,
    one_touch_oracle,
    surface_truth,
    touch_coverage,
    touch_recall_losses,
)
from inhand_tools.stereo_quality import (
    principal_point,
    shot_problem,
    shot_scores,
    stereo_table,
    stereo_truth_problem,
    visible_samples,
)

__all__ = ['EXIT_BAD_INPUT', 'main']

PROG = 'map_metrics'
EXIT_BAD_INPUT = 2
DEFAULT_EXPLORED = 0.005    # m: the simulator truth's explored surface


def _parser() -> argparse.ArgumentParser:
    parser = command_parser(PROG, __doc__)
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
    parser.add_argument('--explored-radius', type=float, metavar='M',
                        help='surface within this distance (m) of a true contact counts as '
                        "explored (default: the truth format's own, 0.005 for the "
                        'simulator, 0.01 for the surface-and-contacts format)')
    parser.add_argument('--resolution', type=float, metavar='M',
                        help='cell size (m) of a PLY or cloud map (default: inferred)')
    parser.add_argument('--config', action='append', default=[],
                        help='ROS parameter file for --bag: its registration_node section '
                        'registers the points, a stereo_node section (config/stereo.yaml, '
                        'camera_pose) places its stereo pair; repeatable, later files '
                        'override earlier ones (default: the node defaults)')
    parser.add_argument('--json', type=Path, metavar='OUT', help='also write the results here')
    return parser


def _check_options(args: argparse.Namespace) -> None:
    for threshold in args.threshold:
        if not 0.0 <= threshold < 1.0:
            raise ValueError(f'--threshold {threshold:g}: must be in [0, 1)')
    if args.explored_radius is not None and not args.explored_radius > 0:
        raise ValueError('--explored-radius must be positive')
    if args.resolution is not None and not args.resolution > 0:
        raise ValueError('--resolution must be positive')


@dataclass
class _Inputs:
    """What is scored: the map, the truth (in the map's frame), the bag's points and its
    stereo shot (or why there is none)."""

    cells: MapCells
    truth_path: Path
    truth: GroundTruth
    frame: str
    points: BagPoints | None
    shot: BagShot | None = None
    shot_note: str | None = None


def _read_shot(bag: Path | None, configs: list[str], mode: str, truth: GroundTruth
               ) -> tuple[BagShot | None, str | None]:
    """The bag's first usable stereo shot, placed as build_map places it (registration mode
    of the map's frame), or None and why (one line)."""
    if bag is None:
        return None, 'give --bag BAG (and --config config/stereo.yaml) for its stereo pair'
    problem = stereo_truth_problem(truth)
    if problem:
        return None, problem
    shot, why = read_configured_shot(bag, configs, {'mode': mode})
    if shot is None:
        return None, why or f'{bag} holds no stereo pair'
    return shot, shot_problem(shot, truth)


def _load_inputs(args: argparse.Namespace) -> _Inputs:
    cells = load_map(args.map, args.resolution)
    truth_path = find_truth(args.truth, args.bag, args.map)
    truth = load_truth(truth_path)
    if args.explored_radius is None:
        args.explored_radius = float(truth.settings.get('explored_radius', DEFAULT_EXPLORED))
    frame = args.frame or default_frame(truth)
    truth = in_frame(truth, frame)
    points = None
    if args.bag is not None:
        points = read_bag_points(args.bag, bag_mode_for_frame(frame), args.config)
    shot, note = _read_shot(args.bag, args.config, bag_mode_for_frame(frame), truth)
    return _Inputs(cells, truth_path, truth, frame, points, None if note else shot, note)


def _evaluate(args: argparse.Namespace, inputs: _Inputs) -> dict:
    """evaluate()'s results, the visible surface from the shot, and the shot's scores."""
    surface: SurfaceTruth = surface_truth(inputs.truth, args.explored_radius)
    visible = None
    if inputs.shot is not None:
        visible = visible_samples(inputs.truth, principal_point(inputs.shot),
                                  inputs.cells.lattice.resolution)
    results = evaluate(inputs.cells, inputs.truth, args.threshold, args.explored_radius,
                       None if inputs.points is None else inputs.points.registered,
                       surface=surface, visible=visible,
                       visible_note=f'no stereo shot: {inputs.shot_note}')
    results['stereo'] = None if inputs.shot is None else shot_scores(inputs.shot, inputs.truth,
                                                                      surface)
    results['stereo_note'] = inputs.shot_note
    results['fusion'] = (fusion_scores(args.map, surface, visible, max(args.threshold))
                         if inputs.cells.kind == 'npz' else None)
    results['touch_coverage'] = touch_coverage(surface, inputs.truth.contact_times,
                                               inputs.cells.lattice)
    results['oracle'] = one_touch_oracle(surface, inputs.cells.lattice)
    results['recall_losses'] = (touch_recall_losses(args.map, inputs.cells, surface,
                                                    max(args.threshold))
                                if results['fusion'] is None else None)
    return results


def _print_summary(args: argparse.Namespace, inputs: _Inputs, results: dict) -> None:
    """What was compared (stdout) and the warnings and notes (stderr)."""
    cells, truth, points = inputs.cells, inputs.truth, inputs.points
    explored = next(iter(results['map'].values()))
    print(f'map:   {cells.describe()}')
    print(f'truth: {inputs.truth_path}: object {truth.object_name!r}, '
          f'{"static" if truth.static else "tracked"} session, '
          f'{len(truth.surface_points)} surface samples, {len(truth.contacts)} contacts, '
          f'{len(truth.stray_points)} stray points; compared in the {inputs.frame} frame')
    print(f'explored surface: {explored["explored_samples"]} of {explored["surface_samples"]} '
          f'samples ({explored["explored_samples"] / explored["surface_samples"]:.1%}) within '
          f'{args.explored_radius * 1000:g} mm of a true contact; '
          f'{explored["explored_cells"]} cells')
    coverage = results['touch_coverage']
    print(f'touched: {coverage["once"]:.1%} of the explored surface at least once, '
          f'{coverage["twice"]:.1%} at least twice (true contacts in its cell more than '
          f'{coverage["gap_s"]:g} s apart)')
    oracle = results['oracle']
    print(f'one-touch oracle (exactly the cells holding a true contact): F@5mm '
          f'{oracle["fscore_at_5mm"]:.3f}, recall {oracle["recall_at_5mm"]:.3f}')
    losses = results['recall_losses']
    if losses is not None:
        print(f'recall lost at p > {losses["threshold"]:g}: {losses["missed"]:.1%} of the '
              f'explored surface: {losses["untouched"]:.1%} with no true contact\'s cell within '
              f'5 mm (the oracle misses it too), {losses["under_one_touch"]:.1%} whose contact '
              f'cells hold under one touch and {losses["unconfirmed"]:.1%} under '
              f'{losses["touches_needed"]:.2f} before the surface rules, '
              f'{losses["taken_by_rules"]:.1%} whose contact cells the rules took under '
              f'{losses["threshold"]:g}')
    if points is not None:
        stats = points.stats
        print(f'bag:   {args.bag}: {len(points.registered)} of {len(points.raw)} fingertip '
              f'positions registered ({points.mode})'
              + (f'; dropped {stats.dropped_gap} (object pose gap), '
                 f'{stats.dropped_before_object} (before the first object pose)'
                 if points.mode == 'tracked' else ''))
    if cells.problem:
        print(f'{PROG}: note: {args.map} is damaged: {cells.problem}',
              file=sys.stderr)
    warning = frame_check(cells, truth, min(args.threshold))
    if warning:
        print(f'{PROG}: warning: {warning}', file=sys.stderr)
    lowest = float(cells.probabilities.min())
    incomplete = [t for t in args.threshold if not cells.complete and t < lowest]
    if incomplete:
        print(f'{PROG}: note: the {cells.kind} holds only the cells it was saved with '
              f'(lowest probability {lowest:.3f}); threshold(s) '
              f'{", ".join(f"{t:g}" for t in incomplete)} see those cells only', file=sys.stderr)


def _jsonable(value):
    """``value`` with NaN and infinities as None and numpy scalars as Python ones."""
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    return value


def _write_json(args: argparse.Namespace, inputs: _Inputs, results: dict) -> None:
    document = {'map': str(args.map), 'map_kind': inputs.cells.kind,
                'truth': str(inputs.truth_path), 'frame': inputs.frame,
                'bag': None if args.bag is None else str(args.bag),
                'explored_radius_mm': args.explored_radius * 1000,
                'thresholds': results['map'], 'points': results['points'],
                'colour': results['colour'], 'colour_note': results['colour_note'],
                'seen_note': results['seen_note'], 'stereo': results['stereo'],
                'stereo_note': results['stereo_note'], 'fusion': results['fusion'],
                'touch_coverage': results['touch_coverage'], 'oracle': results['oracle'],
                'recall_losses': results['recall_losses']}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(_jsonable(document), indent=2) + '\n')


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    try:
        _check_options(args)
        inputs = _load_inputs(args)
    except (ValueError, OSError) as error:  # ParameterError and BagError are ValueErrors
        print(f'{PROG}: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    results = _evaluate(args, inputs)
    _print_summary(args, inputs, results)
    print()
    print('\n'.join(metrics_table(results, [f'map > {t:g}' for t in args.threshold])))
    stereo = stereo_table(results['stereo'], results['stereo_note'], label_width())
    if stereo:
        print()
        print('\n'.join(stereo))
    if results['fusion'] is not None:
        print()
        print('\n'.join(fusion_table(results['fusion'])))
    if args.json:
        try:
            _write_json(args, inputs, results)
        except OSError as error:
            print(f'{PROG}: cannot write {args.json}: {error}', file=sys.stderr)
            return EXIT_BAD_INPUT
        print(f'\nwrote {args.json}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
