#!/usr/bin/env bash
# Builds the Debian package oxbow_<version>_<arch>.deb into build/ (or $OXBOW_BUILD_DIR): installs the
# Debian packages needed, builds (scripts/build.sh; extra arguments go to CMake), then cpack -G DEB.
#   bash scripts/package.sh                      # for this machine's CPU (-march=native, as the build/ default)
#   bash scripts/package.sh -DOXBOW_NATIVE=OFF   # for any x86-64 machine with AVX2 and FMA (x86-64-v3;
#                                                # rebuilds build/ without -march=native)
# Install it with: sudo apt-get install ./build/oxbow_*.deb   (server/README.md, "Debian package")
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build_dir=${OXBOW_BUILD_DIR:-$root/build}
"$root/scripts/install-deps.sh"
"$root/scripts/build.sh" "$@"
cd "$build_dir"
rm -f oxbow_*.deb
cpack -G DEB
if grep -q '^OXBOW_NATIVE:BOOL=ON' CMakeCache.txt; then
  echo "package: built with -march=native: it runs on CPUs like this one only; for other machines:" \
       "bash scripts/package.sh -DOXBOW_NATIVE=OFF" >&2
fi
