#!/usr/bin/env bash
# `buf lint` over proto/ with the repository's buf.yaml (STANDARD rules; the exceptions are explained there).
# buf comes from npm (@bufbuild/buf), pinned, installed once under target/ (outside git's interest).
set -euo pipefail
cd "$(dirname "$0")/../.."
BUF_DIR="${CARGO_TARGET_DIR:-$PWD/target}/buf"
if [[ ! -x "$BUF_DIR/node_modules/.bin/buf" ]]; then
  command -v npm >/dev/null || { echo "lint-proto: npm is needed to fetch buf (Debian: apt install npm)" >&2; exit 1; }
  mkdir -p "$BUF_DIR"
  npm install --silent --prefix "$BUF_DIR" @bufbuild/buf@1.75.0 >/dev/null
fi
"$BUF_DIR/node_modules/.bin/buf" lint
echo "buf lint: clean ($(ls proto/phone2act/v1/*.proto | wc -l) files)"
