"""``calibrate_camera_tracker``: where the stereo camera sits in the tracker frame, from
points touched with a tracked fingertip and seen by the camera.

    calibrate_camera_tracker POINTS [--left LEFT.yaml --right RIGHT.yaml]
                             [--output camera_pose.yaml]

Touch at least 3 points the stereo camera sees (better 6-10, spread over the workspace and
not on one line). For each, write down the fingertip's position in the tracker frame (x, y,
z: metres in polhemus_source, e.g. `topic_echo polhemus/index/pose --once`) and either the
point in the camera frame (x_cam, y_cam, z_cam: metres in stereo_left_optical, the left
camera's optical frame, x right, y down, z forward) or its pixel in the rectified left and
right images (u_left, v_left, u_right), which --left and --right, the camera_info YAML of
the stereo calibration, triangulate (and turn from the rectified frame back into the left
camera with the left R, as the stereo node does with its points).

POINTS is a CSV file: a header line naming the columns (any order; `name` is optional;
lines starting with # are comments), then one row per point that fills either the camera
columns or the pixel columns and leaves the others empty:

    # tracker position (m), then the camera point (m) or the rectified pixels
    name,x,y,z,x_cam,y_cam,z_cam,u_left,v_left,u_right
    corner_a,0.412,-0.031,0.122,0.051,-0.020,0.402,,,
    corner_b,0.398,0.054,0.118,,,,402.5,288.0,318.25

or a YAML file (.yaml) with the same keys, one mapping per point:

    points:
      - {name: corner_a, x: 0.412, y: -0.031, z: 0.122, x_cam: 0.051, y_cam: -0.020, z_cam: 0.402}
      - {name: corner_b, x: 0.398, y: 0.054, z: 0.118, u_left: 402.5, v_left: 288.0, u_right: 318.25}

Fits R, t with tracker = R camera + t by least squares (a proper rotation, no scale), prints
every point's residual and the RMS and largest (mm), and writes the stereo node's parameter
file (the /** wildcard applies it in any namespace):

    /**/stereo_node:
      ros__parameters:
        camera_pose: [x, y, z, qx, qy, qz, qw]

to be passed as `stereo_node --ros-args --params-file camera_pose.yaml`. camera_pose is the
pose of stereo_left_optical in polhemus_source: a point p in the camera frame is R p + t in
the tracker frame.

Exit codes: 0 written; 2 bad input (file, columns, fewer than 3 points, points on one line,
tracker and camera points of different spread), nothing written; 1 the file could not be
written.
"""

from __future__ import annotations

import sys
from pathlib import Path

from inhand_common.cli_types import command_parser
from inhand_stereo.camera_info_yaml import read_camera_info_yaml
from inhand_stereo.rigid_fit import (
    camera_points,
    fit_rigid,
    read_correspondences,
    write_camera_pose_yaml,
)

EXIT_WRITE_FAILED = 1
EXIT_BAD_INPUT = 2
PROG = 'calibrate_camera_tracker'


def main(argv: list[str] | None = None) -> int:
    parser = command_parser(PROG, __doc__, epilog_from=2)
    parser.add_argument('points', type=Path, help='CSV or YAML file of correspondences')
    parser.add_argument('--left', type=Path, metavar='LEFT.yaml',
                        help='left camera_info YAML (to triangulate pixel rows)')
    parser.add_argument('--right', type=Path, metavar='RIGHT.yaml',
                        help='right camera_info YAML (to triangulate pixel rows)')
    parser.add_argument('--output', type=Path, default=Path('camera_pose.yaml'), metavar='FILE',
                        help='parameter file to write (default camera_pose.yaml)')
    args = parser.parse_args(argv)
    try:
        if (args.left is None) != (args.right is None):
            raise ValueError('--left and --right go together (the rectified pair)')
        correspondences = read_correspondences(args.points)
        left = read_camera_info_yaml(args.left) if args.left is not None else None
        right = read_camera_info_yaml(args.right) if args.right is not None else None
        points = camera_points(correspondences, left, right)
        fit = fit_rigid(points, [c.tracker for c in correspondences])
    except ValueError as error:
        print(f'{PROG}: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    width = max(len('point'), *(len(c.name) for c in correspondences))
    print(f'{PROG}: {len(correspondences)} points from {args.points}')
    print(f'  {"point":<{width}}  {"residual":>8}  {"dx":>7}  {"dy":>7}  {"dz":>7}  '
          '(mm, fitted - measured tracker position)')
    for c, distance, residual in zip(correspondences, fit.distances, fit.residuals):
        dx, dy, dz = residual * 1e3
        print(f'  {c.name:<{width}}  {distance * 1e3:8.2f}  {dx:+7.2f}  {dy:+7.2f}  {dz:+7.2f}')
    print(f'  RMS {fit.rms * 1e3:.2f} mm, max {fit.max * 1e3:.2f} mm')
    pose = ', '.join(f'{v:.6f}' for v in fit.pose)
    print(f'  camera_pose [x, y, z, qx, qy, qz, qw] = [{pose}]')
    comments = [f'Written by {PROG} from {args.points}: {len(correspondences)} points, '
                f'RMS residual {fit.rms * 1e3:.2f} mm, max {fit.max * 1e3:.2f} mm.']
    try:
        path = write_camera_pose_yaml(args.output, fit, comments)
    except OSError as error:
        print(f'{PROG}: cannot write {args.output}: {error}', file=sys.stderr)
        return EXIT_WRITE_FAILED
    print(f'  wrote {path}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
