#!/usr/bin/env bash
# lerobot's own Feetech client (FeetechMotorsBus, SO101Follower; lerobot 0.6.1 with feetech-servo-sdk) against
# phone2act's Feetech bus emulator on a pseudo-terminal, and phone2act's SO-101 bridge against lerobot on the same
# bus and calibration file. Venv: the LeRobot plugin suite's (tests/lerobot_plugins/setup-venv.sh).
# Binaries from cargo unless FEETECH_EMULATOR and SO101_CHECK are set. Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/../.."

if ! VENV="$(tests/lerobot_plugins/setup-venv.sh | tail -n 1)" || [[ ! -x "$VENV/bin/python" ]]; then
  echo "feetech upstream: cannot create the lerobot 0.6 venv (see above); tests NOT run" >&2
  exit 2
fi
if [[ -z "${FEETECH_EMULATOR:-}" || -z "${SO101_CHECK:-}" ]]; then
  cargo build --release -p phone2act-bridges --features emulators --bin feetech-emulator --bin so101-check
  target="${CARGO_TARGET_DIR:-$PWD/target}/release"
  FEETECH_EMULATOR="$target/feetech-emulator"
  SO101_CHECK="$target/so101-check"
fi
export FEETECH_EMULATOR SO101_CHECK
# Calibration files go to each test's own directory; lerobot must not reach for the Hub.
export HF_HUB_OFFLINE=1
HF_HOME="$(mktemp -d)"
export HF_HOME
trap 'rm -rf "$HF_HOME"' EXIT

cd tests/feetech_upstream
"$VENV/bin/python" -m pytest -q -p no:cacheprovider "$@"
