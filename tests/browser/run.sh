#!/usr/bin/env bash
# Browser test of the phone page: Debian's Chromium, headless, driven by playwright-core, WebXR from a test shim,
# against the real server and the gateway (built with cargo). Installs what is missing (apt chromium, npm ci).
# Prints "N passed, M failed" and exits non-zero on failure.
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
if [[ ! -x /usr/bin/chromium ]]; then
  if [[ $(id -u) -eq 0 ]]; then SUDO=(); else SUDO=(sudo); fi
  "${SUDO[@]}" apt-get update -qq
  DEBIAN_FRONTEND=noninteractive "${SUDO[@]}" apt-get install -y -qq --no-install-recommends chromium >/dev/null
fi
if [[ ! -d "$HERE/node_modules/playwright-core" ]]; then
  # playwright-core downloads no browser; the lockfile pins it to the npm registry's tarball.
  (cd "$HERE" && npm ci --no-audit --no-fund --silent)
fi
STACK_HTTPS=1
source "$HERE/../rosbridge/stack.sh"
cd "$HERE"
node --experimental-websocket --no-warnings test_page.mjs
