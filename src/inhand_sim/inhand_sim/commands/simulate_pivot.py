"""``simulate_pivot``: a pivot calibration session with known tip offsets.

    simulate_pivot --output bags/NAME [--tip-offset X Y Z ...] [--tilt-deg 45]
                   [--twist-deg 10] [--seconds 10] [--rate 30] [--noise-mm 1]
                   [--seed N] [--force]

Each finger in turn rests its pad in a dimple and pivots about it (inhand_sim/pivot.py),
as a researcher does before a session. ``--tip-offset`` (mm, the pad centre in the
sensor's frame) once for every finger or once per finger (thumb, index, middle); default
0 0 -10. Writes the bag folder ``bags/NAME/`` (the driver's pose topics, static mode) and
``bags/NAME.pivot.yaml`` beside it with the true offsets and pad centres, for checking
``calibrate_fingertips`` against. Exit status: 0 written, 2 bad arguments or output exists.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from inhand_common.cli_types import command_parser, number
from inhand_sim.exploration import FINGERS
from inhand_sim.pivot import PivotSession, PivotSettings, simulate_pivot
from inhand_sim.session import write_recording

PROG = 'simulate_pivot'
EXIT_BAD_ARGUMENTS = 2


def pivot_truth_path(bag: Path) -> Path:
    """Where the truth of the pivot session ``bag`` is written."""
    return bag.with_name(bag.name + '.pivot.yaml')


def _write_truth(path: Path, bag_name: str, session: PivotSession) -> Path:
    """The pivot session's truth: each finger's offset and pivot point, as YAML."""
    lines = [f'# the truth of the pivot session {bag_name} ({PROG})', 'fingers:']
    for name, offset, pivot in zip(FINGERS, session.offsets, session.pivots):
        lines += [f'  {name}:', f'    tip_offset: [{", ".join(f"{v:.6f}" for v in offset)}]',
                  f'    pivot: [{", ".join(f"{v:.6f}" for v in pivot)}]']
    path.write_text('\n'.join(lines) + '\n')
    return path


def main(argv: list[str] | None = None) -> int:
    parser = command_parser(PROG, __doc__)
    parser.add_argument('--output', type=Path, required=True)
    parser.add_argument('--tip-offset', type=float, nargs=3, action='append', metavar=('X', 'Y', 'Z'),
                        help='mm, sensor frame; once for all fingers or once per finger')
    parser.add_argument('--tilt-deg', type=number(at_least=0.0, at_most=120.0), default=45.0)
    parser.add_argument('--twist-deg', type=number(at_least=0.0, at_most=90.0), default=10.0)
    parser.add_argument('--seconds', type=number(above=0.0, at_most=600.0), default=10.0)
    parser.add_argument('--rate', type=number(above=0.0, at_most=240.0), default=30.0)
    parser.add_argument('--noise-mm', type=number(at_least=0.0, at_most=20.0), default=1.0)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--force', action='store_true', help='replace an existing output')
    args = parser.parse_args(argv)
    offsets = np.array(args.tip_offset or [[0.0, 0.0, -10.0]]) / 1000.0
    if len(offsets) == 1:
        offsets = np.repeat(offsets, len(FINGERS), axis=0)
    truth = pivot_truth_path(args.output)
    try:
        if len(offsets) != len(FINGERS):
            raise ValueError(f'--tip-offset: give it once or {len(FINGERS)} times '
                             f'({", ".join(FINGERS)}), not {len(offsets)}')
        session = simulate_pivot(PivotSettings(
            tip_offsets=tuple(map(tuple, offsets)), tilt_deg=args.tilt_deg,
            twist_deg=args.twist_deg, seconds=args.seconds, rate=args.rate,
            noise_mm=args.noise_mm, seed=args.seed))
        write_recording(session, args.output, truth,
                        lambda path: _write_truth(path, args.output.name, session), args.force)
    except (ValueError, FileExistsError) as error:
        print(f'{PROG}: {error}', file=sys.stderr)
        return EXIT_BAD_ARGUMENTS
    print(f'wrote {args.output} and {truth}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
