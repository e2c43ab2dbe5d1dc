#!/usr/bin/env bash
# The workspace's test command: sets up .venv if needed, then runs every test under test/.
# Extra arguments go to pytest (e.g. -k codec, -x, -q).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/launch_scripts/bootstrap.sh"
# The live view's page test takes screenshots with headless Chromium (Debian's package):
# installed on CI and wherever it is missing and apt-get can install it.
if [[ "${CI:-}" == true ]] || { ! command -v chromium >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; }; then
  bash "$ROOT/launch_scripts/install_browser.sh" || echo "[run_tests] no chromium: the live view's page test will say so" >&2
fi
cd "$ROOT"
exec "$ROOT/.venv/bin/python" -m pytest test "$@"
