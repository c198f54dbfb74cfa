#!/usr/bin/env bash
# roslibpy (Python) against the real server through the gateway: publishes to /left/... and /right/..., reads
# feedback back through rosbridge subscriptions. Creates its venv outside the checkout on first use.
# Prints "N passed, M failed" and exits non-zero on failure.
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
VENV="${XDG_CACHE_HOME:-$HOME/.cache}/phone2act/gateway-venv"
if [[ ! -x "$VENV/bin/python" ]] || ! "$VENV/bin/python" -c 'import roslibpy, PIL' 2>/dev/null; then
  python3 -m venv "$VENV"
  "$VENV/bin/pip" install --quiet --disable-pip-version-check -r "$HERE/requirements.txt"
fi
STACK_CONFIG="$HERE/../../server/config/bimanual-sim.toml"
STACK_DEFAULT_ARM=left
source "$HERE/stack.sh"
"$VENV/bin/python" "$HERE/test_roslibpy.py" --port "$ROSBRIDGE_PORT"
