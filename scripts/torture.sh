#!/usr/bin/env bash
# Crash torture (tests/README.md, "Crash torture"): start `oxbow serve`, stream adds and deletes from 3 HTTP
# clients, kill -9 it at a random moment, restart, check every acknowledged write, the fate of every
# unanswered one, the catalogue listing and search results against an index rebuilt from scratch.
#   scripts/torture.sh [ROUNDS] [SEED]      (default 100 rounds, a random seed; OXBOW_BUILD_DIR=build)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build_dir=${OXBOW_BUILD_DIR:-$root/build}
cmake --build "$build_dir" --target crash_torture_test oxbow --parallel "${OXBOW_JOBS:-2}" >&2
export OXBOW_TORTURE_ROUNDS=${1:-100}
export OXBOW_TORTURE_SEED=${2:-$(od -An -N4 -tu4 /dev/urandom | tr -d ' ')}  # the test's own default is fixed (1)
"$build_dir/tests/crash_torture_test" | grep -E 'crash torture|Failure|round|OK|FAILED'
