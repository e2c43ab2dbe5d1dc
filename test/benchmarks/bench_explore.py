#!/usr/bin/env python3
"""Guided exploration against random and coverage-greedy, and the completed surface.

    .venv/bin/python test/benchmarks/bench_explore.py [--objects box,cat,cup,duck]
        [--modes static,tracked] [--explorers random,guided,greedy] [--seeds 2,3]
        [--strokes 10,20,30,40,60,80] [--duration 160] [--jobs 2] [--quick] [--keep DIR]
        [--hand NAME=VALUE ...] [--no-validation] [--no-cost]
    .venv/bin/python test/benchmarks/bench_explore.py --compare DIR[,DIR] [SPEC ...]
    .venv/bin/python test/benchmarks/bench_explore.py --camera [--keep DIR]

Each session: ``simulate_session`` at 30 Hz, 5 cm/s with ``--explorer`` random (the simulated
person), guided (the next touches of the predicted surface) or greedy (the stroke start
farthest from everything touched). After the first 10, 20, ... strokes (the session cut at the
end of that stroke) the bag is mapped by ``build_map`` with the shipped configuration and
scored against the **whole** true surface (not only the explored part):

* ``map F``: F@5mm of the occupied cells (threshold 0.8);
* ``completed F``: F@5mm of the completed surface (``predict_surface``'s
  ``NAME_completed.ply``: the predicted surface within ``completed_reach`` of the touched
  cells, sampled by area) with the shipped prediction settings; ``predicted F`` the same of
  the whole predicted surface (``NAME_predicted.ply``);
* ``2 sigma``: the share of the completed surface (by area) whose distance to the true
  surface is within twice its predicted standard deviation (calibration, target 90 %);
* ``ms``: the time of the prediction.

``--compare`` scores alternative prediction settings on kept maps instead (how the shipped
ones were chosen: docs/exploration.md). Then the same prediction on the independent
generator's sessions (``../shared/data/
validation_sessions``, a check, never tuned on; skipped with a line when absent).

``--camera``: the completed surface with what a camera saw (``predict_surface --bag``): the
texture benchmark's sessions (bench_texture_sessions.py: ``tune``, where the camera's
settings were chosen, then ``report``), each with one stereo pair before a 90 s exploration;
their touch maps cut after 15, 30 and 60 s and whole, the completed surface's F against the
whole true surface without and with the object's stereo points.

The summary gives, per object and mode, the strokes each explorer needs for map F >= 0.8
(interpolated between the checkpoints; '>N' when not reached), guided's saving against random
(target: >= 30 %), and the completed surface's F at 20 strokes against the map's (target:
+0.1), each averaged over the seeds. Then the prediction's cost with 5,000 contacts.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import math
import shutil
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from inhand_shape.superquadric import area_samples

WORKSPACE = Path(__file__).resolve().parents[2]
CONFIG = WORKSPACE / 'config'
TARGET_F = 0.8


def _map_f(centres: np.ndarray, probabilities: np.ndarray, whole) -> float:
    """F@5mm of the map's occupied cells (p >= 0.8) against ``whole`` (a SurfaceTruth)."""
    from inhand_tools.map_quality import point_metrics
    return float(point_metrics(centres[probabilities >= 0.8], whole)['fscore_at_5mm'])


def surface_scores(surface, whole, rng: np.random.Generator, samples: int = 20000) -> dict:
    """A predicted or completed surface against ``whole`` (a SurfaceTruth): ``f``, its F@5mm
    (``samples`` points by area); ``within`` and ``within_one``, the share of its area whose
    distance to the true surface is within 2 and 1 standard deviations; ``spread``, its
    area-weighted mean standard deviation (m). An empty surface: F 0, the rest NaN."""
    from inhand_tools.map_quality import point_metrics
    if surface.empty:
        return {'f': 0.0, 'within': math.nan, 'within_one': math.nan, 'spread': math.nan}
    points = area_samples(surface.vertices, surface.faces, samples, rng)
    error, _ = whole.distance(surface.vertices)
    areas = surface.vertex_areas()
    return {'f': float(point_metrics(points, whole)['fscore_at_5mm']),
            'within': float(areas[error <= 2 * surface.vertex_std].sum() / areas.sum()),
            'within_one': float(areas[error <= surface.vertex_std].sum() / areas.sum()),
            'spread': float((areas * surface.vertex_std).sum() / areas.sum())}


