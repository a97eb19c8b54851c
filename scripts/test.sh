#!/usr/bin/env bash
# The one command that installs, builds and runs every oxbow test (README; .ci/run calls exactly this).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
"$root/scripts/install-deps.sh"
"$root/scripts/build.sh"
build_dir=${OXBOW_BUILD_DIR:-$root/build}
cd "$build_dir"
ctest --output-on-failure --parallel "${OXBOW_JOBS:-$(nproc)}" --timeout 900
