#!/usr/bin/env bash
# Python SDK, GR00T adapter, replay client and example bridge tests against a real phone2act server.
# Venv outside the checkout (reused between runs); server binary from cargo unless PHONE2ACT_BIN is set.
# Extra arguments go to pytest (e.g. tests/python/run.sh -k replay -x).
set -euo pipefail
cd "$(dirname "$0")/../.."
REPO=$PWD

VENV="${XDG_CACHE_HOME:-$HOME/.cache}/phone2act/py-venv"
PY_REQ=(pytest "pyzmq>=25" "msgpack>=1.0" "numpy>=1.24" "pyarrow>=14")
if [[ ! -x "$VENV/bin/python" ]]; then
  python3 -m venv "$VENV"
  "$VENV/bin/pip" install -q --upgrade pip
fi
# The SDK generates its stubs from proto/ at build time; reinstalling picks up proto edits.
"$VENV/bin/pip" install -q "${PY_REQ[@]}" ./sdk/python ./clients/gr00t ./clients/replay

if [[ -z "${PHONE2ACT_BIN:-}" ]]; then
  cargo build --release -p phone2act-cli --bin phone2act
  PHONE2ACT_BIN="${CARGO_TARGET_DIR:-$REPO/target}/release/phone2act"
fi
export PHONE2ACT_BIN
export SVT_LOG=1

cd tests/python
exec "$VENV/bin/python" -m pytest -q -p no:cacheprovider "$@"
