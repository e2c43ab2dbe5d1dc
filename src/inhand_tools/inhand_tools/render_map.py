"""``render_map``: PNG pictures of a map like the paper's figures 4, 5 and 8.

    render_map MAP [--bag BAG] [--truth TRUTH.npz] --output DIR
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
  figure.png             every picture's oblique view in one figure

Each view is SIZE pixels square (two views side by side: 2 x SIZE wide). Every panel is
framed on the object, not on everything the fingertips went through (they travel far off
the object between strokes and during re-grasps): all map-frame panels show one view box,
the truth's surface with a margin (else the map's confident cells, robustly), and the raw
points their own (where most of them are); what falls outside a panel is not drawn and its
subtitle says how much ("+ 812 points outside the view"). The "up" axis of the map's
pictures is +z in the object frame (the simulator's objects stand on their +z) and -z in
the tracker frame (its z points down; also the raw points' up); --up overrides it. The
paths written are printed. Exit status: 0 done, 2 bad input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from inhand_tools import render
from inhand_tools.ground_truth import FRAMES, default_frame, in_frame, load_truth
from inhand_tools.map_metrics import (EXIT_BAD_INPUT, MapCells, bag_mode_for_frame,
                                      bag_topics, find_truth, load_map, read_bag_points)
from inhand_tools.render import OBLIQUE, SIDE, Camera

__all__ = ['main', 'regions', 'FINGER_COLOURS']

# BGR: orange, blue, green, purple, brown (fingers in finger_names order).
FINGER_COLOURS = np.array([[28, 127, 255], [180, 119, 31], [44, 160, 44], [189, 103, 148],
                           [75, 86, 140]], dtype=float)
EXPLORED_COLOUR = (1, 97, 230)     # orange (BGR)
FIRST_COLOUR = (153, 60, 94)       # purple
BASE_COLOUR = (205, 205, 205)      # light grey
STRAY_COLOUR = (40, 40, 215)       # red
SURFACE_COLOUR = (200, 200, 200)
EXPLORED_SURFACE_COLOUR = (80, 150, 60)
FRAME_LABELS = {'object': 'object frame', 'tracker': 'tracker frame (polhemus_source)',
                None: 'map frame'}


def regions(hits, first_touch, top_fraction: float = 0.1, first_fraction: float = 0.1):
    """(most explored mask, first touched mask, hit count cut, first-touch cut in seconds).

    Most explored: hit cells whose hit count reaches the top ``top_fraction`` (hits at or
    above the (1 - top_fraction) quantile of the hit cells' counts). First touched: the
    ``first_fraction`` of hit cells touched earliest (first_touch at or below that quantile).
    """
    hits = np.asarray(hits)
    first_touch = np.asarray(first_touch, dtype=float)
    hit = hits > 0
    most = np.zeros(len(hits), dtype=bool)
    first = np.zeros(len(hits), dtype=bool)
    hit_cut = first_cut = float('nan')
    if hit.any():
        hit_cut = float(np.quantile(hits[hit], 1.0 - top_fraction, method='higher'))
        most = hit & (hits >= hit_cut)
    touched = np.isfinite(first_touch)
    if touched.any():
        first_cut = float(np.quantile(first_touch[touched], first_fraction, method='lower'))
        first = touched & (first_touch <= first_cut)
    return most, first, hit_cut, first_cut


def _views(draw, camera_for, frame_label: str, first_line: str | None = None,
           views=(OBLIQUE, SIDE), title: str | None = None) -> list:
    """Panels of ``draw(camera) -> (image, note)`` for each view (oblique and side by
    default), titled with the view's name (or ``title``); the subtitle is ``first_line``
    over the note (what the panel leaves out)."""
    panels = []
    for view in views:
        camera = camera_for(view)
        image, note = draw(camera)
        panels.append(render.annotate(image, camera, title or view.name,
                                      _lines(first_line, note), frame_label))
    return panels


def _shown(camera: Camera, box: render.ViewBox, points, inset: float = 0.0) -> np.ndarray:
    """Mask of the points a panel draws: inside the view box and pictured inside the
    panel's free area (``inset`` pixels in from its edges)."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    inside = box.contains(points)
    inside[inside] = camera.in_view(points[inside], inset)
    return inside


def _write(path: Path, image: np.ndarray, written: list) -> None:
    if not cv2.imwrite(str(path), image):
        raise OSError(f'{path}: could not write the PNG')
    written.append(path)


def _splat_radius(count: int) -> float:
    """Pixels: bigger splats for sparse clouds, small ones for dense clouds."""
    return float(np.clip(2.6 * np.sqrt(3000.0 / max(count, 1)), 1.0, 2.6))


def _finger_colours(fingers: np.ndarray) -> np.ndarray:
    fingers = np.asarray(fingers, dtype=np.int64)
    return FINGER_COLOURS[np.mod(np.maximum(fingers, 0), len(FINGER_COLOURS))]


def _finger_key(names: list[str]) -> list:
    return [(tuple(int(c) for c in FINGER_COLOURS[k % len(FINGER_COLOURS)]), name)
            for k, name in enumerate(names)]


def _lines(*parts) -> str | None:
    """Subtitle lines (the empty ones dropped), or None."""
    text = '\n'.join(part for part in parts if part)
    return text or None


def _outside(inside: np.ndarray, what: str) -> str | None:
    """'+ N <what> outside the view' when some are outside, else None."""
    count = int(np.count_nonzero(~np.asarray(inside, dtype=bool)))
    return render.outside_note(count, what) if count else None


def default_up(frame: str | None) -> str:
    """The data axis that points up in the pictures of a map in ``frame``: +z in the object
    frame (the simulator's objects stand on their +z), -z in the tracker frame (its z
    points down) and when the frame is not known."""
    return 'z' if frame == 'object' else '-z'


def map_view_box(cells: MapCells, thresholds, truth=None) -> render.ViewBox:
    """What every map-frame panel shows: the object, not the strays.

    With the truth (in the map's frame): its surface's bounding box. Else a robust box of
    the centres of the cells above the highest threshold that has any (all touched cells
    if none has): their 5th-95th percentile box finds the object, the cells within 1.5 cm
    of it are its cells (so that thin extremities stay in view; a 2nd-98th percentile box
    is not enough: a few confident cells left by a stroke far from the object may be more
    than 2 % of them), and the 0.5-99.5 percentile box of those, grown by half a cell, is
    the object's. Either grown by a margin (:func:`render.default_margin`).
    """
    if truth is not None and len(truth.surface_points):
        box = render.box_of(truth.surface_points)
        if box is not None:
            return box
    resolution = cells.lattice.resolution
    centres = cells.centres
    for threshold in sorted(thresholds, reverse=True):
        above = cells.centres[cells.probabilities > threshold]
        if len(above):
            centres = above
            break
    box = render.robust_box(centres, 5.0, 95.0, reach=0.015, keep=0.5, margin=0.0)
    if box is None:
        return render.ViewBox(np.full(3, -0.01), np.full(3, 0.01))
    return box.grown(render.default_margin(box) + resolution / 2.0)


def raw_view_box(raw) -> render.ViewBox | None:
    """What the raw-point panels show (tracker frame): where most fingertip positions are
    (their 5th-95th percentile box), widened to the points within 2 cm of it, cut to
    those points' 1st-99th percentiles (the object, not the lifts and re-grasps), grown by
    a margin."""
    return render.robust_box(raw, 5.0, 95.0, reach=0.02, keep=1.0)


def draw_all(cells: MapCells, output: Path, thresholds, bag_points=None, truth=None,
             frame: str | None = None, up: str | None = None, size: int = 480,
             top_fraction: float = 0.1, first_fraction: float = 0.1,
             name: str = 'map', raw_up: str | None = None) -> list[Path]:
    """Every picture of the module docstring that the inputs allow; returns the paths.

    ``up``: the map frame's up axis (default :func:`default_up` of ``frame``); ``raw_up``:
    the tracker frame's, for the raw points (default -z, or ``up`` for a tracker-frame map).
    """
    output.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    overview: list[np.ndarray] = []
    frame_label = FRAME_LABELS.get(frame, 'map frame')
    width = 2 * size
    up = up or default_up(frame)
    raw_up = raw_up or (up if frame == 'tracker' else '-z')
    registered = None if bag_points is None else bag_points.registered
    resolution = cells.lattice.resolution
    # One view box for every map-frame picture, so they compare at a glance: the object's
    # (the truth's surface, or the map's confident cells), not everything the fingertips
    # went through; what lies outside is left out and counted in the subtitles.
    box = map_view_box(cells, thresholds, truth)
    cell_box = box.grown(resolution / 2.0)  # a cell is drawn if its cube reaches the box

    def map_camera(view):
        return Camera.for_box(view, box, size, up)

    if bag_points is not None and len(bag_points.raw):
        raw_box = raw_view_box(bag_points.raw)
        raw_colours = _finger_colours(bag_points.raw_fingers)
        raw_radius_px = _splat_radius(np.count_nonzero(raw_box.contains(bag_points.raw)))

        def raw_camera(view):
            return Camera.for_box(view, raw_box, size, raw_up)

        def draw_raw(cam):
            shown = _shown(cam, raw_box, bag_points.raw)
            return (render.render_points(cam, bag_points.raw[shown], raw_colours[shown],
                                         raw_radius_px), _outside(shown, 'points'))

        panels = _views(draw_raw, raw_camera, FRAME_LABELS['tracker'])
        footer = render.key_legend(width, _finger_key(bag_points.finger_names))
        _write(output / 'raw_points.png', render.titled(
            render.hstack(panels), f'Raw fingertip positions ({len(bag_points.raw):,} points, '
            'tracker frame)', footer), written)
        overview += _views(draw_raw, raw_camera, FRAME_LABELS['tracker'],
                           f'{len(bag_points.raw):,} fingertip positions', (OBLIQUE,),
                           'raw points')
    if registered is not None and len(registered):
        reg_colours = _finger_colours(bag_points.registered_fingers)
        in_box = registered[box.contains(registered)]
        reg_radius_px = _splat_radius(len(np.unique(np.round(in_box, 4), axis=0)))

        def draw_registered(cam):
            shown = _shown(cam, box, registered)
            return (render.render_points(cam, registered[shown], reg_colours[shown],
                                         reg_radius_px), _outside(shown, 'points'))

        panels = _views(draw_registered, map_camera, frame_label)
        footer = render.key_legend(width, _finger_key(bag_points.finger_names))
        _write(output / 'registered_points.png', render.titled(
            render.hstack(panels), f'Registered fingertip positions ({len(registered):,} '
            f'points, {bag_points.mode} registration, {frame_label})', footer), written)
        overview += _views(draw_registered, map_camera, frame_label,
                           f'{len(registered):,} points, {bag_points.mode} registration',
                           (OBLIQUE,), 'registered points')

    def cell_drawer(centres, colours):
        """draw(camera) of the cells at ``centres``: those whose cubes reach into the view
        box and whose centres are pictured in the panel's free area."""
        def draw(cam):
            # The whole cube in the free area: its centre well inside.
            shown = _shown(cam, cell_box, centres, 0.6 * resolution * cam.scale)
            return (render.render_cells(cam, centres[shown], resolution, colours[shown]),
                    _outside(shown, 'cells'))
        return draw

    threshold_panels = []
    lowest = float(cells.probabilities.min())
    for threshold in thresholds:
        keep = cells.probabilities > threshold
        draw = cell_drawer(cells.centres[keep],
                           render.probability_colours(cells.probabilities[keep]))
        note = f'{np.count_nonzero(keep)} cells'
        if not cells.complete and threshold < lowest:
            note += f' (file holds only p > {lowest:.2f})'
        panels = _views(draw, map_camera, frame_label, note)
        _write(output / f'map_above_{threshold:g}.png', render.titled(
            render.hstack(panels), f'Probabilistic map: cells with probability > {threshold:g} '
            f'({note})', render.probability_legend(width, thresholds=tuple(
                t for t in thresholds if 0 < t < 1))), written)
        threshold_panels += _views(draw, map_camera, frame_label, note, (OBLIQUE,),
                                   f'map, p > {threshold:g}')
    _write(output / 'map_thresholds.png', render.grid_figure(
        threshold_panels, len(threshold_panels),
        f'Probabilistic map at thresholds {", ".join(f"> {t:g}" for t in thresholds)} '
        '(oblique view)', render.probability_legend(size * len(threshold_panels),
                                                    tuple(t for t in thresholds if 0 < t < 1))),
        written)
    overview.extend(threshold_panels)

    # Most explored and first touched regions over the occupied map.
    most, first, hit_cut, first_cut = regions(cells.hits, cells.first_touch, top_fraction,
                                              first_fraction)
    base_threshold = max(t for t in thresholds) if thresholds else 0.8
    show = (cells.probabilities > base_threshold) | most | first
    colours = np.tile(np.array(BASE_COLOUR, dtype=float), (len(cells.centres), 1))
    colours[most] = EXPLORED_COLOUR
    colours[first] = FIRST_COLOUR
    keys = [(BASE_COLOUR, f'map, p > {base_threshold:g}')]
    if np.isfinite(hit_cut):
        keys.append((EXPLORED_COLOUR, f'most explored: top {top_fraction:.0%} hit counts '
                                      f'(>= {hit_cut:g} hits, {np.count_nonzero(most)} cells)'))
    if np.isfinite(first_cut):
        keys.append((FIRST_COLOUR, f'first touched: earliest {first_fraction:.0%} '
                                   f'(first {first_cut:.2f} s, {np.count_nonzero(first)} cells)'))
    # Highlighted cells are drawn whatever their probability (a first touch may be one hit).
    draw = cell_drawer(cells.centres[show], colours[show])
    subtitle = None if np.isfinite(hit_cut) else 'the map has no hit counts'
    panels = _views(draw, map_camera, frame_label, subtitle)
    _write(output / 'regions.png', render.titled(
        render.hstack(panels), 'Most explored region and first region touched',
        render.key_legend(width, keys)), written)
    overview += _views(draw, map_camera, frame_label, 'orange: most hits, purple: first',
                       (OBLIQUE,), 'most explored / first touched')

    if truth is not None:
        step = max(1, len(truth.surface_points) // 60000)
        surface = truth.surface_points[::step]
        from inhand_tools.metrics import explored_mask
        explored = explored_mask(surface, truth.contacts, 0.005)
        colours = np.where(explored[:, None], np.array(EXPLORED_SURFACE_COLOUR, dtype=float),
                           np.array(SURFACE_COLOUR, dtype=float))
        normals = truth.surface_normals[::step]

        def draw_truth(cam):
            # Lambert shading from the surface normals (facing away: as dim as the dimmest);
            # the strays in view drawn with the surface (z-buffered: the object hides those
            # behind it).
            light = np.clip(normals @ cam.light_in_data(), 0.0, 1.0)
            shaded = colours * (0.55 + 0.45 * light)[:, None]
            shown = _shown(cam, box, truth.stray_points)
            points = np.concatenate([surface, truth.stray_points[shown]])
            point_colours = np.concatenate([shaded, np.tile(np.array(STRAY_COLOUR, float),
                                                            (np.count_nonzero(shown), 1))])
            return (render.render_points(cam, points, point_colours, 1.5, 0.0),
                    _outside(shown, 'stray points'))

        panels = _views(draw_truth, map_camera, frame_label,
                        f'{len(truth.stray_points)} stray points')
        keys = [(SURFACE_COLOUR, 'true surface'),
                (EXPLORED_SURFACE_COLOUR, 'explored (within 5 mm of a true contact)'),
                (STRAY_COLOUR, 'stray fingertip positions')]
        _write(output / 'truth.png', render.titled(
            render.hstack(panels), f'Ground truth: {truth.object_name} ({frame_label})',
            render.key_legend(width, keys)), written)
        overview += _views(draw_truth, map_camera, frame_label, 'green: explored, red: strays',
                           (OBLIQUE,), 'ground truth')

    columns = {1: 1, 2: 2, 3: 3, 4: 2, 5: 3, 6: 3}.get(len(overview), 4)
    _write(output / 'figure.png', render.grid_figure(
        overview, columns, f'{name}: raw data, registration and probabilistic map'
        if bag_points is not None else f'{name}: probabilistic map',
        render.probability_legend(size * columns, tuple(t for t in thresholds if 0 < t < 1))),
        written)
    return written


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='render_map', description=__doc__.split('\n\n')[0],
                                     epilog=__doc__.split('\n\n', 1)[1],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('map', type=Path, help='map: NPZ, PLY, or a bag with an occupancy cloud')
    parser.add_argument('--output', type=Path, required=True, help='folder for the PNGs')
    parser.add_argument('--bag', type=Path, help='session bag: raw and registered points')
    parser.add_argument('--truth', help='simulator truth file (default: the bag\'s sidecar '
                        'BAG.truth.npz, if there is one)')
    parser.add_argument('--thresholds', type=float, nargs='+', default=[0.0, 0.6, 0.8],
                        help='probability thresholds of the map pictures (default 0 0.6 0.8)')
    parser.add_argument('--frame', choices=FRAMES, help='frame the map is in (default: from '
                        'the truth; else object if the bag has an object sensor)')
    parser.add_argument('--up', choices=sorted(render.UP_AXES),
                        help='axis of the map frame that points up in the pictures (default: '
                        'z in the object frame, -z in the tracker frame or an unknown one)')
    parser.add_argument('--size', type=int, default=480, help='pixels per view (default 480)')
    parser.add_argument('--top-fraction', type=float, default=0.1,
                        help='most explored = this fraction of cells with the most hits')
    parser.add_argument('--first-fraction', type=float, default=0.1,
                        help='first touched = this fraction of cells touched earliest')
    parser.add_argument('--resolution', type=float, metavar='M',
                        help='cell size (m) of a PLY or cloud map (default: inferred)')
    parser.add_argument('--config', help='ROS parameter file for the registration of --bag')
    args = parser.parse_args(argv)
    try:
        if not 120 <= args.size <= 4000:
            raise ValueError(f'--size {args.size}: must be between 120 and 4000 pixels')
        for threshold in args.thresholds:
            if not 0.0 <= threshold < 1.0:
                raise ValueError(f'--thresholds {threshold:g}: must be in [0, 1)')
        for option in ('top_fraction', 'first_fraction'):
            if not 0.0 < getattr(args, option) <= 1.0:
                raise ValueError(f'--{option.replace("_", "-")} must be in (0, 1]')
        cells = load_map(args.map, args.resolution)
        truth = None
        try:
            truth_path = find_truth(args.truth, args.bag, args.map)
        except ValueError:
            truth_path = None  # the truth is optional here
        if truth_path is not None:
            truth = load_truth(truth_path)
        frame = args.frame or (default_frame(truth) if truth is not None else None)
        bag_points = None
        if args.bag is not None:
            if frame is None:
                topics = bag_topics(args.bag)
                frame = 'object' if 'polhemus/object/pose' in topics else 'tracker'
            bag_points = read_bag_points(args.bag, bag_mode_for_frame(frame), args.config)
        if truth is not None:
            truth = in_frame(truth, frame or 'object')
        written = draw_all(cells, args.output, sorted(args.thresholds), bag_points, truth,
                           frame, args.up, args.size, args.top_fraction, args.first_fraction,
                           args.map.name.rsplit('.', 1)[0] or 'map')
    except (ValueError, OSError) as error:
        print(f'render_map: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f'render_map: {cells.describe()}')
    for path in written:
        print(path)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
