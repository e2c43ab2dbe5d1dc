#!/usr/bin/env bash
# The main job: set up the workspace if needed, then replay the bundled non-static cat
# session through the mapping graph; writes the map, its pictures and metrics to
# output/demo/.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/launch_scripts/bootstrap.sh"
cd "$ROOT"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
exec "$ROOT/.venv/bin/python" "$ROOT/launch_scripts/demo.py" "$@"