def _truth_in_map_frame(truth_path: Path, static: bool):
    from inhand_common.ground_truth import in_frame, load_truth
    truth = load_truth(truth_path)
    return in_frame(truth, 'tracker') if static else truth


def run_session(job: tuple) -> list[dict]:
    """Every checkpoint of one (object, mode, explorer, seed) session."""
    name, static, explorer, seed, checkpoints, duration, folder, hand = job
    from inhand_common.ground_truth import write_truth
    from inhand_shape.implicit_surface import predict_map_surface
    from inhand_sim.exploration import ExplorationSettings, speed_range_around
    from inhand_sim.session import SessionSettings, simulate, write_bag
    from inhand_tools.commands.build_map import main as build_map
    from inhand_tools.map_cells import load_map
    from inhand_tools.map_quality import SurfaceTruth
    rng = np.random.default_rng(seed)
    settings = SessionSettings(object_name=name, static=static, rate=30.0, duration=duration,
                               seed=seed, exploration=replace(
                                   ExplorationSettings(speed_range=speed_range_around(0.05)),
                                   explorer=explorer, **dict(hand)))
    started = time.perf_counter()
    session = simulate(settings)
    simulate_s = time.perf_counter() - started
    tag = f'{name}_{"static" if static else "tracked"}_{explorer}_{seed}'
    truth_file = Path(folder) / f'{tag}.truth.npz'
    write_truth(truth_file, session.truth)
    truth = _truth_in_map_frame(truth_file, static)
    whole = SurfaceTruth(truth.surface_points, truth.surface_points)
    ends = sorted(t1 for _, kind, _, t1 in session.exploration.events if kind == 'stroke')
    config = CONFIG / ('mapping_static.yaml' if static else 'mapping.yaml')
    rows = []
    for count in checkpoints:
        if count > len(ends):
            break
        frames = int(np.searchsorted(session.exploration.times, ends[count - 1], side='right'))
        cut = replace(session, stamps_ns=session.stamps_ns[:frames], poses=session.poses[:, :frames])
        bag = Path(folder) / f'{tag}_{count}'
        shutil.rmtree(bag, ignore_errors=True)  # a --keep folder of an earlier run: this run's session
        write_bag(cut, bag)
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            build_map([str(bag), '--config', str(config), '--output-dir', str(folder), '--quiet',
                       '--force'])
        cells = load_map(Path(folder) / f'{bag.name}.npz')
        row = {'object': name, 'mode': 'static' if static else 'tracked', 'explorer': explorer,
               'seed': seed, 'strokes': count, 'seconds': float(ends[count - 1]),
               'map_f': _map_f(cells.centres, cells.probabilities, whole), 'simulate_s': simulate_s}
        start = time.perf_counter()
        surface = predict_map_surface(cells.centres, cells.probabilities, cells.lattice.resolution)
        row['predict_ms'] = 1000 * (time.perf_counter() - start)
        completed = surface_scores(surface.completed(), whole, rng)
        row.update(completed_f=completed['f'], calibrated=completed['within'],
                   predicted_f=surface_scores(surface, whole, rng)['f'])
        rows.append(row)
    return rows


def strokes_to(rows: list[dict], key: str, target: float) -> float:
    """Strokes at which ``key`` first reaches ``target``, linearly interpolated between
    checkpoints; inf when it never does."""
    previous = (0, 0.0)
    for row in rows:
        if row[key] >= target:
            n0, f0 = previous
            n1, f1 = row['strokes'], row[key]
            return n0 + (target - f0) / max(f1 - f0, 1e-9) * (n1 - n0)
        previous = (row['strokes'], row[key])
    return math.inf


def _print_rows(rows: list[dict]) -> None:
    for row in rows:
        print(f"{row['object']:7} {row['mode']:7} {row['explorer']:7} seed {row['seed']}  "
              f"{row['strokes']:3d} strokes {row['seconds']:6.1f} s  map F {row['map_f']:.3f}  "
              f"completed F {row['completed_f']:.3f}  2 sigma {row['calibrated']:.2f}  "
              f"predicted F {row['predicted_f']:.3f}  "
              f"{row['predict_ms']:5.0f} ms", flush=True)


