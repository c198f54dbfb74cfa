#!/usr/bin/env bash
# Browser tests of the phone page: Debian's Chromium, headless, driven by playwright-core, against the real server
# and the gateway (built with cargo). The phone path gets WebXR from a test shim (test_page.mjs, one arm); headset
# controllers and iPhone browser apps get it from Meta's emulator iwer (test_headset.mjs, two arms, and the live
# video on a panel in the immersive session); live video
# against control, on a throttled link and through the gateway's stalls, in test_video.mjs, and [gateway.video] (off; a
# camera scaled down) in test_video_config.mjs; the recording habits (outcome buttons, countdown,
# SAVE LAST) in test_habits.mjs; a policy
# session's plan preview and the hand-back in test_handback.mjs. Installs
# what is missing (apt chromium, npm ci). Prints "N passed, M failed" per suite and exits non-zero on failure.
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
if [[ ! -x /usr/bin/chromium ]]; then
  if [[ $(id -u) -eq 0 ]]; then SUDO=(); else SUDO=(sudo); fi
  "${SUDO[@]}" apt-get update -qq
  DEBIAN_FRONTEND=noninteractive "${SUDO[@]}" apt-get install -y -qq --no-install-recommends chromium >/dev/null
fi
if [[ ! -d "$HERE/node_modules/playwright-core" || ! -d "$HERE/node_modules/iwer" ]]; then
  # playwright-core downloads no browser; the lockfile pins both to the npm registry's tarballs.
  (cd "$HERE" && npm ci --no-audit --no-fund --silent)
fi
# Each suite in a subshell of its own: stack.sh stops its server and gateway when that subshell exits.
# BROWSER_SUITES=headset (or page, habits, handback, video) runs one.
suites="${BROWSER_SUITES:-page headset habits handback video}"
rc=0
if [[ "$suites" == *page* ]]; then
  (
    STACK_HTTPS=1
    source "$HERE/../rosbridge/stack.sh"
    cd "$HERE"
    node --experimental-websocket --no-warnings test_page.mjs
  ) || rc=1
fi
if [[ "$suites" == *headset* ]]; then
  (
    STACK_HTTPS=1
    STACK_CONFIG="$HERE/../../server/config/bimanual-sim.toml"
    STACK_DEFAULT_ARM=left
    STACK_GATEWAY_CONFIG="$HERE/headset-gateway.toml"
    source "$HERE/../rosbridge/stack.sh"
    cd "$HERE"
    node --experimental-websocket --no-warnings test_headset.mjs
  ) || rc=1
fi
if [[ "$suites" == *habits* ]]; then
  # Recording habits (outcome buttons), on a stack of its own so its dataset holds only its episodes.
  (
    STACK_HTTPS=1
    source "$HERE/../rosbridge/stack.sh"
    cd "$HERE"
    node --experimental-websocket --no-warnings test_habits.mjs outcome
  ) || rc=1
  (
    STACK_HTTPS=1
    # A short episode limit and reset period, and the next episode started after each reset.
    export EPISODE_TIME_S=2 RESET_TIME_S=2
    export PHONE2ACT_RECORDER__EPISODE_TIME_S=$EPISODE_TIME_S PHONE2ACT_RECORDER__RESET_TIME_S=$RESET_TIME_S
    export PHONE2ACT_RECORDER__START_NEXT_AFTER_RESET=true
    source "$HERE/../rosbridge/stack.sh"
    cd "$HERE"
    node --experimental-websocket --no-warnings test_habits.mjs countdown
  ) || rc=1
  (
    STACK_HTTPS=1
    # The last seconds kept while idle, saved with the page's SAVE LAST button.
    export HIGHLIGHT_S=2 PHONE2ACT_RECORDER__HIGHLIGHT_S=2
    source "$HERE/../rosbridge/stack.sh"
    cd "$HERE"
    node --experimental-websocket --no-warnings test_habits.mjs highlight
  ) || rc=1
fi
if [[ "$suites" == *handback* ]]; then
  # A scripted policy session drives the arm; the page previews its plan, the operator takes over and hands
  # the arm back.
  (
    STACK_HTTPS=1
    source "$HERE/../rosbridge/stack.sh"
    (cd "$REPO" && cargo build --quiet -p phone2act-tests --bin policy-script)
    export GRPC_URL POLICY_SCRIPT="$BIN/policy-script"
    cd "$HERE"
    node --experimental-websocket --no-warnings test_handback.mjs
  ) || rc=1
fi
if [[ "$suites" == *video* ]]; then
  (
    STACK_HTTPS=1
    source "$HERE/../rosbridge/stack.sh"
    # The stall check stops and resumes the gateway this stack started (by its pid).
    export GATEWAY_PID
    cd "$HERE"
    node --experimental-websocket --no-warnings test_video.mjs
  ) || rc=1
  # [gateway.video] against the page: the video turned off, and a camera larger than the size limit.
  (
    STACK_HTTPS=1
    STACK_GATEWAY_CONFIG="$HERE/video-off-gateway.toml"
    source "$HERE/../rosbridge/stack.sh"
    cd "$HERE"
    node --experimental-websocket --no-warnings test_video_config.mjs off
  ) || rc=1
  (
    STACK_HTTPS=1
    STACK_CONFIG="$HERE/camera-1080p.toml"
    source "$HERE/../rosbridge/stack.sh"
    cd "$HERE"
    node --experimental-websocket --no-warnings test_video_config.mjs scaled
  ) || rc=1
fi
exit $rc
