#!/usr/bin/env bash
# Benchmarks of the workspace. Sets up .venv if needed, then runs the chosen benchmark from
# the workspace root; the remaining arguments go to the benchmark script.
#
# Usage: bash launch_scripts/benchmark.sh [liberty|mapping|replay|stereo|stereo-bags|stereo-node|vision|texture|texture-sessions|quality|validation|cell-judge|fingers|shape|explore|startup|latency|fuzz|soak|all]
#                                         [benchmark options]
#   liberty (default)  Liberty codec parse rate + driver end-to-end throughput
#                      (test/benchmarks/bench_liberty.py: --seconds N, --quick, --codec-only)
#   mapping            occupancy integration vs OctoMap + publishing a full 70^3 map + build_map
#                      (test/benchmarks/bench_mapping.py: --quick, --points N, --runs R)
#   replay             a 240 Hz, 4-station, 60 s bag through bag_replay -> registration ->
#                      occupancy over DDS: real-time factor, nothing lost
#                      (test/benchmarks/bench_replay.py: --bag BAG, --runs R)
#   stereo             disparity accuracy on synthetic scenes + the node's per-frame path
#                      against the bare OpenCV matcher (test/benchmarks/bench_stereo.py:
#                      --quick, --runs N, --no-accuracy, --no-timing)
#   stereo-bags        disparity of the bundled bags' stereo pairs against their truth
#                      (test/benchmarks/bench_stereo_bags.py: no options)
#   stereo-node        the stereo node over DDS: 640x480 rgb8 images best effort with and
#                      without the graph's Fast DDS profile, publish-to-disparity latency
#                      against the bare OpenCV matcher, 15 pairs/s for 60 s from a reliable
#                      and a best-effort publisher, every pair counted
#                      (test/benchmarks/bench_stereo_node.py: --seconds S, --rate HZ,
#                      --latency-pairs N, --quick)
#   vision             one pair's vision update (segmentation, integration) on each bundled
#                      bag's pair, the integration against Open3D's UniformTSDFVolume on one
#                      core (installs open3d-cpu into .venv-open3d on first use), against
#                      OctoMap, and fusion (test/benchmarks/bench_vision.py: --runs N,
#                      --no-open3d)
#   texture            texture of the occupied cells: time and visibility rules
#                      (test/benchmarks/bench_texture.py: --quick, --runs N)
#   texture-sessions   texture on touch maps of other hands and objects, against its
#                      targets, and on the validation sessions drawn by point splatting
#                      (test/benchmarks/bench_texture_sessions.py: --keep DIR, --set S)
#   quality            the touch map on simulated sessions: objects x stroke speeds x rates x
#                      static/tracked, F / precision / recall / stray cells / touched surface
#                      per session and a summary against the targets
#                      (test/benchmarks/bench_quality.py: --quick, --objects, --speeds, --rates,
#                      --modes, --duration, --jobs, --set NAME=VALUE, --keep DIR, --hand NAME=VALUE,
#                      --sweep: the hand varied one property at a time, with the worst F and
#                      precision per property value)
#   validation         the touch map on ../shared/data/validation_sessions (an independent
#                      generator's hands and meshes; a check, never tuned on) beside each
#                      session's one-touch oracle (test/benchmarks/bench_validation.py:
#                      --sessions, --set NAME=VALUE, --jobs, --keep DIR)
#   cell-judge         the touch map's cell judge (cell_judge.py): learned from
#                      hand_sessions.py's sets, each session judged by the classifier of the
#                      other draws, checked on the validation folder; --export FILE writes
#                      the map's model (test/benchmarks/bench_cell_judge.py: --train DIRS,
#                      --check DIR, --keep DIR; installs scikit-learn into .sklearn-lib)
#   fingers            real fingers: pivot calibration accuracy (10-60 degrees), the cat mapped
#                      with sensors on the nail (point fingertips / raw / offset only /
#                      calibrated, a wrong offset) and the finger rolling 0-30 degrees
#                      (test/benchmarks/bench_fingers.py: --quick, --keep DIR)
#   shape              surface mesh, superquadric parts and graspable part on objects of known
#                      superquadrics explored by the simulator, static and tracked: parts,
#                      size/exponent/centre errors, Chamfer against the classic fit and the
#                      dense-truth fit, times (test/benchmarks/bench_shape.py: --shapes,
#                      --modes, --keep DIR, --duration S, --seeds N, --set NAME=VALUE)
#   explore            guided exploration (the predicted surface's next touches) against random
#                      and coverage-greedy: map and completed-surface F@5mm of the whole true
#                      surface after 10-80 strokes, the prediction's calibration and cost
#                      (test/benchmarks/bench_explore.py: --objects, --modes, --explorers,
#                      --seeds, --strokes, --jobs, --keep DIR, --quick; --camera: the
#                      completed surface with a stereo pair's points instead)
#   startup            first start: build_map, occupancy_node and stereo_node with an empty
#                      numba cache and after compile_kernels (what bootstrap.sh runs)
#                      (test/benchmarks/bench_startup.py: --fresh-clone)
#   latency            live-view latency: poses published at 240 Hz x 4 in real time ->
#                      the cell in occupancy/updates, p50/p95 (test/benchmarks/
#                      bench_live_latency.py: --duration S, --seed N, --view, --exploration)
#   fuzz               the hypothesis properties of test/test_fuzz.py (Liberty parser, PoseStamped
#                      and PointCloud2 decoders, NPZ and PLY readers, parameter checks) on a
#                      million random inputs (test/benchmarks/fuzz.py: --inputs N, --jobs J,
#                      --round R, --targets NAME...)
#   soak               the live graph against the emulator for 30 min, a fault a minute, the
#                      occupancy node killed and resumed from its autosave once: crashes,
#                      memory, frames lost, the map against build_map of the recorded bag
#                      (test/benchmarks/soak.py: --minutes M, --fault-every S, --autosave S,
#                      --output DIR)
#   all                every benchmark in turn, each with the same options
# Examples:
#   bash launch_scripts/benchmark.sh --seconds 20
#   bash launch_scripts/benchmark.sh liberty --quick
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

