"""``calibrate_stereo``: chessboard image pairs -> left and right camera_info YAML, as ROS's
camera_calibration writes them.

    calibrate_stereo INPUT --size 8x6 --square 0.025 [--output-dir DIR]
                     [--camera-name stereo] [--k-coefficients 2|3] [--joint]

INPUT is a folder of image pairs or a bag:

  folder  one folder holding left<rest> and right<rest> images that pair by <rest>, e.g.
          left-0001.png with right-0001.png (the names camera_calibration gives the images
          it saves in /tmp/calibrationdata.tar.gz); .png, .jpg, .bmp, .tif, .pgm or .ppm.
  bag     a rosbag2 bag (folder, .mcap or .db3) with stereo/left/image_raw and
          stereo/right/image_raw (sensor_msgs/Image: mono8, rgb8 or bgr8), paired by exact
          header.stamp.

--size is the count of inner corners (where four squares meet), columns x rows, and
--square the edge of a square in metres, as for camera_calibration. Each camera's
intrinsics (plumb_bob: k1, k2, p1, p2; k3 too with --k-coefficients 3) come from every
image of it that shows the whole board; the pairs where both cameras show it then give the
pose of the right camera with those intrinsics fixed (camera_calibration's way), or, with
--joint, refine both cameras' intrinsics together with it. Rectification uses alpha 0
(only valid pixels), so the right P holds -fx' * baseline in P[0, 3]. A view that barely
moved from an earlier one is skipped (a bag held still adds nothing). At least 6 pairs
must show the board.

Writes DIR/left.yaml and DIR/right.yaml (camera names <camera-name>/left and /right) and
prints the RMS reprojection error, the epipolar error (mean |y_left - y_right| of the
corners after rectification, px: what the stereo matcher sees), the baseline and how many
pairs were used and why the others were not.

Exit codes: 0 written; 2 bad input (no such folder or bag, no images, too few pairs with
the chessboard, a result that is not a side-by-side pair), nothing written; 1 the files
could not be written.
"""

from __future__ import annotations

import sys
from pathlib import Path

from inhand_common.bag_source import BagError, BagSource
from inhand_common.cli_types import command_parser, positive_float
from inhand_stereo.calibration import (
    CalibrationError,
    Chessboard,
    Detections,
    StereoCalibration,
    bag_pairs,
    calibrate_stereo,
    detect_chessboards,
    folder_pairs,
)
from inhand_stereo.camera_info_yaml import write_camera_info_yaml
from inhand_stereo.camera_model import CameraModel

EXIT_WRITE_FAILED = 1
EXIT_BAD_INPUT = 2
PROG = 'calibrate_stereo'


def is_bag(path: Path) -> bool:
    """A bag file, or a folder holding a bag (metadata.yaml, .mcap or .db3)."""
    if path.is_file():
        return path.suffix in ('.mcap', '.db3')
    return path.is_dir() and ((path / 'metadata.yaml').exists() or any(path.glob('*.mcap'))
                              or any(path.glob('*.db3')))


class ProgressLine:
    """'N of M pairs' on stderr every 10% for long inputs (a bag takes a while)."""

    def __init__(self, total: int):
        self.total, self.next = total, 0.1

    def __call__(self, done: int) -> None:
        if self.total >= 50 and done >= self.next * self.total:
            print(f'{PROG}: {done} of about {self.total} pairs looked at', file=sys.stderr)
            self.next += 0.1


def detect(source: Path, board: Chessboard) -> Detections:
    if is_bag(source):
        with BagSource(source) as bag:
            total, pairs = bag_pairs(bag, name=str(source))
            return detect_chessboards(pairs, board, progress=ProgressLine(total))
    total, pairs = folder_pairs(source)
    return detect_chessboards(pairs, board, progress=ProgressLine(total))


def describe(label: str, model: CameraModel, rms: float, views: int) -> str:
    k, d = model.K, ', '.join(f'{v:+.4f}' for v in model.D)
    return (f'  {label} ({model.name}): fx {k[0, 0]:.2f} fy {k[1, 1]:.2f} cx {k[0, 2]:.2f} '
            f'cy {k[1, 2]:.2f} px; D [{d}]; RMS {rms:.3f} px over {views} images')


def report(result: StereoCalibration, detections: Detections) -> None:
    board = detections.board
    rejected = len(detections.rejected)
    print(f'{PROG}: {result.pairs} pairs used, {rejected} not used (of {detections.seen}); '
          f'chessboard {board.label} inner corners, {board.square * 1e3:g} mm squares')
    for line in detections.rejection_summary():
        print(f'  not used: {line}')
    print(describe('left ', result.left, result.rms_left, result.left_views))
    print(describe('right', result.right, result.rms_right, result.right_views))
    how = 'intrinsics refined jointly' if result.joint else 'intrinsics fixed'
    print(f'  stereo ({how}): RMS reprojection error {result.rms:.3f} px over {result.pairs} '
          f'pairs; baseline {result.baseline * 1e3:.2f} mm; cameras '
          f'{result.rotation_angle:.2f} deg apart')
    corners = result.pairs * board.count
    print(f'  epipolar error after rectification: mean {result.epipolar_error:.3f} px, max '
          f'{result.epipolar_max:.3f} px (|y_left - y_right| of {corners} corners)')
    if result.epipolar_error > 0.5 or result.rms > 1.0:
        print(f'{PROG}: warning: errors above 0.5 px epipolar / 1 px RMS: are the pairs taken '
              'at the same moment, the board flat and --square right?', file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    parser = command_parser(PROG, __doc__, epilog_from=2)
    parser.add_argument('input', type=Path, help='folder of left*/right* images, or a bag')
    parser.add_argument('--size', required=True, metavar='COLSxROWS',
                        help='inner corners of the chessboard, e.g. 8x6')
    parser.add_argument('--square', required=True, type=positive_float, metavar='M',
                        help='edge of one square (m), e.g. 0.025')
    parser.add_argument('--output-dir', type=Path, default=Path('.'), metavar='DIR',
                        help='where left.yaml and right.yaml go (default: here)')
    parser.add_argument('--camera-name', default='stereo',
                        help='camera_name prefix: <name>/left, <name>/right (default stereo)')
    parser.add_argument('--k-coefficients', type=int, choices=(2, 3), default=2,
                        help='radial distortion coefficients to estimate (default 2: k3 = 0)')
    parser.add_argument('--joint', action='store_true',
                        help='refine both intrinsics with the extrinsics from the pairs')
    args = parser.parse_args(argv)
    try:
        board = Chessboard.parse(args.size, args.square)
        if not args.input.exists():
            raise CalibrationError(f'{args.input}: no such folder or bag')
        detections = detect(args.input, board)
        names = (f'{args.camera_name}/left', f'{args.camera_name}/right')
        result = calibrate_stereo(detections, args.k_coefficients, args.joint, names)
    except (CalibrationError, BagError, OSError) as error:
        print(f'{PROG}: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    report(result, detections)
    try:
        paths = [write_camera_info_yaml(args.output_dir / 'left.yaml', result.left),
                 write_camera_info_yaml(args.output_dir / 'right.yaml', result.right)]
    except OSError as error:
        print(f'{PROG}: cannot write the camera_info files: {error}', file=sys.stderr)
        return EXIT_WRITE_FAILED
    print('  wrote ' + ', '.join(str(p) for p in paths))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
