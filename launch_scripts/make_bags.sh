#!/usr/bin/env bash
# Regenerate the bundled bags bit for bit (simulated sessions, seeded; each bag folder has
# its ground truth beside it as <name>.truth.npz).
#   bash launch_scripts/make_bags.sh [DIR]     (default DIR: bags)
#   cat_static   the cat fixed on the table, no object sensor, 120 s at 15 Hz (the paper's rate)
#   cat_moving   the cat held, moved and re-grasped by the other hand, 120 s at 15 Hz (the
#                paper's rate and the static cat's duration: the two maps compare on equal terms)
#   bottle_static  the wine bottle on the table, 120 s at 15 Hz
# Each with one stereo image pair of the object at its first frame (--stereo), taken by the
# virtual rig of config/stereo.yaml.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/launch_scripts/bootstrap.sh"
SIM="$ROOT/.venv/bin/simulate_session"
# numpy computes float64 sin/cos/exp with Intel's SVML on AVX-512 machines and with libm
# elsewhere; the two differ in the last bit, and the bags would differ with the CPU. Keep numpy
# on its AVX2 (libm) paths everywhere so the bags are the same on every x86_64 machine.
export NPY_DISABLE_CPU_FEATURES="X86_V4 AVX512_ICL AVX512_SPR"
# Likewise OpenBLAS (numpy's matrix products) picks its kernels by CPU: the Haswell (AVX2)
# ones everywhere.
export OPENBLAS_CORETYPE=Haswell
cd "$ROOT"
DIR="${1:-bags}"
mkdir -p "$DIR"
"$SIM" --object cat --static --rate 15 --duration 120 --seed 1 --stereo --output "$DIR/cat_static" --force --quiet
"$SIM" --object cat --moving --regrasp --rate 15 --duration 120 --seed 1 --stereo --output "$DIR/cat_moving" --force --quiet
"$SIM" --object bottle --static --rate 15 --duration 120 --seed 3 --stereo --output "$DIR/bottle_static" --force --quiet
du -sh "$DIR"/* | sed 's/^/[make_bags] /'
