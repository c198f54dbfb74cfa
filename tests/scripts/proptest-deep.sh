#!/usr/bin/env bash
# Runs the property tests with fresh random seeds and many cases (release build). `make test` draws every
# property test from one fixed seed so that a run is reproducible; this is where new counterexamples are
# looked for. A failure prints the case and proptest saves its seed under the crate's
# `proptest-regressions/`: commit that file with the fix.
# Usage: tests/scripts/proptest-deep.sh [CASES]   (default 20000 per property)
set -euo pipefail
cd "$(dirname "$0")/../.."
unset PROPTEST_RNG_SEED
export PROPTEST_CASES="${1:-20000}"
cargo test --release -p phone2act-core -p phone2act-dataset -p phone2act-proto --lib
cargo test --release -p phone2act-core --test gimbal_lock
cargo test --release -p phone2act-tests --test fuzz_parsers
