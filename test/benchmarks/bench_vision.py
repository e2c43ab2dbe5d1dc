#!/usr/bin/env python3
"""Cost of the vision local map and of fusion on the 70^3 grid.

    .venv/bin/python test/benchmarks/bench_vision.py [--runs N] [--no-open3d]

1. One 640x480 stereo pair of each bundled bag, through the stereo node's pipeline: the
   shot's pixels back-projected into the map and the scene segmentation (target: <= 10 ms),
   then the integration into the 70^3 grid (``VisionMap.integrate``: the depth's local
   spread and the projective update of every cell); the whole vision update of a pair
   (target: <= 20 ms).
2. The integration against Open3D's ``UniformTSDFVolume.integrate`` on the same depth image
   and the same grid (origin, 5 mm cells, 70^3), both on one thread: each process pinned to
   the same core (Open3D runs its loops on every core it may use, whatever OMP_NUM_THREADS
   says), in alternating rounds so that both see the same machine, each into a fresh map
   or volume made outside the timing. Target: ours at most Open3D's (best of the runs;
   medians printed too). Open3D is a benchmark-only dependency:
   installed here on first use into ``.venv-open3d`` (pip ``open3d-cpu``; its library
   needs Debian's ``libusb-1.0-0``, installed with apt-get when run as root).
3. OctoMap's ``insertPointCloud`` on the same points (pyoctomap: ray casting from the camera
   through every point, 5 mm): the integration at least 10x faster.
4. Fusing the full grid (the touch map of ``cat_static`` and that vision map): the product
   form (eq. 9) and the entropy form (eqs. 10-12, whole map; local r = 1; log pooling).
   Target: at most 10 ms for both forms; the paper's remark that eq. 9 is the cheaper.

Best and median of N runs after a warm-up (the compiled loops' first call is not counted).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

WORKSPACE = Path(__file__).resolve().parents[2]
OPEN3D_ENV = WORKSPACE / '.venv-open3d'
OPEN3D_PACKAGE = 'open3d-cpu==0.20.0'
CORE = 0                # both integrations run pinned to this core
BAGS = (('cat_static', 'mapping_static.yaml'), ('bottle_static', 'mapping_static.yaml'),
        ('cat_moving', 'mapping.yaml'))

from inhand_common.blas_threads import single_threaded_blas  # noqa: E402
from inhand_common.heap_reuse import reuse_freed_memory  # noqa: E402
from inhand_mapping.bag_mapping import build_map_from_bag  # noqa: E402
from inhand_mapping.fusion import fuse  # noqa: E402
from inhand_mapping.mapping_config import load_parameters  # noqa: E402
from inhand_stereo.scene_segmentation import segment_object  # noqa: E402
from inhand_stereo.vision_model import VisionMap  # noqa: E402
from inhand_tools.bag_stereo_shot import read_bag_shot, stereo_config_for_map  # noqa: E402


def timings_ms(function, runs: int) -> tuple[float, float]:
    """(best, median) of ``runs`` calls after one warm-up call, in ms."""
    function()
    times = []
    for _ in range(runs):
        started = time.perf_counter()
        function()
        times.append(time.perf_counter() - started)
    return float(np.min(times)) * 1000.0, float(np.median(times)) * 1000.0


def median_ms(function, runs: int) -> float:
    return timings_ms(function, runs)[1]


def verdict(ok: bool) -> str:
    return 'met' if ok else 'NOT met'


class Pair:
    """One bundled bag's stereo pair, placed, as the stereo node has it."""

    def __init__(self, bag: str, mapping_config: str):
        configs = [str(WORKSPACE / 'config' / mapping_config),
                   str(WORKSPACE / 'config' / 'stereo.yaml')]
        self.bag = WORKSPACE / 'bags' / bag
        self.registration, self.occupancy = load_parameters(configs, {})
        self.stereo = stereo_config_for_map(configs, self.registration, self.occupancy)
        shot, why = read_bag_shot(self.bag, self.stereo)
        if shot is None:
            raise SystemExit(f'bench_vision: {bag}: {why}')
        self.placed = shot.placed
        self.depth = self.placed.shot.depth
        self.P = self.placed.shot.left_camera.P
        self.map_to_camera = self.placed.map_to_camera(self.stereo.camera_pose)
        self.vision = VisionMap(self.stereo.grid, self.stereo.vision, self.stereo.clamp)
        self.mask = self.segment().keep.reshape(self.depth.shape)

    def segment(self):
        return segment_object(self.placed.pixel_points_in_map(self.stereo.camera_pose),
                              self.stereo.grid, self.stereo.segmentation)

    def integrate(self) -> None:
        self.vision.reset()
        self.expose()

    def expose(self) -> None:
        """The exposure alone, into the map as it is (reset outside the timing)."""
        self.vision.integrate(self.depth, self.P, self.map_to_camera, self.mask)

    def update(self) -> None:
        """The whole vision update of a pair (PlacedShot.integrate_into, as the node)."""
        self.vision.reset()
        self.placed.integrate_into(self.vision, self.stereo.camera_pose, self.stereo.segmentation)


