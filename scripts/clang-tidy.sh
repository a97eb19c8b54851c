#!/usr/bin/env bash
# Runs clang-tidy (profile: .clang-tidy, warnings as errors) over every oxbow source file.
#   scripts/clang-tidy.sh [BUILD_DIR] [FILE_REGEX]
# BUILD_DIR holds compile_commands.json (configured here if missing; default build-tidy). FILE_REGEX
# narrows the files (default: every .cc of the modules and tests). Exit 0 only when clean.
#
# oxbow is C++23 built with GCC 12; clang-tidy 16 parses it as C++2b. libstdc++ 12 only declares
# std::expected when __cpp_concepts >= 202002L, which clang 16 implements (P0848, conditionally trivial
# special members) but still advertises as 201907L, so the macro is raised (-U then -D, which warns
# about nothing) for the analysis only.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build_dir=${1:-$root/build-tidy}
files=${2:-"^$root/(sift|vocab|index|api|server|eval|tests)/.*\\.cc\$"}
tidy=$(command -v clang-tidy-16 || true)
runner=$(command -v run-clang-tidy-16 || true)
if [[ -z "$tidy" || -z "$runner" ]]; then
  echo "clang-tidy.sh: clang-tidy-16 not found (scripts/install-deps.sh installs it)" >&2
  exit 1
fi
if [[ ! -f "$build_dir/compile_commands.json" ]]; then
  cmake -S "$root" -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=Release >/dev/null
fi
start=$(date +%s)
"$runner" -clang-tidy-binary "$tidy" -p "$build_dir" -quiet -j "${OXBOW_JOBS:-$(nproc)}" \
  -extra-arg=-std=c++2b -extra-arg=-U__cpp_concepts -extra-arg=-D__cpp_concepts=202002L \
  -extra-arg=-Wno-builtin-macro-redefined -extra-arg=-Wno-unknown-warning-option "$files" > "$build_dir/clang-tidy.log" 2>&1 && status=0 || status=$?
grep -E "(warning|error): " "$build_dir/clang-tidy.log" | sort -u || true
echo "clang-tidy.sh: $(grep -c '^clang-tidy-16\|^/usr/bin/clang-tidy-16' "$build_dir/clang-tidy.log" || true) files in $(( $(date +%s) - start )) s, exit $status (log: $build_dir/clang-tidy.log)"
exit "$status"
