#!/usr/bin/env bash
# Provides the S3 server the storage tests (tests/tests/fleet.rs) start on loopback: moto's server from PyPI,
# in a venv outside the checkout (${XDG_CACHE_HOME:-~/.cache}/phone2act/moto), created once and reused. Prints
# the path of its `moto_server` executable; test-all.sh exports it as PHONE2ACT_MOTO_SERVER. Without it the
# fleet tests skip, loudly.
set -euo pipefail
VENV="${XDG_CACHE_HOME:-$HOME/.cache}/phone2act/moto"
if [[ ! -x "$VENV/bin/moto_server" ]]; then
  python3 -m venv "$VENV" >&2
  "$VENV/bin/pip" install -q --upgrade pip >&2
  # 5.x: the version line these tests were written against (S3 user metadata, multipart, request log).
  "$VENV/bin/pip" install -q "moto[server]>=5,<6" >&2
fi
echo "$VENV/bin/moto_server"
