#!/usr/bin/env bash
# Lists, ends and reports every process still alive that was started under this test run: each carries the run's
# PHONE2ACT_TEST_RUN_ID in its environment, however far it was re-parented (a launcher that exited, a daemon
# that detached). Exit 1 when any was found, so a suite that leaves a process behind fails `make test`.
# Usage: tests/scripts/leftover-processes.sh RUN_ID
set -euo pipefail
run_id="${1:?usage: leftover-processes.sh RUN_ID}"
# This script and the shells above it carry the same variable: they are not leftovers.
skip=" $$ $PPID "
pid=$PPID
while [[ $pid -gt 1 ]]; do
  pid=$(awk '{print $4}' "/proc/$pid/stat" 2>/dev/null || echo 1)
  skip+="$pid "
done
found=()
for env in /proc/[0-9]*/environ; do
  pid=${env#/proc/}
  pid=${pid%/environ}
  [[ $skip == *" $pid "* ]] && continue
  if { tr '\0' '\n' <"$env"; } 2>/dev/null | grep -qx "PHONE2ACT_TEST_RUN_ID=$run_id"; then
    # The scan's own pipelines (children of this script) carry the variable too.
    parent=$(awk '{print $4}' "/proc/$pid/stat" 2>/dev/null || echo 0)
    [[ $parent == "$$" ]] && continue
    cmd=$({ tr '\0' ' ' <"/proc/$pid/cmdline"; } 2>/dev/null || true)
    [[ -z $cmd ]] && continue
    found+=("$pid $cmd")
  fi
done
if ((${#found[@]} == 0)); then
  exit 0
fi
echo "processes left behind by the test run (ended now):" >&2
for line in "${found[@]}"; do
  echo "  $line" >&2
  kill -KILL "${line%% *}" 2>/dev/null || true
done
exit 1
