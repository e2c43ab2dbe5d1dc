"""``calibrate_vision_model``: the stereo camera's range noise, for the vision sensor model.

    calibrate_vision_model BAG [BAG ...] --config config/mapping.yaml
                           --config config/stereo.yaml (--truth | --touch)
                           [--output vision_model.yaml] [--bins 8]

Measures the range errors of the stereo node's depth in each bag's first stereo pair and
fits ``sigma_s(d)`` of eq. 7 both ways (inhand_stereo/noise_fit.py: the paper's
``sigma_min + zeta d`` and the stereo ``sigma_min + zeta d^2``), prints the bins, both fits
and which fits better, and writes the better one as the stereo node's parameters
(``vision_noise``, ``vision_sigma_min``, ``vision_zeta``) in a ``/**/stereo_node`` section.
The errors come from (inhand_tools/range_errors.py)

* ``--truth``: the simulator's true depth of the left image (``BAG.truth.npz``), on the
  object's pixels; or
* ``--touch``: the fingertips, registered into the map frame as the registration node does
  (a fingertip on the surface is a true surface point; those more than 2 cm from the
  measured surface are left out).

Use sessions at several distances: one view spans a few centimetres of range, where the
two models cannot be told apart. Exit status: 0 written, 2 bad input.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from inhand_common.atomic_file import atomic_write
from inhand_common.cli_types import command_parser
from inhand_common.ground_truth import load_truth, truth_path
from inhand_common.parameters import ParameterError
from inhand_mapping.mapping_config import load_parameters
from inhand_stereo.noise_fit import NoiseFit, fit_noise
from inhand_tools.bag_points import read_bag_points
from inhand_tools.bag_stereo_shot import read_bag_shot, stereo_config_for_map
from inhand_tools.range_errors import touch_range_errors, truth_range_errors

PROG = 'calibrate_vision_model'
EXIT_BAD_INPUT = 2


def _errors(bag: Path, configs: list[str], source: str) -> tuple[np.ndarray, np.ndarray]:
    registration, occupancy = load_parameters(configs, {})
    shot, why = read_bag_shot(bag, stereo_config_for_map(configs, registration, occupancy))
    if shot is None:
        raise ValueError(f'{bag}: {why or "no stereo pair"}')
    if source == 'truth':
        truth = load_truth(truth_path(bag))
        if truth.stereo is None:
            raise ValueError(f'{truth_path(bag)}: no stereo truth (a session without --stereo)')
        return truth_range_errors(shot, truth.stereo)
    points = read_bag_points(bag, registration.mode, configs)
    return touch_range_errors(shot, points.registered)


def _yaml(fit: NoiseFit, bags: list[Path], source: str) -> str:
    best = fit.best
    others = ', '.join(f'{f.noise}: sigma_min {f.sigma_min * 1000:.3f} mm, zeta {f.zeta:.5f}, '
                       f'rms {f.rms * 1000:.3f} mm' for f in fit.fits.values())
    return (f'# written by {PROG} from {", ".join(map(str, bags))} ({source})\n'
            f'# fits: {others}; {best.noise} fits better\n'
            '/**/stereo_node:\n  ros__parameters:\n'
            f'    vision_noise: {best.noise}\n'
            f'    vision_sigma_min: {best.sigma_min:.6g}\n'
            f'    vision_zeta: {best.zeta:.6g}\n')


def main(argv: list[str] | None = None) -> int:
    parser = command_parser(PROG, __doc__)
    parser.add_argument('bags', type=Path, nargs='+', metavar='BAG')
    parser.add_argument('--config', action='append', default=[], required=True,
                        help='ROS parameter files (the session\'s mapping file and the rig\'s '
                        'stereo file); repeatable')
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument('--truth', dest='source', action='store_const', const='truth',
                        help='errors against the simulator\'s true depth')
    source.add_argument('--touch', dest='source', action='store_const', const='touch',
                        help='errors against the registered fingertips')
    parser.add_argument('--output', type=Path, default=Path('vision_model.yaml'))
    parser.add_argument('--bins', type=int, default=8, help='range bins (default 8)')
    args = parser.parse_args(argv)
    try:
        if not 2 <= args.bins <= 100:
            raise ValueError(f'--bins {args.bins}: must be in [2, 100]')
        ranges, errors = [], []
        for bag in args.bags:
            bag_ranges, bag_errors = _errors(bag, args.config, args.source)
            print(f'{PROG}: {bag}: {len(bag_errors)} range errors at '
                  f'{bag_ranges.min() if len(bag_ranges) else 0:.3f}-'
                  f'{bag_ranges.max() if len(bag_ranges) else 0:.3f} m')
            ranges.append(bag_ranges)
            errors.append(bag_errors)
        fit = fit_noise(np.concatenate(ranges), np.concatenate(errors), args.bins)
    except (ParameterError, ValueError, OSError) as error:
        print(f'{PROG}: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f'  median error (bias) {fit.bias * 1000:+.3f} mm; robust spread per range bin:')
    for d, sigma, count in zip(fit.bin_ranges, fit.bin_sigmas, fit.bin_counts):
        print(f'    {d:.3f} m: {sigma * 1000:.3f} mm ({count} samples)')
    for f in fit.fits.values():
        growth = 'd' if f.noise == 'linear' else 'd^2'
        print(f'  {f.noise:6s} sigma_s = {f.sigma_min * 1000:.3f} mm + {f.zeta:.5f} {growth}: '
              f'rms {f.rms * 1000:.3f} mm')
    print(f'  {fit.best.noise} fits better')
    with atomic_write(args.output) as stream:
        stream.write(_yaml(fit, args.bags, args.source).encode('utf-8'))
    print(f'  wrote {args.output}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
