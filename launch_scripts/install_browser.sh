#!/usr/bin/env bash
# Install headless Chromium from Debian's packages (the live view's page test takes its
# screenshots with it). Nothing to do when a chromium is on PATH already.
#
# run_tests.sh calls this on CI (CI=true) and whenever chromium is missing and apt-get is
# there; it needs root (or passwordless sudo). It took 15 s here (apt-get update, then
# chromium and its libraries without the recommended extras).
#
# Usage: bash launch_scripts/install_browser.sh
set -euo pipefail

say() { printf '[install_browser] %s\n' "$*" >&2; }

for name in chromium chromium-browser; do
  if command -v "$name" >/dev/null 2>&1; then
    exit 0
  fi
done
if ! command -v apt-get >/dev/null 2>&1; then
  say "no chromium and no apt-get: install Chromium by hand for the live view's page test"
  exit 1
fi
SUDO=()
if [[ "$(id -u)" != 0 ]]; then
  if command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    SUDO=(sudo -n)
  else
    say "installing chromium needs root: run 'apt-get install chromium' as root"
    exit 1
  fi
fi
started=$SECONDS
say "installing chromium from Debian's packages"
export DEBIAN_FRONTEND=noninteractive
"${SUDO[@]}" apt-get update -qq
"${SUDO[@]}" apt-get install -y -qq --no-install-recommends chromium >/dev/null
say "chromium installed in $((SECONDS - started)) s: $(chromium --version 2>/dev/null || echo '?')"