def ensure_open3d() -> Path | None:
    """The Python of the benchmark's Open3D environment, installed on first use; None
    (and why, printed) if it cannot be."""
    python = OPEN3D_ENV / 'bin' / 'python'
    if not python.exists():
        print(f'  .. installing {OPEN3D_PACKAGE} into {OPEN3D_ENV.name} (benchmark only)',
              flush=True)
        done = subprocess.run([sys.executable, '-m', 'venv', '--without-pip', str(OPEN3D_ENV)])
        if done.returncode == 0:
            done = subprocess.run([str(python), '-m', 'ensurepip'], stdout=subprocess.DEVNULL)
        if done.returncode == 0:
            done = subprocess.run([str(python), '-m', 'pip', 'install', '-q', OPEN3D_PACKAGE])
        if done.returncode != 0:
            print('  Open3D: could not be installed (see above); its comparison is skipped')
            return None
    probe = subprocess.run([str(python), '-c', 'import open3d'], capture_output=True, text=True)
    if 'libusb' in probe.stderr and os.geteuid() == 0:
        print('  .. installing libusb-1.0-0 (apt-get), which Open3D\'s library loads', flush=True)
        subprocess.run(['apt-get', 'install', '-y', '-q', 'libusb-1.0-0'],
                       stdout=subprocess.DEVNULL)
        probe = subprocess.run([str(python), '-c', 'import open3d'], capture_output=True,
                               text=True)
    if probe.returncode != 0:
        print(f'  Open3D: cannot be imported ({probe.stderr.strip().splitlines()[-1]}); '
              f'its comparison is skipped')
        return None
    return python


