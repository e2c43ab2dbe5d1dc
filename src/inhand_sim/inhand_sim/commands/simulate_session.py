"""``simulate_session``: write a simulated exploration session as a bag plus ground truth.

    simulate_session --object NAME|MESH_FILE [--mesh-scale S] [--mesh-up z]
                     --static|--moving [--regrasp/--no-regrasp] [--second-object-sensor]
                     --rate 15|30|120|240 --duration SECONDS --seed N [--speed CM_PER_S]
                     [--lifts continuous|between-frames] [--noise-mm 1.0]
                     [--hand NAME=VALUE ...] [--explorer random|guided|greedy]
                     [--tip-offset-mm X Y Z ...] [--pad-radius-mm R] [--finger-roll-deg D]
                     --output bags/NAME [--force] [--quiet]

``--object``: a built-in object (cat, bottle, mug), a mesh this package ships (cup, animal,
duck) or a mesh file (OBJ, STL, PLY; ``--mesh-scale`` metres per file unit, ``--mesh-up``
its up axis); see :mod:`inhand_sim.catalogue`. A mesh that cannot be an object (unreadable,
not watertight, too small or large) is refused with the reason in one line.

Writes the bag folder ``bags/NAME/`` (MCAP: the driver's ``polhemus/<name>/pose`` topics)
and ``bags/NAME.truth.npz`` beside it (see :mod:`inhand_sim.session` for both formats),
atomically: into a temporary folder beside them, then renamed into place. An existing bag
or sidecar is replaced only with ``--force``. The same arguments write the same bytes.

Exit status: 0 written, 1 could not write, 2 bad arguments (an object that cannot be one
included) or output exists.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace

from inhand_common.cli_types import number
from inhand_common.ground_truth import truth_path
from inhand_sim.catalogue import object_choices
from inhand_sim.exploration import ExplorationSettings, parse_hand_setting, speed_range_around
from inhand_sim.guidance import EXPLORERS
from inhand_sim.mesh_objects import MESH_SUFFIXES, UP_AXES
from inhand_sim.session import SessionSettings, simulate, write_session

EXIT_WRITE_FAILED = 1
EXIT_BAD_ARGUMENTS = 2
RATES = (15.0, 30.0, 120.0, 240.0)
LIFTS = ('continuous', 'between-frames')


def _rate(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a rate') from None
    if value not in RATES:
        raise argparse.ArgumentTypeError(
            f'{text} Hz: choose 15 (the paper\'s rate), 30, 120 or 240 (the Liberty\'s two)')
    return value


def _object(text: str) -> str:
    """A name of :func:`object_choices`, or something that looks like a mesh file (whether
    it is one is for the loader to say)."""
    if text in object_choices() or text.lower().endswith(MESH_SUFFIXES):
        return text
    raise argparse.ArgumentTypeError(
        f'{text!r}: choose one of {", ".join(object_choices())} or give a mesh file '
        f'({", ".join(MESH_SUFFIXES)})')


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not an integer seed') from None
    if value < 0 or value >= 2 ** 63:
        raise argparse.ArgumentTypeError(f'seed {text} must be in [0, 2^63)')
    return value


def _finger_settings(parser: argparse.ArgumentParser, args: argparse.Namespace) -> dict:
    """The real-finger settings of the arguments (none given: the bundled bags' fingers)."""
    offsets = args.tip_offset_mm
    if offsets is not None and len(offsets) not in (1, 3):
        parser.error(f'--tip-offset-mm: give it once or once per finger (3), not {len(offsets)}')
    return {'tip_offset_mm': None if offsets is None else
            (tuple(offsets[0]) if len(offsets) == 1 else tuple(map(tuple, offsets))),
            'pad_radius_mm': args.pad_radius_mm, 'finger_roll_deg': args.finger_roll_deg}


def _hand(text: str) -> tuple[str, object]:
    try:
        return parse_hand_setting(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _pairs(count: int) -> str:
    if count == 0:
        return ''
    return '; and a stereo pair with its camera_infos' if count == 1 else \
        f'; and {count} stereo pairs with their camera_infos'


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='simulate_session',
        description='Simulate three fingertips exploring an object (contour-following '
                    'strokes, tracker noise, involuntary lifts; static on the table or held '
                    'and re-grasped) and write the driver\'s bag plus exact ground truth.')
    parser.add_argument('--object', required=True, type=_object, metavar='NAME|MESH_FILE',
                        help=f'the object explored: {", ".join(object_choices())}, or a mesh '
                        f'file ({", ".join(MESH_SUFFIXES)})')
    parser.add_argument('--mesh-scale', type=number(above=0.0, unit='m per unit'), default=1.0,
                        metavar='S', help='meshes: metres per unit of the file (0.001 for '
                        'millimetres; default 1)')
    parser.add_argument('--mesh-up', choices=UP_AXES, default='z',
                        help="meshes: the file's axis that points up (default z)")
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument('--static', dest='static', action='store_true',
                      help='object fixed on the table, no object sensor (map with '
                           'config/mapping_static.yaml)')
    mode.add_argument('--moving', dest='static', action='store_false',
                      help='object held and moved by the other hand, object sensor published '
                           '(map with config/mapping.yaml)')
    parser.add_argument('--regrasp', action=argparse.BooleanOptionalAction, default=None,
                        help='moving only: the other hand turns the object 60-120 degrees '
                             'about every 40 s while the fingers are off it (default: on)')
    parser.add_argument('--second-object-sensor', action='store_true',
                        help='moving only: also publish a second sensor rigidly attached to '
                             'the object (station object2)')
    parser.add_argument('--rate', type=_rate, required=True, metavar='15|30|120|240',
                        help='tracker frame rate in Hz')
    parser.add_argument('--speed', type=number(at_least=1.0, at_most=30.0, unit='cm/s'),
                        metavar='CM_PER_S', help='mean sliding speed of the strokes (each stroke '
                        'within 20%% of it, varying by 30%% within itself; default: 2-5 cm/s)')
    parser.add_argument('--lifts', choices=LIFTS, default='continuous',
                        help='continuous (default): lifts, lift-offs and touch-downs pass through '
                        'every height above the surface; between-frames: they jump past 6 mm '
                        'between two frames (the sessions made before)')
    parser.add_argument('--hand', action='append', default=[], type=_hand, metavar='NAME=VALUE',
                        help='how the hand moves, beyond the default hand (repeatable): '
                        'stroke_length_range=0.03,0.12 (m), speed_profile=wave|bell, '
                        'liftoff_height_range=0.01,0.04 (m), liftoff_speed_range=0.1,0.3 (m/s), '
                        'liftoff_angle_range=0,45 (degrees from the normal), '
                        'hover_probability=0.2, hover_height_range=0.002,0.006 (m), '
                        'tremor_amplitude=0.0005 (m), tremor_frequency=10 (Hz), '
                        'held_scale=1.5, transit_speed=0.3 (m/s), speed_variation=0.3, '
                        'focus_centre=0.05,0,0 (object frame, m: where the hand starts and comes '
                        'back to most, e.g. a handle), focus_radius=0.03 (m), focus_weight=4')
    parser.add_argument('--explorer', choices=EXPLORERS, default='random',
                        help='who chooses where each stroke starts: random (default) the '
                        'simulated person, guided the predicted surface\'s next touches '
                        '(predict_surface), each stroke steered away from the touched surface, '
                        'greedy the start farthest from all touched so far')
    parser.add_argument('--duration', type=number(above=0.0, at_most=24 * 3600, unit='seconds'),
                        required=True, metavar='SECONDS')
    parser.add_argument('--seed', type=_seed, required=True, metavar='N')
    parser.add_argument('--noise-mm', type=number(at_least=0.0, at_most=50.0, unit='mm'),
                        default=1.0, metavar='MM',
                        help='fingertip tracker noise, standard deviation per axis (default 1.0)')
    parser.add_argument('--tip-offset-mm', type=float, nargs=3, action='append',
                        metavar=('X', 'Y', 'Z'),
                        help='real fingers: the pad centre in the fingertip sensor\'s frame '
                        '(sensor on the nail); once for every finger or once per finger')
    parser.add_argument('--pad-radius-mm', type=number(at_least=0.0, at_most=15.0, unit='mm'),
                        default=0.0, metavar='MM', help='real fingers: the pad\'s radius')
    parser.add_argument('--finger-roll-deg', type=number(at_least=0.0, at_most=60.0),
                        default=0.0, metavar='DEG',
                        help='real fingers: how far the finger rolls about its axis')
    parser.add_argument('--output', required=True, metavar='bags/NAME',
                        help='bag folder to write; the ground truth goes to NAME.truth.npz beside it')
    parser.add_argument('--stereo', action='store_true',
                        help='also one stereo image pair (and both camera_infos) of the object, '
                        'stamped at the first tracker frame, with its true depth in the sidecar')
    parser.add_argument('--stereo-shots', type=int, default=1, metavar='N',
                        help='with --stereo: N pairs in all, the first before the exploration and '
                        'the others at evenly spaced frames during it (default 1; the sidecar '
                        'describes the first)')
    parser.add_argument('--camera-distance', type=number(at_least=0.15, at_most=2.0, unit='m'),
                        default=0.42, help='distance of the stereo rig from the object (m)')
    parser.add_argument('--camera-azimuth', type=number(at_least=-360.0, at_most=360.0,
                                                        unit='degrees'),
                        help='where the rig stands around the object: degrees about the '
                        'vertical from the tracker\'s +x (default: the bench rig, -79)')
    parser.add_argument('--camera-elevation', type=number(at_least=-80.0, at_most=89.0,
                                                          unit='degrees'),
                        help='degrees above the horizontal (default: the bench rig, 34)')
    parser.add_argument('--force', action='store_true', help='replace an existing bag and sidecar')
    parser.add_argument('--quiet', action='store_true', help='no progress line')
    return parser


class _Progress:
    """One progress line on stderr: redrawn in place on a terminal, every 10% otherwise."""

    def __init__(self, quiet: bool, stream=sys.stderr):
        self.quiet, self.stream = quiet, stream
        self.tty = stream.isatty()
        self.stage = ''
        self.decile = -1

    def stage_done(self, stage: str) -> None:
        self.stage = stage
        if not self.quiet and not self.tty:
            print(f'simulate_session: {stage}', file=self.stream, flush=True)
        elif not self.quiet:
            self.stream.write(f'\rsimulate_session: {stage:<60}')
            self.stream.flush()

    def fraction(self, value: float) -> None:
        if self.quiet:
            return
        line = f'simulate_session: writing [{"#" * int(value * 30):<30}] {value:6.1%}'
        if self.tty:
            self.stream.write('\r' + line)
            self.stream.flush()
            if value >= 1.0:
                self.stream.write('\n')
        elif int(value * 10) > self.decile:
            self.decile = int(value * 10)
            print(line, file=self.stream, flush=True)


def main(argv=None) -> int:
    parser = make_parser()
    args = parser.parse_args(argv)
    if args.static and args.regrasp:
        parser.error('--regrasp needs --moving: a static object is not re-grasped')
    if args.static and args.second_object_sensor:
        parser.error('--second-object-sensor needs --moving: a static session has no object sensor')
    if args.stereo_shots != 1 and not args.stereo:
        parser.error('--stereo-shots needs --stereo')
    if not 1 <= args.stereo_shots <= 100:
        parser.error(f'--stereo-shots {args.stereo_shots}: allowed is 1 to 100')
    output = args.output.rstrip('/') or args.output
    sidecar = truth_path(output)
    from pathlib import Path
    existing = [str(p) for p in (Path(output), sidecar) if p.exists()]
    if existing and not args.force:
        print(f'simulate_session: {" and ".join(existing)} already '
              f'{"exists" if len(existing) == 1 else "exist"}; use --force to replace',
              file=sys.stderr)
        return EXIT_BAD_ARGUMENTS
    exploration = ExplorationSettings(continuous_lifts=args.lifts == 'continuous')
    if args.speed is not None:
        exploration = replace(exploration, speed_range=speed_range_around(args.speed / 100.0))
    if args.hand:
        exploration = replace(exploration, **dict(args.hand))
    if args.explorer != 'random':
        exploration = replace(exploration, explorer=args.explorer)
    settings = SessionSettings(
        object_name=args.object, mesh_scale=args.mesh_scale, mesh_up=args.mesh_up,
        exploration=exploration, static=args.static,
        regrasp=(args.regrasp is not False) and not args.static,
        second_object_sensor=args.second_object_sensor, rate=args.rate,
        duration=args.duration, seed=args.seed, noise_mm=args.noise_mm, stereo=args.stereo,
        camera_distance=args.camera_distance, camera_azimuth_deg=args.camera_azimuth,
        camera_elevation_deg=args.camera_elevation, stereo_shots=args.stereo_shots,
        **_finger_settings(parser, args))
    progress = _Progress(args.quiet)
    started = time.monotonic()
    try:
        session = simulate(settings, progress=lambda stage: progress.stage_done(stage))
    except ValueError as error:    # the object: unknown, or a mesh that cannot be one
        print(f'simulate_session: {error}', file=sys.stderr)
        return EXIT_BAD_ARGUMENTS
    try:
        bag, truth = write_session(session, output, force=args.force, progress=progress.fraction)
    except OSError as error:
        print(f'simulate_session: could not write {output}: {error}', file=sys.stderr)
        return EXIT_WRITE_FAILED
    elapsed = time.monotonic() - started
    tr = session.truth
    kind = 'static' if settings.static else (
        f'moving, {len(session.regrasp_windows)} re-grasp(s)' if settings.regrasp else 'moving, no re-grasp')
    low, high = (100 * v for v in exploration.speed_range)
    print(f'simulate_session: {settings.object_name} ({kind}), {settings.duration:g} s at '
          f'{settings.rate:g} Hz, seed {settings.seed}, noise {settings.noise_mm:g} mm, '
          f'strokes {low:.3g}-{high:.3g} cm/s, {args.lifts} lifts'
          + ''.join(f', {name}={value}' for name, value in args.hand)
          + (f', {args.explorer} explorer' if args.explorer != 'random' else ''))
    print(f'  wrote {bag}/ : {session.message_count:,} messages '
          f'({len(session.stamps_ns):,} frames x {len(session.stations)} stations: '
          f'{", ".join(session.stations)}'
          f'{_pairs(len(session.stereo_shots))})')
    print(f'  wrote {truth} : {len(tr["contacts"]):,} contacts, {len(tr["stray_points"]):,} '
          f'strays, {len(tr["surface_points"]):,} surface samples')
    print(f'  in {elapsed:.1f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
