#!/usr/bin/env bash
# The live view (clients/view) against a real phone2act server, its .rrd files read back with rerun-sdk's own
# reader. Its own venv (rerun-sdk is ~500 MB; the other Python suites don't need it), outside the checkout and
# reused between runs; server binary from cargo unless PHONE2ACT_BIN is set. Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/../.."
source tests/scripts/python-suite.sh

# rerun-sdk within the range lerobot's `viz` extra accepts (<0.34), and >=0.32 for rerun's RrdReader, which
# the test reads the .rrd files with.
py_venv view-venv pytest "rerun-sdk>=0.32,<0.34" ./sdk/python ./clients/view

server_binary

cd tests/view
exec "$VENV/bin/python" -m pytest -q -p no:cacheprovider "$@"
