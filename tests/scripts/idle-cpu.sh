#!/usr/bin/env bash
# Measures what an idle `phone2act serve` costs: CPU milliseconds per wall second (utime + stime from
# /proc/PID/stat) over a window with no client connected. A benchmark, not a test: it prints numbers.
#
#   tests/scripts/idle-cpu.sh [BINARY] [SECONDS]
#
# BINARY defaults to target/release/phone2act. Two configurations are measured: `minimal` (one simulated
# arm, no camera, no gateway: what the server itself costs) and `default` (the embedded default config: its
# rendered camera parks 2 s after its last reader, and its gateway waits for phones).
set -euo pipefail
cd "$(dirname "$0")/../.."
bin="${1:-$PWD/target/release/phone2act}"
window_s="${2:-20}"
bin="$(realpath "$bin")"
[[ -x "$bin" ]] || { echo "no binary at $bin (cargo build --release -p phone2act-cli --bin phone2act)" >&2; exit 2; }
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
clk_tck="$(getconf CLK_TCK)"
cat >"$work/minimal.toml" <<'EOF'
[server]
listen = "127.0.0.1:0"

[[arms]]
name = "main"
bridge = "sim"

[recorder]
root = "datasets"

[gateway]
enabled = false
EOF

# utime + stime of PID in clock ticks (fields 14 and 15; the command name in field 2 has no spaces here).
cpu_ticks() { awk '{print $14 + $15}' "/proc/$1/stat"; }

measure() {
  local name="$1"
  shift
  (cd "$work" && exec "$bin" serve "$@" >"$work/$name.log" 2>&1) &
  local pid=$!
  # Startup (bridge connect, camera and encoder threads) is not idle cost: let it settle first.
  sleep 3
  if ! kill -0 "$pid" 2>/dev/null; then
    echo "$name: server exited at startup:" >&2
    cat "$work/$name.log" >&2
    return 1
  fi
  local before after
  before="$(cpu_ticks "$pid")"
  sleep "$window_s"
  after="$(cpu_ticks "$pid")"
  kill -INT "$pid"
  wait "$pid" || true
  awk -v b="$before" -v a="$after" -v t="$clk_tck" -v w="$window_s" -v n="$name" \
    'BEGIN { printf "%-8s idle CPU: %.1f ms per second (%d ticks over %d s)\n", n, (a - b) * 1000 / t / w, a - b, w }'
}

measure minimal --config "$work/minimal.toml"
PHONE2ACT_GATEWAY__HTTPS_LISTEN=127.0.0.1:0 PHONE2ACT_GATEWAY__ROSBRIDGE_LISTEN=127.0.0.1:0 PHONE2ACT_GATEWAY__PRINT_QR=false \
  measure default --listen 127.0.0.1:0