def summary(results: dict, explorers: list[str]) -> None:
    """Per object and mode: strokes to F >= 0.8 by explorer, guided's saving, the completed
    surface at 20 strokes."""
    print('\n# strokes to map F >= 0.8 of the whole surface (mean over seeds; inf: not reached)')
    groups = sorted({(k[0], k[1]) for k in results})
    savings, gains, whole_gains, calibration = [], [], [], []
    for name, mode in groups:
        line = f'{name:7} {mode:7}'
        need = {}
        for explorer in explorers:
            values = [strokes_to(rows, 'map_f', TARGET_F) for key, rows in results.items()
                      if key[:3] == (name, mode, explorer)]
            need[explorer] = float(np.mean(values)) if values else math.nan
            line += f'  {explorer} {need[explorer]:5.1f}'
        if 'guided' in need and 'random' in need and math.isfinite(need['random']):
            saving = 1 - need['guided'] / need['random']
            savings.append(saving)
            line += f'  guided saves {100 * saving:4.0f} % ({"PASS" if saving >= 0.3 else "FAIL"} >= 30 %)'
        print(line)
        for key, rows in results.items():
            if key[:2] == (name, mode):
                at20 = [r for r in rows if r['strokes'] == 20]
                if at20:
                    gains.append(at20[0]['completed_f'] - at20[0]['map_f'])
                    whole_gains.append(at20[0]['predicted_f'] - at20[0]['map_f'])
                calibration.extend(r['calibrated'] for r in rows if math.isfinite(r['calibrated']))
    if gains:
        print(f'\n# completed surface F - map F at 20 strokes: mean {np.mean(gains):+.3f}, worst '
              f'{min(gains):+.3f} (target >= +0.10 on every session: '
              f'{"PASS" if min(gains) >= 0.1 else "FAIL"}, {sum(g >= 0.1 for g in gains)}/{len(gains)}); '
              f'the whole predicted surface: mean {np.mean(whole_gains):+.3f}, worst '
              f'{min(whole_gains):+.3f}, >= +0.10 on {sum(g >= 0.1 for g in whole_gains)}/{len(whole_gains)}')
    if calibration:
        print(f'# true error within 2 sigma: median {np.median(calibration):.2f}, worst '
              f'{min(calibration):.2f} of the surface (target >= 0.90: '
              f'{sum(c >= 0.9 for c in calibration)}/{len(calibration)} maps)')
    if savings:
        print(f'# guided against random: {sum(s >= 0.3 for s in savings)}/{len(savings)} '
              f'object x mode reach F {TARGET_F} in >= 30 % fewer strokes')