def against_open3d(pair: Pair, runs: int) -> bool | None:
    """Part 2: our integration and Open3D's on one core, alternating rounds."""
    python = ensure_open3d()
    if python is None:
        return None
    matrix, offset = pair.map_to_camera
    extrinsic = np.eye(4)
    extrinsic[:3, :3], extrinsic[:3, 3] = matrix, offset
    spec = pair.stereo.grid
    with tempfile.TemporaryDirectory() as scratch:
        shot = Path(scratch) / 'shot.npz'
        np.savez(shot, depth=pair.depth, K=np.asarray(pair.P)[:, :3], extrinsic=extrinsic,
                 n=spec.cells_per_axis, resolution=spec.resolution, origin=spec.origin)
        child = subprocess.Popen([str(python), str(Path(__file__).with_name('open3d_tsdf.py')),
                                  str(shot), str(CORE)], stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, text=True)
        assert child.stdin is not None and child.stdout is not None
        if child.stdout.readline().strip() != 'ready':
            print('  Open3D: the timing process did not start; its comparison is skipped')
            return None
        allowed = os.sched_getaffinity(0)
        ours: list[float] = []
        theirs: list[float] = []
        voxels = 0
        rounds = 4
        try:
            os.sched_setaffinity(0, {CORE})
            pair.integrate()                              # warm
            for _ in range(rounds):
                for _ in range(runs):
                    # a fresh map each time, cleared outside the timing as Open3D's fresh
                    # volume is made outside it
                    pair.vision.reset()
                    started = time.perf_counter()
                    pair.expose()
                    ours.append(time.perf_counter() - started)
                child.stdin.write(f'{runs}\n')
                child.stdin.flush()
                words = child.stdout.readline().split()
                theirs.extend(float(word) for word in words[1:1 + runs])
                voxels = int(words[-1])
        finally:
            os.sched_setaffinity(0, allowed)
            child.stdin.close()
            child.wait(timeout=30)
    best, best_o3d = min(ours) * 1e3, min(theirs[runs:] or theirs) * 1e3   # its first: warm-up
    median, median_o3d = float(np.median(ours)) * 1e3, float(np.median(theirs)) * 1e3
    print(f'  integration, one thread (core {CORE}), {rounds} alternating rounds of {runs}:')
    print(f'    ours   VisionMap.integrate                 {best:6.2f} ms best, '
          f'{median:6.2f} median ({pair.vision.observed_mask().sum():,} cells updated)')
    print(f'    Open3D UniformTSDFVolume.integrate         {best_o3d:6.2f} ms best, '
          f'{median_o3d:6.2f} median ({voxels:,} voxels with a surface)')
    ok = best <= best_o3d
    print(f'    ours / Open3D: {best / best_o3d:.2f} best, {median / median_o3d:.2f} median '
          f'(target <= 1: {verdict(ok)})')
    return ok


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=9)
    parser.add_argument('--no-open3d', action='store_true',
                        help='skip the comparison with Open3D (no install)')
    args = parser.parse_args()
    single_threaded_blas()     # as in the stereo node
    reuse_freed_memory()       # likewise (node_runner.py)
    print(f'# {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}; best and median '
          f'of {args.runs} runs (ms)')
    print('== Part 1: one pair\'s vision update (640x480, 70^3 grid of 5 mm)')
    pairs = {}
    results = []
    for bag, mapping_config in BAGS:
        pair = pairs[bag] = Pair(bag, mapping_config)
        segmentation = timings_ms(pair.segment, args.runs)
        integration = timings_ms(pair.integrate, args.runs)
        whole = timings_ms(pair.update, args.runs)
        results.append((segmentation[0] <= 10.0, whole[0] <= 20.0))
        print(f'  {bag:14s} segmentation {segmentation[0]:5.1f} best {segmentation[1]:5.1f} '
              f'median (<= 10: {verdict(results[-1][0])}); integration {integration[0]:5.1f} '
              f'best {integration[1]:5.1f} median; the whole update {whole[0]:5.1f} best '
              f'{whole[1]:5.1f} median (<= 20: {verdict(results[-1][1])})')
    pair = pairs['cat_static']

    print('== Part 2: the integration against Open3D (cat_static\'s pair)')
    open3d_ok = None if args.no_open3d else against_open3d(pair, args.runs)

    print('== Part 3: against OctoMap (cat_static\'s pair)')
    # OctoMap: the same measured points (every valid pixel inside the grid), the camera's
    # centre as the sensor origin, full rays.
    import pyoctomap
    stereo = pair.stereo
    points = pair.placed.pixel_points_in_map(stereo.camera_pose)
    points = points[np.all(np.isfinite(points), axis=1)]
    points = points[stereo.grid.contains(points)]
    matrix, offset = pair.map_to_camera
    origin = -(matrix.T @ offset)                 # the rectified camera's centre, map frame

    def octomap():
        tree = pyoctomap.OcTree(stereo.grid.resolution)
        tree.insertPointCloud(np.ascontiguousarray(points), origin)
    t_octomap = median_ms(octomap, max(3, args.runs // 3))
    t_integrate = median_ms(pair.integrate, args.runs)
    print(f'  OctoMap insertPointCloud, {len(points):,} points, full rays: {t_octomap:.1f} ms '
          f'-> the integration {t_octomap / t_integrate:.1f}x faster (target >= 10x: '
          f'{verdict(t_octomap / t_integrate >= 10)})')

    print('== Part 4: fusion (cat_static)')
    bag, registration, occupancy, vision = pair.bag, pair.registration, pair.occupancy, pair.vision
    touch = build_map_from_bag(bag, registration, occupancy, progress=False)['grid']
    pair.integrate()
    clamp = occupancy.log_odds_clamp
    forms = {
        'product (eq. 9)': dict(fusion='product'),
        'entropy, whole map (eqs. 10-12)': dict(fusion='entropy'),
        'entropy, local r=1': dict(fusion='entropy', entropy_radius=1),
        'entropy, local r=1, log pooling': dict(fusion='entropy', entropy_radius=1,
                                                entropy_pooling='log'),
    }
    for name, options in forms.items():
        t = median_ms(lambda options=options: fuse(touch=touch.log_odds,
                                                   vision=vision.log_odds, clamp=clamp,
                                                   **options), args.runs)
        target = '' if 'local' in name else f" (target <= 10 ms: {'met' if t <= 10 else 'NOT met'})"
        print(f'  fusion, {name}: {t:.1f} ms{target}')
    met = all(all(result) for result in results) and open3d_ok is not False
    print(f'== Summary: segmentation <= 10 ms and the update <= 20 ms on every pair, the '
          f"integration at most Open3D's: {verdict(met)}"
          + (' (Open3D not compared)' if open3d_ok is None else ''))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
