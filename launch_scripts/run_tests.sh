#!/usr/bin/env bash
# The workspace's test command: sets up .venv if needed, then runs every test under test/.
# Extra arguments go to pytest (e.g. -k codec, -x, -q).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/launch_scripts/bootstrap.sh"
cd "$ROOT"
exec "$ROOT/.venv/bin/python" -m pytest test "$@"
