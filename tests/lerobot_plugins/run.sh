#!/usr/bin/env bash
# The LeRobot plugins (clients/lerobot_robot_phone2act, clients/lerobot_teleoperator_phone2act) against a real
# `phone2act serve`, with lerobot 0.6.1 (Python 3.12) discovering them as it discovers any plugin.
# Venv: ${PHONE2ACT_CACHE_DIR:-~/.cache/phone2act}/lerobot06-venv (setup-venv.sh; created once, reused).
# Server binary from cargo unless PHONE2ACT_BIN is set. Extra arguments go to pytest (-k teleop -x ...).
set -euo pipefail
cd "$(dirname "$0")/../.."
source tests/scripts/python-suite.sh

if ! VENV="$(tests/lerobot_plugins/setup-venv.sh | tail -n 1)" || [[ ! -x "$VENV/bin/python" ]]; then
  echo "lerobot plugins: cannot create the lerobot 0.6 venv (see above); tests NOT run" >&2
  exit 2
fi
# Reinstalled every run (a few seconds): picks up edits to the SDK, the proto and the plugins. Not editable, so
# lerobot discovers them exactly as a user's `pip install` leaves them.
"$VENV/bin/python" -m pip install -q ./sdk/python ./clients/lerobot_robot_phone2act \
  ./clients/lerobot_teleoperator_phone2act ./clients/replay

server_binary
# lerobot must never reach for the Hub here: datasets are local, calibration files go to a scratch HF_HOME.
export HF_HUB_OFFLINE=1
HF_HOME="$(mktemp -d)"
export HF_HOME
trap 'rm -rf "$HF_HOME"' EXIT

cd tests/lerobot_plugins
"$VENV/bin/python" -m pytest -q -p no:cacheprovider "$@"
