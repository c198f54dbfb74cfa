#!/usr/bin/env bash
# The Python environment the conformance checks run in: the one venv the LeRobot plugin tests and the
# closed-loop benchmark use (lerobot 0.6.1 on Python >= 3.12, tests/lerobot_plugins/setup-venv.sh; reads v3.0),
# plus lerobot 0.3.3 (reads v2.1) in a side directory put on PYTHONPATH only for the v2.1 checks: 0.3.3 pins
# datasets<=3.6 where 0.6.1 needs datasets>=4.8, so the two cannot share one site-packages; both it and
# datasets 3.6.0 are pure Python and run on the venv's torch, numpy and pyarrow.
# Everything lives outside the checkout and is reused across runs and checkouts.
# Prints the venv directory on the last line of stdout; exits 2 when no Python >= 3.12 exists.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
venv="$("$here/../lerobot_plugins/setup-venv.sh" | tail -n 1)"
v21="$(dirname "$venv")/lerobot-0.3.3"
# A marker file written last means an interrupted install is redone instead of half-used.
if [[ ! -f "$v21/.phone2act-ready" ]]; then
  echo "conformance: installing lerobot 0.3.3 (v2.1 reader) into $v21" >&2
  rm -rf "$v21"
  "$venv/bin/python" -m pip install --quiet --no-deps --target "$v21" lerobot==0.3.3 datasets==3.6.0 >&2
  touch "$v21/.phone2act-ready"
fi
# GR00T's decord reader, in a side directory of its own: decord bundles its own FFmpeg libraries, so it is put
# on PYTHONPATH only for the conformance checks (which import it after every torchcodec check), never into the
# venv that the plugin tests and the closed loop share. No decord wheel exists for some platforms: the frame
# pairing check then reports the decord reader as skipped.
backends="$(dirname "$venv")/gr00t-video-backends"
if [[ ! -f "$backends/.phone2act-ready" ]]; then
  echo "conformance: installing decord 0.6.0 (GR00T's video reader) into $backends" >&2
  rm -rf "$backends"
  if "$venv/bin/python" -m pip install --quiet --no-deps --target "$backends" decord==0.6.0 >&2; then
    touch "$backends/.phone2act-ready"
  else
    echo "conformance: decord cannot be installed here; GR00T's decord reader will be reported as SKIPPED" >&2
  fi
fi
echo "$venv"