def cost(contacts: int = 5000, runs: int = 5) -> None:
    """The prediction and the next touches from ``contacts`` occupied cells (a sphere's
    surface, 4,000 free cells around it): the first one, which fits the prior superquadric,
    and an update, which keeps it (as the exploration node does until the cells grow by a
    quarter)."""
    from inhand_shape.implicit_surface import predict_surface
    from inhand_shape.next_touch import next_touches
    rng = np.random.default_rng(0)
    direction = rng.normal(size=(contacts * 3, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    cells = np.unique(np.round(0.1 * direction / 0.005), axis=0)[:contacts] * 0.005
    free = np.unique(np.round(0.12 * direction / 0.005), axis=0)[:4000] * 0.005
    first, update, touch_times = [], [], []
    for _ in range(runs):
        start = time.perf_counter()
        surface = predict_surface(cells, 0.005, free)
        first.append(time.perf_counter() - start)
        start = time.perf_counter()
        surface = predict_surface(cells, 0.005, free, prior=surface.prior)
        update.append(time.perf_counter() - start)
        start = time.perf_counter()
        next_touches(surface, 0.005)
        touch_times.append(time.perf_counter() - start)
    total = np.median(update) + np.median(touch_times)
    print(f'\n# cost, {len(cells):,} occupied cells + {len(free):,} free cells: first prediction '
          f'(prior fitted) {1000 * np.median(first):.0f} ms; an update (prior kept) '
          f'{1000 * np.median(update):.0f} ms + next touches {1000 * np.median(touch_times):.0f} ms '
          f'= {1000 * total:.0f} ms ({"PASS" if total <= 0.2 else "FAIL"} <= 200 ms)')


VALIDATION = WORKSPACE.parent / 'shared' / 'data' / 'validation_sessions'


def validation_check(folder: Path) -> None:
    """The completed surface on the independent generator's sessions (a check, never tuned
    on): each mapped by build_map with the shipped files, then predicted with the shipped
    settings, against its whole true surface."""
    from inhand_common.ground_truth import load_truth
    from inhand_shape.implicit_surface import predict_map_surface
    from inhand_tools.commands.build_map import main as build_map
    from inhand_tools.map_cells import load_map
    from inhand_tools.map_quality import SurfaceTruth
    bags = sorted(p for p in VALIDATION.glob('*') if p.is_dir()) if VALIDATION.is_dir() else []
    if not bags:
        print(f'\n# validation sessions: none at {VALIDATION} (skipped)')
        return
    print(f'\n# the independent generator\'s sessions ({VALIDATION}), whole true surface:')
    rng = np.random.default_rng(0)
    gains, calibration = [], []
    for bag in bags:
        truth = load_truth(VALIDATION / f'{bag.name}_truth.npz')
        config = CONFIG / ('mapping_static.yaml' if truth.static else 'mapping.yaml')
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            build_map([str(bag), '--config', str(config), '--output-dir', str(folder), '--quiet', '--force'])
        cells = load_map(Path(folder) / f'{bag.name}.npz')
        whole = SurfaceTruth(truth.surface_points, truth.surface_points)
        map_f = _map_f(cells.centres, cells.probabilities, whole)
        surface = predict_map_surface(cells.centres, cells.probabilities, cells.lattice.resolution)
        completed = surface_scores(surface.completed(), whole, rng)
        predicted_f = surface_scores(surface, whole, rng)['f']
        gains.append(completed['f'] - map_f)
        calibration.append(completed['within'])
        print(f'{bag.name:32} map F {map_f:.3f}  completed F {completed["f"]:.3f}  2 sigma '
              f'{completed["within"]:.2f}  predicted F {predicted_f:.3f}', flush=True)
    print(f'# completed - map F: mean {np.mean(gains):+.3f}, worst {min(gains):+.3f}; within 2 sigma: '
          f'median {np.median(calibration):.2f}, worst {min(calibration):.2f}')


def compare(folders: list[Path], specs: list[str]) -> None:
    """Alternative prediction settings side by side on the maps kept in ``folders`` (by
    ``--keep``): each spec is NAME=VALUE pairs joined by commas (PredictionSettings fields, or
    an upper-case constant of implicit_surface.py); each kind of prior is fitted once per map.
    Besides the completed surface over all the maps, the issue's figure: at 20 strokes, the
    completed surface's F minus the map's."""
    import inhand_shape.implicit_surface as implicit
    from inhand_tools.map_cells import load_map
    from inhand_tools.map_quality import SurfaceTruth
    maps, strokes = [], []
    for folder in folders:
        for path in sorted(folder.glob('*_[0-9]*_[0-9]*.npz')):
            tag, count = path.stem.rsplit('_', 1)
            truth = _truth_in_map_frame(folder / f'{tag}.truth.npz', '_static_' in tag)
            maps.append((load_map(path), SurfaceTruth(truth.surface_points, truth.surface_points)))
            strokes.append(int(count))
    print(f'# {len(maps)} maps from {", ".join(map(str, folders))}')
    twenty = {i: _map_f(c.centres, c.probabilities, whole)      # the 20-stroke maps' own F
              for i, ((c, whole), count) in enumerate(zip(maps, strokes)) if count == 20}
    priors: dict[str, list] = {}      # kind -> the fitted prior of each map
    defaults = {name: getattr(implicit, name) for name in dir(implicit) if name.isupper()}

    def restore() -> None:
        for name, value in defaults.items():
            setattr(implicit, name, value)
    rng = np.random.default_rng(0)
    for spec in specs:
        pairs = dict(item.split('=', 1) for item in spec.split(',') if item)
        kind = pairs.get('prior', implicit.PredictionSettings().prior)
        if kind not in priors:      # fitted with the module's own constants
            restore()
            priors[kind] = [implicit.predict_map_surface(
                c.centres, c.probabilities, c.lattice.resolution,
                implicit.PredictionSettings(prior=kind)).prior for c, _ in maps]
        for name, value in defaults.items():
            setattr(implicit, name, type(value)(float(pairs.pop(name))) if name in pairs else value)
        settings = implicit.PredictionSettings(**{k: v if k == 'prior' else float(v)
                                                  for k, v in pairs.items()})
        scores, within, within_one, spread = [], [], [], []
        for (cells, whole), prior in zip(maps, priors[kind]):
            surface = implicit.predict_map_surface(
                cells.centres, cells.probabilities, cells.lattice.resolution, settings,
                prior=prior)
            score = surface_scores(surface.completed(), whole, rng, 10000)
            scores.append(score['f'])
            within.append(score['within'])
            within_one.append(score['within_one'])
            spread.append(score['spread'])
        # within one sigma and the mean std: a std calibrated only by being wide shows here
        print(f'{spec or "(shipped)":45} completed F mean {np.mean(scores):.3f} worst {min(scores):.3f}; '
              f'within 2 sigma worst {min(within):.2f}, >= 0.9 on {sum(w >= 0.9 for w in within)}/'
              f'{len(within)}; within 1 sigma median {np.median(within_one):.2f}, mean std '
              f'{1000 * np.median(spread):.1f} mm', flush=True)
        gains = [scores[i] - f for i, f in twenty.items()]
        if gains:
            print(f'{"":45} at 20 strokes: completed - map F mean {np.mean(gains):+.3f}, worst '
                  f'{min(gains):+.3f}, >= +0.10 on {sum(g >= 0.10 for g in gains)}/{len(gains)}',
                  flush=True)
    restore()


CAMERA_CUTS = (15.0, 30.0, 60.0, math.inf)   # s of exploration the touch map is cut after


def camera_check(folder: Path) -> None:
    """``--camera`` (module doc)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_texture_sessions import SETS, camera_file, session

    from inhand_common.ground_truth import in_frame, load_truth
    from inhand_mapping.bag_mapping import BagRegistration
    from inhand_mapping.mapping_config import load_parameters
    from inhand_shape.implicit_surface import predict_map_surface
    from inhand_tools.commands.predict_surface import camera_points
    from inhand_tools.map_quality import SurfaceTruth
    labels = [f'{c:g} s' if math.isfinite(c) else 'whole' for c in CAMERA_CUTS]
    for set_name in ('tune', 'report'):
        gains: dict[str, list[tuple[float, float, float]]] = {label: [] for label in labels}
        print(f'# {set_name}: map F | completed F without -> with the camera, per cut', flush=True)
        for name, options in SETS[set_name].items():
            bag = session(name, options, folder)
            truth = load_truth(f'{bag}.truth.npz')
            configs = [str(CONFIG / ('mapping_static.yaml' if truth.static else 'mapping.yaml')),
                       str(CONFIG / 'stereo.yaml'), str(camera_file(bag, truth, folder))]
            truth = in_frame(truth, 'tracker' if truth.static else 'object')
            whole = SurfaceTruth(truth.surface_points, truth.surface_points)
            registration, occupancy = load_parameters(configs, {})
            seen, _ = camera_points(bag, configs, registration.mode)
            assert seen is not None, f'{bag}: no stereo pair'
            chunks = [c for c in BagRegistration(bag, registration, False) if len(c[1])]
            start = min(float(c[1].min()) for c in chunks)
            line = f'{name:8s}'
            for cut, label in zip(CAMERA_CUTS, labels):
                grid = occupancy.make_grid()
                for points, times, fingers in chunks:
                    keep = times < start + cut
                    if keep.any():
                        grid.integrate(points[keep], times[keep], fingers[keep])
                grid.flush()
                centres, probabilities, _, _ = grid.cells()
                map_f = _map_f(centres, probabilities, whole)
                completed = []
                for camera in (None, seen):
                    surface = predict_map_surface(
                        centres, probabilities, occupancy.grid.resolution,
                        seen=None if camera is None else camera[0],
                        seen_from=None if camera is None else camera[1])
                    completed.append(surface_scores(surface.completed(), whole,
                                                    np.random.default_rng(0))['f'])
                gains[label].append((map_f, completed[0], completed[1]))
                line += f' | {label}: {map_f:.3f} | {completed[0]:.3f} -> {completed[1]:.3f}'
            print(line, flush=True)
        for label, rows in gains.items():
            r = np.array(rows)
            print(f'# {set_name}, {label}: map F {r[:, 0].mean():.3f}, completed F {r[:, 1].mean():.3f} '
                  f'-> with the camera {r[:, 2].mean():.3f} (each session {np.min(r[:, 2] - r[:, 1]):+.3f} '
                  f'to {np.max(r[:, 2] - r[:, 1]):+.3f})', flush=True)


def _hand_setting(text: str) -> tuple[str, object]:
    from inhand_sim.exploration import parse_hand_setting
    try:
        return parse_hand_setting(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--objects', default='box,cat,cup,duck')
    parser.add_argument('--modes', default='static,tracked')
    parser.add_argument('--explorers', default='random,guided,greedy')
    # seed 1 is where the prediction's settings were chosen (docs/exploration.md): not reported
    parser.add_argument('--seeds', default='2,3')
    parser.add_argument('--strokes', default='10,20,30,40,60,80')
    parser.add_argument('--duration', type=float, default=160.0)
    parser.add_argument('--jobs', type=int, default=2)
    parser.add_argument('--quick', action='store_true', help='box and cat, static, one seed')
    parser.add_argument('--no-cost', action='store_true')
    parser.add_argument('--keep', type=Path, help='keep the bags, truths and maps in this folder')
    parser.add_argument('--hand', action='append', default=[], metavar='NAME=VALUE',
                        type=_hand_setting, help='another hand (simulate_session --hand)')
    parser.add_argument('--compare', nargs='+', metavar=('DIRS', 'SPEC'),
                        help='instead of sessions: score prediction settings on the maps kept in '
                        'DIRS (comma-separated --keep folders), one SPEC per line of output '
                        '(NAME=VALUE,...; "" the shipped settings)')
    parser.add_argument('--camera', action='store_true',
                        help="instead of sessions: the completed surface with a stereo pair's "
                        'points, on the texture benchmark\'s sessions')
    parser.add_argument('--no-validation', action='store_true',
                        help="skip the check on ../shared/data/validation_sessions")
    args = parser.parse_args()
    if args.compare:
        compare([Path(p) for p in args.compare[0].split(',')], args.compare[1:] or [''])
        return 0
    if args.camera:
        with contextlib.ExitStack() as stack:
            folder = args.keep or Path(stack.enter_context(
                tempfile.TemporaryDirectory(prefix='bench_explore_camera_')))
            folder.mkdir(parents=True, exist_ok=True)
            camera_check(folder)
        return 0
    if args.quick:
        args.objects, args.modes, args.seeds = 'box,cat', 'static', '1'
    objects, modes = args.objects.split(','), args.modes.split(',')
    explorers = args.explorers.split(',')
    seeds = [int(s) for s in args.seeds.split(',')]
    checkpoints = [int(s) for s in args.strokes.split(',')]
    with contextlib.ExitStack() as stack:
        if args.keep is not None:
            args.keep.mkdir(parents=True, exist_ok=True)
            folder = str(args.keep)
        else:
            folder = stack.enter_context(tempfile.TemporaryDirectory(prefix='bench_explore_'))
        jobs = [(name, mode == 'static', explorer, seed, checkpoints, args.duration, folder, args.hand)
                for name in objects for mode in modes for seed in seeds for explorer in explorers]
        print(f'# {len(jobs)} sessions ({args.duration:g} s, 30 Hz, 5 cm/s), {args.jobs} at a time',
              flush=True)
        results = {}
        started = time.monotonic()
        with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            for job, rows in zip(jobs, pool.map(run_session, jobs)):
                results[(job[0], 'static' if job[1] else 'tracked', job[2], job[3])] = rows
                _print_rows(rows)
                print(f'#   {len(results)}/{len(jobs)} sessions, {time.monotonic() - started:.0f} s',
                      flush=True)
        summary(results, explorers)
        if not args.no_validation:
            validation_check(Path(folder))
    if not args.no_cost:
        cost()
    return 0


if __name__ == '__main__':
    sys.exit(main())
