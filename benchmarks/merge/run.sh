#!/usr/bin/env bash
# Merge time and peak memory: `phone2act dataset merge` against lerobot's own `aggregate_datasets` on the same
# three inputs (copies of one dataset recorded by record-demo: one data, metadata and video file per episode,
# as a station writes them), each result loaded back by lerobot to check it.
#
# usage: benchmarks/merge/run.sh [--episodes N] [--out DIR] [--bin PATH]
#   --episodes N   episodes per input (default 100; each about 0.25 s, 2 cameras 64x64 AV1, 20 fps)
#   --bin PATH     the phone2act binary (default target/release/phone2act, else target/debug/phone2act)
# Needs the lerobot 0.6 venv (tests/lerobot_plugins/setup-venv.sh) and /usr/bin/time.
set -euo pipefail
repo="$(cd "$(dirname "$0")/../.." && pwd)"
episodes=100
out="$repo/target/merge-bench"
bin=""
while (($#)); do
  case "$1" in
    --episodes) episodes="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --bin) bin="$2"; shift 2 ;;
    *) echo "unknown option $1" >&2; exit 2 ;;
  esac
done
if [[ -z "$bin" ]]; then
  bin="$repo/target/release/phone2act"
  [[ -x "$bin" ]] || bin="$repo/target/debug/phone2act"
fi
demo="$(dirname "$bin")/record-demo"
venv="$("$repo/tests/lerobot_plugins/setup-venv.sh" | tail -n 1)"
export SVT_LOG=1 HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1
mkdir -p "$out"
base="$out/base-$episodes"
if [[ ! -f "$base/meta/info.json" ]]; then
  "$demo" "$base" --episodes "$episodes" --seconds 0.25 --size 64x64 >/dev/null
fi
for s in a b c; do
  rm -rf "$out/$s"
  cp -r "$base" "$out/$s"
done
echo "inputs: 3 x $episodes episodes, $(find "$out/a" -type f | wc -l) files each"
rm -rf "$out/phone2act" "$out/lerobot"
/usr/bin/time -f "phone2act merge: %e s wall, %M kB peak RSS" "$bin" dataset merge "$out/a" "$out/b" "$out/c" --out "$out/phone2act"
cat >"$out/aggregate.py" <<PY
from pathlib import Path
from lerobot.datasets.aggregate import aggregate_datasets
roots = [Path("$out") / s for s in "abc"]
aggregate_datasets(repo_ids=["local/" + r.name for r in roots], aggr_repo_id="local/lerobot", roots=roots,
                   aggr_root=Path("$out/lerobot"))
PY
/usr/bin/time -f "lerobot aggregate_datasets: %e s wall, %M kB peak RSS" "$venv/bin/python" "$out/aggregate.py" 2>&1 \
  | grep -E "aggregate_datasets:|Error" || true
echo "files out: phone2act $(find "$out/phone2act" -type f | wc -l), lerobot $(find "$out/lerobot" -type f | wc -l)"
HF_DATASETS_CACHE="$(mktemp -d)" "$venv/bin/python" "$repo/tests/conformance/check_merge.py" "$out/phone2act" \
  "$out/a" "$out/b" "$out/c" 2>&1 | grep -E "^(PASS|FAIL|[0-9]+ passed)"
