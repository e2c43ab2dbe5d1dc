#!/usr/bin/env bash
# Replay any bag of the driver's topics through the mapping graph (see replay_bag.py --help).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/launch_scripts/bootstrap.sh"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
exec "$ROOT/.venv/bin/python" "$ROOT/launch_scripts/replay_bag.py" "$@"