# name -> script under test/benchmarks/; add further benchmarks here.
declare -A BENCHMARKS=(
  [liberty]=bench_liberty.py
  [mapping]=bench_mapping.py
  [replay]=bench_replay.py
  [stereo]=bench_stereo.py
  [stereo-bags]=bench_stereo_bags.py
  [stereo-node]=bench_stereo_node.py
  [vision]=bench_vision.py
  [texture]=bench_texture.py
  [texture-sessions]=bench_texture_sessions.py
  [quality]=bench_quality.py
  [validation]=bench_validation.py
  [fingers]=bench_fingers.py
  [startup]=bench_startup.py
  [latency]=bench_live_latency.py
  [fuzz]=fuzz.py
  [soak]=soak.py
  [shape]=bench_shape.py
  [explore]=bench_explore.py
  [cell-judge]=bench_cell_judge.py
)
ORDER=(liberty mapping replay stereo stereo-bags stereo-node vision texture texture-sessions quality validation cell-judge fingers shape explore startup latency fuzz soak)

WHICH=liberty
if [[ $# -gt 0 && "$1" != -* ]]; then
  WHICH="$1"
  shift
fi
if [[ "$WHICH" == all ]]; then
  SELECTED=("${ORDER[@]}")
elif [[ -n "${BENCHMARKS[$WHICH]:-}" ]]; then
  SELECTED=("$WHICH")
else
  echo "benchmark.sh: unknown benchmark '$WHICH'; choose one of: ${ORDER[*]} all" >&2
  exit 2
fi

bash "$ROOT/launch_scripts/bootstrap.sh"
cd "$ROOT"
status=0
for name in "${SELECTED[@]}"; do
  echo "### benchmark: $name ($(date -u +%Y-%m-%dT%H:%M:%SZ), $(nproc) cores)"
  "$ROOT/.venv/bin/python" "test/benchmarks/${BENCHMARKS[$name]}" "$@" || status=$?
done
exit "$status"
