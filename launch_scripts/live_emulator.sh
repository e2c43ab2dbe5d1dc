#!/usr/bin/env bash
# Live mode without hardware: an emulated Liberty on a pty and the driver node reading it.
#
#   bash launch_scripts/live_emulator.sh [--duration SECONDS] [--motion builtin|FILE.txt|BAG]
#                                        [--format binary|ascii]
#
# Publishes polhemus/{thumb,index,middle,object}/pose and diagnostics. Ctrl-C (or the end
# of --duration) stops both processes cleanly: the driver sends P and closes the port.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
DURATION=""
MOTION="builtin"
FORMAT="binary"
while [[ $# -gt 0 ]]; do
  case "$1" in
    --duration) DURATION="$2"; shift 2 ;;
    --motion) MOTION="$2"; shift 2 ;;
    --format) FORMAT="$2"; shift 2 ;;
    -h|--help) sed -n '2,9p' "$0"; exit 0 ;;
    *) echo "live_emulator.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done
bash "$ROOT/launch_scripts/bootstrap.sh"
BIN="$ROOT/.venv/bin"
PORT="/tmp/liberty-live-$$"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"

PIDS=()
cleanup() {
  trap - EXIT INT TERM
  # Last started first: the driver stops the device (P) while the device is still there.
  for ((i = ${#PIDS[@]} - 1; i >= 0; i--)); do
    kill -INT "${PIDS[i]}" 2>/dev/null || true
    for _ in $(seq 50); do kill -0 "${PIDS[i]}" 2>/dev/null || break; sleep 0.1; done
    kill -KILL "${PIDS[i]}" 2>/dev/null || true
  done
  wait 2>/dev/null || true
}
trap cleanup EXIT INT TERM

"$BIN/liberty_emulator" --port "$PORT" --motion "$MOTION" --status-every 5 < /dev/null &
PIDS+=($!)
"$BIN/liberty_driver" --ros-args --params-file "$ROOT/config/liberty_emulator.yaml" \
  -p "port:=$PORT" -p "output_format:=$FORMAT" &
PIDS+=($!)
echo "live_emulator: emulator on $PORT, driver publishing polhemus/<name>/pose (Ctrl-C to stop)"
if [[ -n "$DURATION" ]]; then
  sleep "$DURATION"
else
  wait -n "${PIDS[@]}"
fi
