#!/usr/bin/env bash
# Loads every dataset the Rust tests produced with the real lerobot library and checks it (see check.py).
# Datasets: directories with meta/info.json under $PHONE2ACT_CONFORMANCE_DIR (default
# target/conformance-datasets). v3.0 datasets are read by lerobot 0.6.1 (Python >= 3.12, the venv the plugin
# tests use), v2.1 datasets by lerobot 0.3.3 plus a GR00T-style check of modality.json and stats.json.
# The Python environment is created on first use outside the checkout (tests/conformance/setup-venv.sh); with
# no Python >= 3.12 the checks are reported as skipped, loudly, and exit 2. Every dataset's frames are also
# decoded step by step with each of GR00T's and LeRobot's video readers (check.py, `Pairing`); a reader that
# cannot run here is listed as SKIP with its reason.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
dir="${PHONE2ACT_CONFORMANCE_DIR:-$repo/target/conformance-datasets}"
if [[ ! -d "$dir" ]]; then
  echo "conformance: no datasets in $dir (run cargo test with PHONE2ACT_CONFORMANCE_DIR set first)" >&2
  echo "0 passed, 1 failed"
  exit 1
fi
v30=()
v21=()
while IFS= read -r info; do
  root="$(dirname "$(dirname "$info")")"
  version="$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["codebase_version"])' "$info")"
  case "$version" in
    v3.0) v30+=("$root") ;;
    v2.1) v21+=("$root") ;;
    *) echo "conformance: $root has unknown codebase_version $version" >&2; v30+=("$root") ;;
  esac
done < <(find "$dir" -mindepth 3 -maxdepth 3 -path '*/meta/info.json' | sort)
if ((${#v30[@]} + ${#v21[@]} == 0)); then
  echo "conformance: no datasets found under $dir" >&2
  echo "0 passed, 1 failed"
  exit 1
fi
if ! venv="$("$here/setup-venv.sh" | tail -n 1)" || [[ ! -x "$venv/bin/python" ]]; then
  echo "conformance: SKIPPED: no lerobot 0.6 venv (needs a Python >= 3.12; see above)" >&2
  exit 2
fi
cache="$(dirname "$venv")"
# GR00T's decord reader (see setup-venv.sh); absent, check.py reports it as skipped.
backends="$cache/gr00t-video-backends"
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 TOKENIZERS_PARALLELISM=false
# datasets caches Arrow copies of the parquet files; keep them out of the user's cache and fresh per run.
export HF_DATASETS_CACHE="$(mktemp -d)"
trap 'rm -rf "$HF_DATASETS_CACHE"' EXIT
log="$(mktemp)"
status=0
run_group() {
  local label="$1" count="$2"; shift 2
  echo "conformance: $label: $count dataset(s)"
  set +e
  (cd "$dir" && "$@") 2>&1 | grep -E '^(PASS|FAIL|SKIP|pairing|[0-9]+ passed)|Error|error' | tee -a "$log"
  local rc=${PIPESTATUS[0]}
  set -e
  [[ $rc -eq 0 ]] || status=1
}
if ((${#v30[@]})); then
  run_group "lerobot $("$venv/bin/python" -c 'import importlib.metadata as m; print(m.version("lerobot"))') (v3.0)" "${#v30[@]}" \
    env PYTHONPATH="$backends" "$venv/bin/python" "$here/check.py" "${v30[@]}"
fi
if ((${#v21[@]})); then
  run_group "lerobot 0.3.3 (v2.1 + GR00T checks)" "${#v21[@]}" \
    env PYTHONPATH="$cache/lerobot-0.3.3:$backends" "$venv/bin/python" "$here/check.py" "${v21[@]}"
fi
passed=$(grep -c '^PASS' "$log" || true)
failed=$(grep -c '^FAIL' "$log" || true)
rm -f "$log"
if [[ $status -ne 0 && $failed -eq 0 ]]; then
  failed=1 # the checker itself crashed
fi
echo "conformance: ${passed} passed, ${failed} failed"
[[ $failed -eq 0 ]]
