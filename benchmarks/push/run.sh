#!/usr/bin/env bash
# Push throughput to S3-compatible storage on loopback: `phone2act dataset push` against `rclone copy`
# (Debian's rclone) on the same dataset and the same moto server (tests/scripts/s3-server.sh), each into an
# empty prefix, wall time by `/usr/bin/time`.
#
# usage: benchmarks/push/run.sh DATASET [--pad] [--bin PATH]
#   --pad   push a copy with one 64 MiB and twenty 1 MiB random files added under extra/ (video-sized objects;
#           the recorded test-pattern videos compress to a few kB each)
set -euo pipefail
repo="$(cd "$(dirname "$0")/../.." && pwd)"
dataset="$1"; shift
bin="$repo/target/release/phone2act"
[[ -x "$bin" ]] || bin="$repo/target/debug/phone2act"
pad=0
while (($#)); do
  case "$1" in
    --pad) pad=1; shift ;;
    --bin) bin="$2"; shift 2 ;;
    *) echo "unknown option $1" >&2; exit 2 ;;
  esac
done
if ((pad)); then
  scratch="$(mktemp -d)"
  trap 'rm -rf "$scratch"' EXIT
  cp -r "$dataset" "$scratch/ds"
  dataset="$scratch/ds"
  mkdir -p "$dataset/extra"
  head -c $((64 << 20)) /dev/urandom >"$dataset/extra/blob-64MiB.bin"
  for i in $(seq -w 1 20); do head -c $((1 << 20)) /dev/urandom >"$dataset/extra/blob-1MiB-$i.bin"; done
fi
command -v rclone >/dev/null || { echo "push bench: rclone is needed (Debian: apt install rclone)" >&2; exit 2; }
moto="$("$repo/tests/scripts/s3-server.sh")"
port="$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')"
"$moto" -H 127.0.0.1 -p "$port" >/dev/null 2>&1 &
moto_pid=$!
trap 'kill "$moto_pid" 2>/dev/null || true; rm -rf "${scratch:-}"' EXIT
ep="http://127.0.0.1:$port"
for _ in $(seq 100); do curl -s "$ep/" >/dev/null && break; sleep 0.2; done
# Plain HTTP on loopback: a CA bundle from the environment only makes rclone refuse its own transport.
unset AWS_CA_BUNDLE
export AWS_ACCESS_KEY_ID=bench AWS_SECRET_ACCESS_KEY=bench AWS_REGION=us-east-1
# rclone's remote from the environment (no config file): "bench:" is S3 at the moto endpoint.
export RCLONE_CONFIG_BENCH_TYPE=s3 RCLONE_CONFIG_BENCH_PROVIDER=Other RCLONE_CONFIG_BENCH_ENDPOINT="$ep" \
  RCLONE_CONFIG_BENCH_ACCESS_KEY_ID=bench RCLONE_CONFIG_BENCH_SECRET_ACCESS_KEY=bench \
  RCLONE_CONFIG_BENCH_REGION=us-east-1 RCLONE_CONFIG=/dev/null RCLONE_LOW_LEVEL_RETRIES=1 RCLONE_RETRIES=1
remote="bench:bench"
rclone mkdir "$remote"
bytes="$(du -sb --exclude='.phone2act-*' "$dataset" | cut -f1)"
files="$(find "$dataset" -type f -not -path '*/.phone2act-*' | wc -l)"
echo "dataset: $files files, $bytes bytes"
rate() { python3 -c "import sys; print(f'{int(sys.argv[1])/float(sys.argv[2])/1e6:.1f} MB/s')" "$bytes" "$1"; }
t0=$(date +%s.%N)
/usr/bin/time -f "phone2act push: %e s wall, %M kB peak RSS" "$bin" dataset push "$dataset" s3://bench/phone2act --endpoint "$ep" >/dev/null
t1=$(date +%s.%N)
echo "phone2act push: $(rate "$(echo "$t1 - $t0" | bc)")"
t0=$(date +%s.%N)
/usr/bin/time -f "rclone copy: %e s wall, %M kB peak RSS" rclone copy --exclude '.phone2act-*/**' --exclude '.phone2act-*' "$dataset" "$remote/rclone"
t1=$(date +%s.%N)
echo "rclone copy: $(rate "$(echo "$t1 - $t0" | bc)")"
t0=$(date +%s.%N)
/usr/bin/time -f "rclone copy --transfers 1: %e s wall, %M kB peak RSS" rclone copy --transfers 1 --checkers 1 --exclude '.phone2act-*/**' --exclude '.phone2act-*' "$dataset" "$remote/rclone-1"
t1=$(date +%s.%N)
echo "rclone copy --transfers 1: $(rate "$(echo "$t1 - $t0" | bc)")"
