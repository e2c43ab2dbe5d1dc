#!/usr/bin/env python3
"""Open3D's ``UniformTSDFVolume.integrate`` timed on one depth image, for bench_vision.py.

Run by bench_vision.py with the Python of the benchmark-only Open3D environment:

    open3d_tsdf.py SHOT.npz CORE

``SHOT.npz`` holds the depth (H, W; NaN: none), the camera matrix K, the map-to-camera
extrinsic (4x4) and the grid (cells per axis n, resolution, origin). The process pins itself
to ``CORE`` (one thread: Open3D runs its loops on every core it may use, whatever
OMP_NUM_THREADS says), prints ``ready``, then for each line ``N`` on its input integrates
the image N times, each into a fresh volume (made outside the timing), and prints one
line: ``times`` and the N durations in seconds, then ``voxels`` and how many voxels the
last volume holds a surface in (a check that the image landed in the grid).
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np


def main() -> int:
    shot_path, core = sys.argv[1], int(sys.argv[2])
    os.sched_setaffinity(0, {core})
    import open3d as o3d  # after pinning: its thread pool sees one core

    shot = np.load(shot_path)
    depth = np.nan_to_num(shot['depth'].astype(np.float32), nan=0.0)   # 0: no depth
    depth[depth < 0] = 0.0
    K, extrinsic = shot['K'], shot['extrinsic']
    n, resolution, origin = int(shot['n']), float(shot['resolution']), shot['origin']
    height, width = depth.shape
    intrinsic = o3d.camera.PinholeCameraIntrinsic(width, height, K[0, 0], K[1, 1], K[0, 2],
                                                  K[1, 2])
    rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(np.zeros((height, width, 3), np.uint8)), o3d.geometry.Image(depth),
        depth_scale=1.0, depth_trunc=1e3, convert_rgb_to_intensity=False)

    def volume():
        return o3d.pipelines.integration.UniformTSDFVolume(
            length=n * resolution, resolution=n, sdf_trunc=3 * resolution,
            color_type=o3d.pipelines.integration.TSDFVolumeColorType.NoColor,
            origin=np.asarray(origin, dtype=np.float64).reshape(3, 1))

    print('ready', flush=True)
    for line in sys.stdin:
        times = []
        last = None
        for _ in range(int(line)):
            last = volume()
            started = time.perf_counter()
            last.integrate(rgbd, intrinsic, extrinsic)
            times.append(time.perf_counter() - started)
        voxels = len(last.extract_voxel_point_cloud().points) if last is not None else 0
        print('times', *times, 'voxels', voxels, flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
