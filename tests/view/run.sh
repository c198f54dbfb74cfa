#!/usr/bin/env bash
# The live view (clients/view) against a real phone2act server, its .rrd files read back with rerun-sdk's own
# reader. Its own venv (rerun-sdk is ~500 MB; the other Python suites don't need it), outside the checkout and
# reused between runs; server binary from cargo unless PHONE2ACT_BIN is set. Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/../.."
REPO=$PWD

VENV="${XDG_CACHE_HOME:-$HOME/.cache}/phone2act/view-venv"
# rerun-sdk within the range lerobot's `viz` extra accepts (<0.34), and >=0.32 for rerun's RrdReader, which
# the test reads the .rrd files with.
PY_REQ=(pytest "rerun-sdk>=0.32,<0.34")
if [[ ! -x "$VENV/bin/python" ]]; then
  python3 -m venv "$VENV"
  "$VENV/bin/pip" install -q --upgrade pip
fi
"$VENV/bin/pip" install -q "${PY_REQ[@]}" ./sdk/python ./clients/view

if [[ -z "${PHONE2ACT_BIN:-}" ]]; then
  cargo build --release -p phone2act-cli --bin phone2act
  PHONE2ACT_BIN="${CARGO_TARGET_DIR:-$REPO/target}/release/phone2act"
fi
export PHONE2ACT_BIN
export SVT_LOG=1

cd tests/view
exec "$VENV/bin/python" -m pytest -q -p no:cacheprovider "$@"
