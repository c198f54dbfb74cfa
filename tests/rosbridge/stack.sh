#!/usr/bin/env bash
# Sourced by tests/rosbridge/run.sh and tests/browser/run.sh: builds the `phone2act` server and the standalone
# `phone2act-gateway`, starts both on free loopback ports with a throw-away dataset, and stops them on exit.
#
# Inputs:  STACK_CONFIG (server config file, default: the embedded default), STACK_HTTPS=1 to serve the page,
#          STACK_GATEWAY_CONFIG (a file with the gateway's [gateway] table), STACK_DEFAULT_ARM, STACK_BIN_DIR (run
#          `phone2act` and `phone2act-gateway` from there instead of this tree's debug build: before/after runs).
# Outputs: GRPC_URL, ROSBRIDGE_PORT, HTTPS_PORT, PAIRING_TOKEN, STACK_DIR, SERVER_PID, GATEWAY_PID.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }

# Debug build: the same artefacts `cargo test` already built, so this costs seconds in the test run.
(cd "$REPO" && cargo build --quiet -p phone2act-cli --bin phone2act -p phone2act-gateway --bin phone2act-gateway)
TARGET_DIR="$(cd "$REPO" && cargo metadata --format-version 1 --no-deps | python3 -c 'import json,sys; print(json.load(sys.stdin)["target_directory"])')"
BIN="${STACK_BIN_DIR:-$TARGET_DIR/debug}"

STACK_DIR="$(mktemp -d -t phone2act-stack.XXXXXX)"
GRPC_PORT=$(free_port)
ROSBRIDGE_PORT=$(free_port)
HTTPS_PORT=$(free_port)
GRPC_URL="http://127.0.0.1:$GRPC_PORT"
PAIRING_TOKEN="stack-$(python3 -c 'import secrets; print(secrets.token_hex(8))')"
SERVER_PID=""
GATEWAY_PID=""

stack_stop() {
  local rc=$?
  # Only the two processes this script started, by pid.
  [[ -n "$GATEWAY_PID" ]] && kill "$GATEWAY_PID" 2>/dev/null || true
  [[ -n "$SERVER_PID" ]] && kill "$SERVER_PID" 2>/dev/null || true
  [[ -n "$GATEWAY_PID" ]] && wait "$GATEWAY_PID" 2>/dev/null || true
  [[ -n "$SERVER_PID" ]] && wait "$SERVER_PID" 2>/dev/null || true
  if [[ $rc -ne 0 ]]; then
    # Keep the logs of a failed run where they can be read after the temporary directory is gone.
    local keep="${TMPDIR:-/tmp}/phone2act-stack-logs"
    mkdir -p "$keep" && cp "$STACK_DIR"/*.log "$keep"/ 2>/dev/null && echo "server and gateway logs kept in $keep" >&2
  fi
  rm -rf "$STACK_DIR"
}
trap stack_stop EXIT

config_args=()
[[ -n "${STACK_CONFIG:-}" ]] && config_args=(--config "$STACK_CONFIG")
# This stack runs the standalone gateway on free ports; a server that embeds one would also bind the default
# 9090/8443, so turn that off when the server knows the key.
if PHONE2ACT_GATEWAY__ENABLED=false "$BIN/phone2act" serve "${config_args[@]}" --check >/dev/null 2>&1; then
  export PHONE2ACT_GATEWAY__ENABLED=false
fi
SVT_LOG=1 PHONE2ACT_RECORDER__ROOT="$STACK_DIR/dataset" RUST_LOG="${RUST_LOG:-info}" \
  "$BIN/phone2act" serve "${config_args[@]}" --listen "127.0.0.1:$GRPC_PORT" >"$STACK_DIR/server.log" 2>&1 &
SERVER_PID=$!

gateway_args=(--server "$GRPC_URL" --rosbridge-listen "127.0.0.1:$ROSBRIDGE_PORT" --no-qr
  --cert-dir "$STACK_DIR/cert" --public-host 127.0.0.1 --token "$PAIRING_TOKEN")
if [[ "${STACK_HTTPS:-0}" == 1 ]]; then
  gateway_args+=(--https-listen "127.0.0.1:$HTTPS_PORT")
else
  gateway_args+=(--no-https)
fi
[[ -n "${STACK_DEFAULT_ARM:-}" ]] && gateway_args+=(--default-arm "$STACK_DEFAULT_ARM")
[[ -n "${STACK_GATEWAY_CONFIG:-}" ]] && gateway_args+=(--config "$STACK_GATEWAY_CONFIG")
RUST_LOG="${RUST_LOG:-info}" "$BIN/phone2act-gateway" "${gateway_args[@]}" >"$STACK_DIR/gateway.log" 2>&1 &
GATEWAY_PID=$!

wait_port() {
  for _ in $(seq 1 200); do
    if python3 -c "import socket,sys; socket.create_connection(('127.0.0.1',$1),0.2)" 2>/dev/null; then return 0; fi
    sleep 0.1
  done
  echo "port $1 did not open; server log:" >&2
  cat "$STACK_DIR/server.log" "$STACK_DIR/gateway.log" >&2
  return 1
}
wait_port "$GRPC_PORT"
wait_port "$ROSBRIDGE_PORT"
[[ "${STACK_HTTPS:-0}" == 1 ]] && wait_port "$HTTPS_PORT"
export GRPC_URL ROSBRIDGE_PORT HTTPS_PORT PAIRING_TOKEN STACK_DIR
