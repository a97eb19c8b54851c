#!/usr/bin/env bash
# Configures and builds oxbow (Release) into build/ (or $OXBOW_BUILD_DIR).
# Extra arguments go to CMake's configure step, e.g. scripts/build.sh -DOXBOW_SANITIZE='address;undefined'.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build_dir=${OXBOW_BUILD_DIR:-$root/build}
generator=()
if command -v ninja >/dev/null 2>&1 && [[ ! -f "$build_dir/Makefile" ]]; then generator=(-G Ninja); fi
cmake -S "$root" -B "$build_dir" "${generator[@]}" -DCMAKE_BUILD_TYPE="${OXBOW_BUILD_TYPE:-Release}" "$@" >/dev/null
cmake --build "$build_dir" --parallel "${OXBOW_JOBS:-$(nproc)}"
