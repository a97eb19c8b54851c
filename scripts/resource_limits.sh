#!/usr/bin/env bash
# Prints the peak-memory-per-request table (eval/results/load.md): each hostile or large input is
# searched once in a fresh process with the server's defaults (--max-megapixels 40, --max-image-side
# 1600, RootSIFT with the 2x first octave) and its resident-memory high-water mark is checked against
# the stated bound. Includes the slow rows (real 40- and 100-megapixel JPEGs) that CI leaves out.
#   scripts/resource_limits.sh            (OXBOW_BUILD_DIR=build by default)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build_dir=${OXBOW_BUILD_DIR:-$root/build}
cmake --build "$build_dir" --target resource_limits_test --parallel "${OXBOW_JOBS:-2}" >&2
OXBOW_MEASURE_ALL=1 "$build_dir/tests/resource_limits_test" --gtest_filter='*PeakMemory*' 2>/dev/null | grep -E '^\||OK|FAILED'
