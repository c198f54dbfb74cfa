#!/usr/bin/env bash
# Mutation testing of the safety-critical core (not in CI: it takes tens of minutes on two cores).
# cargo-mutants changes one operator / return value at a time in the given files, builds a scratch copy of
# the workspace and runs only the core crate's tests; a mutant no test notices is "missed".
#
#   benchmarks/mutants/run.sh                       # gate, teleop, chunk (and arbiter when it exists)
#   benchmarks/mutants/run.sh server/core/src/gate.rs
#   benchmarks/mutants/run.sh --iterate             # after adding tests: re-test only the survivors
#
# Arguments starting with "-" go to cargo-mutants.
# Needs `cargo install cargo-mutants --locked`. Results: target/mutants/mutants.out/ (missed.txt lists the
# survivors); the table at the end counts outcomes per file. Equivalent mutants (no
# observable difference) are listed with the reason in benchmarks/mutants/EQUIVALENT.md.
set -euo pipefail
cd "$(dirname "$0")/../.."
files=()
extra=()
for a in "$@"; do
  if [[ $a == -* ]]; then extra+=("$a"); else files+=("$a"); fi
done
if ((${#files[@]} == 0)); then
  files=(server/core/src/gate.rs server/core/src/teleop.rs server/core/src/chunk.rs)
  [[ -f server/core/src/arbiter.rs ]] && files+=(server/core/src/arbiter.rs)
fi
command -v cargo-mutants >/dev/null || { echo "install cargo-mutants: cargo install cargo-mutants --locked" >&2; exit 1; }
# Debug info is the slowest part of each rebuild and nothing here reads it.
export CARGO_PROFILE_DEV_DEBUG=0 CARGO_PROFILE_TEST_DEBUG=0
out=target/mutants
mkdir -p "$out"
# One run for all files: one scratch copy and one dependency build. Exit status 2 = some mutants missed,
# 3 = timeouts: both are results here, not failures.
args=()
for f in "${files[@]}"; do args+=(-f "$f"); done
nice -n 19 cargo mutants -p phone2act-core "${args[@]}" "${extra[@]}" -j 1 --no-shuffle --output "$out" || {
  rc=$?
  [[ $rc -eq 2 || $rc -eq 3 ]] || exit "$rc"
}
d="$out/mutants.out"
# Each line of caught.txt etc. starts with the mutated file's path.
count() {
  [[ -f "$d/$1.txt" ]] || { echo 0; return; }
  grep -c "^$2:" "$d/$1.txt" || true
}
printf '%-28s %7s %7s %9s %8s %8s\n' file caught missed unviable timeout score
for f in "${files[@]}"; do
  c=$(count caught "$f") m=$(count missed "$f") u=$(count unviable "$f") t=$(count timeout "$f")
  score=$(awk -v c="$c" -v m="$m" -v t="$t" 'BEGIN { n = c + m + t; printf "%s", n ? sprintf("%.0f %%", 100 * (c + t) / n) : "-" }')
  printf '%-28s %7s %7s %9s %8s %8s\n' "$f" "$c" "$m" "$u" "$t" "$score"
done
