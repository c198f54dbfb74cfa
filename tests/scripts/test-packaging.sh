#!/usr/bin/env bash
# The Python packages as someone outside this checkout gets them: the SDK's source distribution must carry
# its .proto files and build in a directory with no repository around it, and `pip install
# ./clients/replay` must resolve its `phone2act` dependency once the SDK is installed (the documented
# two-step install: the SDK is not on PyPI). Everything happens in fresh venvs under a scratch directory.
set -euo pipefail
cd "$(dirname "$0")/../.."
REPO=$PWD
SCRATCH=$(mktemp -d)
trap 'rm -rf "$SCRATCH"' EXIT
fail() { echo "packaging: FAIL: $*" >&2; exit 1; }

# Runtime dependencies are ranges: an exact pin (grpcio==...) conflicts with other packages' extras.
for f in sdk/python/pyproject.toml clients/replay/pyproject.toml clients/gr00t/pyproject.toml; do
  [[ -f $f ]] || continue
  deps=$(sed -n '/^dependencies/,/]/p' "$f")
  if grep -q '==' <<<"$deps"; then fail "$f pins a runtime dependency exactly: $deps"; fi
done

# What git sees under the Python packages, ignored files included: a build must not change it.
tree_state() { git status --porcelain --ignored -- sdk/python clients/replay clients/gr00t | sort; }
before=$(tree_state)

python3 -m venv "$SCRATCH/build-venv"
"$SCRATCH/build-venv/bin/pip" install -q build
"$SCRATCH/build-venv/bin/python" -m build --sdist --outdir "$SCRATCH/dist" sdk/python >"$SCRATCH/build.log" 2>&1 ||
  { cat "$SCRATCH/build.log" >&2; fail "python -m build --sdist sdk/python"; }
sdist=$(ls "$SCRATCH"/dist/phone2act-*.tar.gz)
protos=$(tar -tzf "$sdist" | grep -c '/proto/phone2act/v1/.*\.proto$' || true)
[[ $protos -ge 7 ]] || fail "$sdist holds $protos .proto files, expected the 7 of proto/phone2act/v1"
echo "packaging: $(basename "$sdist") carries $protos .proto files"

# Build and install from the sdist alone, from a directory that has no repository around it.
python3 -m venv "$SCRATCH/user-venv"
cp "$sdist" "$SCRATCH/elsewhere.tar.gz"
(cd "$SCRATCH" && "$SCRATCH/user-venv/bin/pip" install -q "$SCRATCH/elsewhere.tar.gz")
# And straight from the checkout, as the README says.
python3 -m venv "$SCRATCH/tree-venv"
"$SCRATCH/tree-venv/bin/pip" install -q ./sdk/python
(cd "$SCRATCH" && "$SCRATCH/tree-venv/bin/python" -c 'from phone2act.v1 import teleop_pb2_grpc')
# Then the replay client, from the checkout, with the SDK already there.
"$SCRATCH/user-venv/bin/pip" install -q "$REPO/clients/replay"
(cd "$SCRATCH" && "$SCRATCH/user-venv/bin/python" -c '
import phone2act, phone2act_replay
from phone2act.v1 import system_pb2, system_pb2_grpc
from phone2act.aio import AsyncClient
print("packaging: the installed SDK imports its generated stubs, and the replay client imports")
')
after=$(tree_state)
if [[ "$before" != "$after" ]]; then
  diff <(echo "$before") <(echo "$after") >&2 || true
  fail "building or installing the Python packages changed the checkout (above: git status before/after)"
fi
echo "packaging: the checkout is unchanged by the builds and installs"
echo "packaging: ok"
