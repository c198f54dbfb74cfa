#!/usr/bin/env bash
# Creates (once) and reuses the Python environment the conformance checks run in: the newest lerobot that
# installs on this Python (0.4.4 on 3.11, reads v3.0) in a venv, and lerobot 0.3.3 (reads v2.1) in a side
# directory put on PYTHONPATH, because 0.3.3 pins datasets<=3.6 which conflicts with 0.4.x.
# The venv lives outside the checkout (about 8 GB) and is reused across runs and checkouts.
# Prints the venv directory on the last line of stdout.
set -euo pipefail
cache="${PHONE2ACT_CACHE_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/phone2act}"
venv="$cache/lerobot-venv"
v21="$cache/lerobot-0.3.3"
mkdir -p "$cache"
# A marker file written last means an interrupted install is redone instead of half-used.
if [[ ! -f "$venv/.phone2act-ready" ]]; then
  echo "conformance: installing lerobot into $venv (first run only, ~4.6 GB download, a few minutes)" >&2
  rm -rf "$venv"
  python3 -m venv "$venv"
  "$venv/bin/python" -m pip install --quiet --upgrade pip >&2
  "$venv/bin/python" -m pip install --quiet lerobot >&2
  touch "$venv/.phone2act-ready"
fi
if [[ ! -f "$v21/.phone2act-ready" ]]; then
  echo "conformance: installing lerobot 0.3.3 (v2.1 reader) into $v21" >&2
  rm -rf "$v21"
  "$venv/bin/python" -m pip install --quiet --no-deps --target "$v21" lerobot==0.3.3 datasets==3.6.0 >&2
  touch "$v21/.phone2act-ready"
fi
echo "$venv"
