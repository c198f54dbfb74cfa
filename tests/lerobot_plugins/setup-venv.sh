#!/usr/bin/env bash
# Creates (once) and reuses the Python 3.12 environment with lerobot 0.6.1 that the LeRobot plugin tests run
# in (lerobot 0.6 needs Python >= 3.12; Debian 12's python3 is 3.11). Lives outside the checkout and is
# reused across runs and checkouts. Prints the venv directory on the last line of stdout.
set -euo pipefail
cache="${PHONE2ACT_CACHE_DIR:-$HOME/.cache/phone2act}"
venv="$cache/lerobot06-venv"
# The `dataset` extra: lerobot-record and lerobot-replay need it; `feetech`: feetech-servo-sdk, for lerobot's own
# Feetech client against the bus emulator (tests/feetech_upstream); `training`: lerobot-train (the closed-loop
# benchmark, benchmarks/closed_loop).
spec="lerobot[dataset,training,feetech]==0.6.1"
mkdir -p "$cache"
# A marker file written last (holding what was installed) means an interrupted or outdated install is redone
# instead of half-used.
find_python() {
  local cand
  for cand in python3.12 python3.13 "$HOME"/.pyenv/versions/3.12*/bin/python "$HOME"/.pyenv/versions/3.13*/bin/python; do
    if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; assert sys.version_info[:2] >= (3, 12)' 2>/dev/null; then
      echo "$cand"
      return 0
    fi
  done
  return 1
}
# `--which-python`: print the interpreter that would be used, or exit 3 when there is none.
if [[ "${1:-}" == "--which-python" ]]; then
  find_python || exit 3
  exit 0
fi
if [[ "$(cat "$venv/.phone2act-ready" 2>/dev/null)" != "$spec" ]]; then
  py="$(find_python || true)"
  if [[ -z "$py" ]]; then
    echo "lerobot plugins: no Python >= 3.12 found (tried python3.12 on PATH and pyenv's 3.12.1);" \
      "lerobot 0.6 needs it. Install one (e.g. pyenv install 3.12) and rerun." >&2
    exit 2
  fi
  echo "lerobot plugins: installing lerobot 0.6.1 into $venv with $py (first run only, a few GB, a few minutes)" >&2
  if [[ ! -x "$venv/bin/python" ]]; then
    "$py" -m venv "$venv"
    "$venv/bin/python" -m pip install --quiet --upgrade pip >&2
  fi
  "$venv/bin/python" -m pip install --quiet "$spec" pytest >&2
  echo "$spec" > "$venv/.phone2act-ready"
fi
echo "$venv"
