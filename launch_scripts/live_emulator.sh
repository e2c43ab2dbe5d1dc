#!/usr/bin/env bash
# Live mode without hardware: emulator, driver, registration and occupancy nodes
# (see live_emulator.py --help). Ctrl-C saves the map and stops everything.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/launch_scripts/bootstrap.sh"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
exec "$ROOT/.venv/bin/python" "$ROOT/launch_scripts/live_emulator.py" "$@"
