#!/usr/bin/env bash
# The one command that installs, builds and runs every oxbow test (README; .ci/run calls exactly this).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
"$root/scripts/install-deps.sh"
"$root/scripts/build.sh"
build_dir=${OXBOW_BUILD_DIR:-$root/build}
# playwright-core for the web page's browser test (pinned in tests/browser/package-lock.json).
npm ci --prefix "$root/tests/browser" --no-audit --no-fund --loglevel=error
cd "$build_dir"
ctest --output-on-failure --parallel "${OXBOW_JOBS:-$(nproc)}" --timeout 900
# The Debian package from this build: lintian, the unit, then install, serve, purge (as root; ~20 s).
OXBOW_BUILD_DIR="$build_dir" "$root/scripts/package-test.sh"
# Hardening phases, on by default (scripts/test-hardening.sh): every test again under ASan + UBSan, the
# concurrency tests under TSan, clang-tidy (warnings as errors), and 60 s of fuzzing per target.
# OXBOW_TEST_HARDENING=0 skips them for a quick local run; CI (.ci/run) always runs them.
if [[ "${OXBOW_TEST_HARDENING:-1}" != 0 ]]; then "$root/scripts/test-hardening.sh"; fi
