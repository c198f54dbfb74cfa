#!/usr/bin/env bash
# Python SDK, GR00T adapter, replay client and example bridge tests against a real phone2act server.
# Venv outside the checkout (reused between runs); server binary from cargo unless PHONE2ACT_BIN is set.
# Extra arguments go to pytest (e.g. tests/python/run.sh -k replay -x).
set -euo pipefail
cd "$(dirname "$0")/../.."
source tests/scripts/python-suite.sh

py_venv py-venv pytest "pyzmq>=25" "msgpack>=1.0" "numpy>=1.24" "pyarrow>=14" \
  ./sdk/python ./clients/gr00t ./clients/replay

server_binary

cd tests/python
exec "$VENV/bin/python" -m pytest -q -p no:cacheprovider "$@"
