#!/usr/bin/env bash
# Runs clang-tidy (profile: .clang-tidy, warnings as errors) over every oxbow source file.
#   scripts/clang-tidy.sh [BUILD_DIR] [FILE_REGEX]
# BUILD_DIR holds compile_commands.json (configured here if missing; default build-tidy). FILE_REGEX
# narrows the files (default: every .cc of the modules and tests). Files run $OXBOW_JOBS (default nproc)
# at a time, each under a time limit of $OXBOW_TIDY_FILE_TIMEOUT seconds (default 600; a file that
# exceeds it fails the run, so a pathological analysis cannot stall CI). Prints every finding, the
# slowest files and the total; exit 0 only when every file is clean. Per-file output: BUILD_DIR/clang-tidy/.
#
# oxbow is C++23 built with GCC 12; clang-tidy 16 parses it as C++2b. libstdc++ 12 only declares
# std::expected when __cpp_concepts >= 202002L, which clang 16 implements (P0848, conditionally trivial
# special members) but still advertises as 201907L, so the macro is raised (-U then -D, which warns
# about nothing) for the analysis only.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build_dir=${1:-$root/build-tidy}
files_regex=${2:-"^$root/(sift|vocab|index|api|server|eval|tests)/.*\\.cc\$"}
tidy=$(command -v clang-tidy-16 || true)
if [[ -z "$tidy" ]]; then
  echo "clang-tidy.sh: clang-tidy-16 not found (scripts/install-deps.sh installs it)" >&2
  exit 1
fi
if [[ ! -f "$build_dir/compile_commands.json" ]]; then
  cmake -S "$root" -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=Release >/dev/null
fi
# Sources that include generated headers (server/cluster: shard.proto's) need them in the build tree.
cmake --build "$build_dir" --target oxbow_generated_sources >/dev/null
out=$build_dir/clang-tidy
rm -rf "$out" && mkdir -p "$out"
mapfile -t files < <(python3 - "$build_dir/compile_commands.json" "$files_regex" <<'EOF'
import json, os, re, sys
entries = json.load(open(sys.argv[1]))
pattern = re.compile(sys.argv[2])
paths = {os.path.normpath(os.path.join(e["directory"], e["file"])) for e in entries}
print("\n".join(sorted(p for p in paths if pattern.search(p))))
EOF
)
if [[ ${#files[@]} -eq 0 ]]; then
  echo "clang-tidy.sh: no file of $build_dir/compile_commands.json matches $files_regex" >&2
  exit 1
fi
export tidy build_dir out
export limit=${OXBOW_TIDY_FILE_TIMEOUT:-600}
# One file: its findings go to $out/<n>.log, its line "seconds status path" to $out/<n>.time.
# GoogleTest files (*_test.cc) get every check but two:
#  - bugprone-unchecked-optional-access: its dataflow analysis does not see that ASSERT_TRUE(opt)
#    returns when opt is empty, so every access after such an assertion is reported
#    (llvm/llvm-project issue 181737, fixed only in releases much later than Debian 12's 16);
#  - clang-analyzer-* (the static analyser): two thirds of clang-tidy's time per file; what it looks
#    for (null dereferences, use after free, leaks) the asan phase checks while running every test.
# Both still check all non-test code (the modules, the server, the benchmarks, the fuzz targets).
check_one() {
  local n=$1 file=$2 start status=0 extra=()
  if [[ $file == *_test.cc ]]; then extra=(--checks=-bugprone-unchecked-optional-access,-clang-analyzer-*); fi
  start=$(date +%s%N)
  timeout "$limit" "$tidy" -p "$build_dir" --quiet "${extra[@]}" --extra-arg=-std=c++2b --extra-arg=-U__cpp_concepts \
    --extra-arg=-D__cpp_concepts=202002L --extra-arg=-Wno-builtin-macro-redefined \
    --extra-arg=-Wno-unknown-warning-option "$file" >"$out/$n.log" 2>&1 || status=$?
  if [[ $status -eq 124 ]]; then echo "$file: error: clang-tidy took over $limit s (OXBOW_TIDY_FILE_TIMEOUT)" >>"$out/$n.log"; fi
  printf '%6.1f %3d %s\n' "$(( ($(date +%s%N) - start) / 1000000 ))e-3" "$status" "$file" >"$out/$n.time"
}
export -f check_one
start=$(date +%s)
for i in "${!files[@]}"; do printf '%s\0%s\0' "$i" "${files[$i]}"; done |
  xargs -0 -n 2 -P "${OXBOW_JOBS:-$(nproc)}" bash -c 'check_one "$1" "$2"' _
cat "$out"/*.log | grep -E "(warning|error): " | sort -u || true
failed=$(cat "$out"/*.time | awk '$2 != 0' | wc -l)
echo "clang-tidy.sh: slowest files (s, exit status):"
cat "$out"/*.time | sort -rn | head -5 | sed 's/^/  /'
echo "clang-tidy.sh: ${#files[@]} files, $failed with findings, $(( $(date +%s) - start )) s wall (load average $(cut -d' ' -f1-3 /proc/loadavg)); per-file output in $out/"
[[ $failed -eq 0 ]]
