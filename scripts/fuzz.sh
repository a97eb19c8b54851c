#!/usr/bin/env bash
# Builds the libFuzzer targets of tests/fuzz (GCC + ASan + UBSan + coverage, cmake/OxbowFuzz.cmake) and
# runs each for a fixed time on its corpus (--parallel targets at a time, one core each).
#   scripts/fuzz.sh [--seconds N] [--target NAME]... [--build-dir DIR] [--no-build] [--parallel N]
#     --seconds N    fuzzing time per target (default 60)
#     --target NAME  run only this target (repeatable; default: every tests/fuzz/*_fuzz.cc)
#     --build-dir    build folder (default build-fuzz; $OXBOW_FUZZ_BUILD_DIR)
#     --parallel N   targets fuzzed at the same time, one process each (default $OXBOW_JOBS or nproc)
# Seeds are regenerated from real files by fuzz_seeds into BUILD/fuzz-seeds/<target>; what a run finds
# is kept in BUILD/fuzz-corpus/<target> (reused by the next run); a crashing input is written to
# BUILD/fuzz-artifacts/<target>/ and the script exits 1: fix the bug, then keep the input as a regression
# test in tests/fuzz/regressions/<target>/ (replayed by the ctest fuzz_<target> in the normal and ASan builds).
# Prints one line per target: executions, executions/s, corpus files, result; then the wall time.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
seconds=60
targets=()
build_dir=${OXBOW_FUZZ_BUILD_DIR:-$root/build-fuzz}
build=1
parallel=${OXBOW_JOBS:-$(nproc)}
while [[ $# -gt 0 ]]; do
  case "$1" in
    --seconds) seconds=$2; shift 2 ;;
    --target) targets+=("$2"); shift 2 ;;
    --build-dir) build_dir=$2; shift 2 ;;
    --no-build) build=0; shift ;;
    --parallel) parallel=$2; shift 2 ;;
    *) echo "fuzz.sh: unknown argument $1 (see the comment at the top of scripts/fuzz.sh)" >&2; exit 2 ;;
  esac
done
if [[ ${#targets[@]} -eq 0 ]]; then
  for f in "$root"/tests/fuzz/*_fuzz.cc; do targets+=("$(basename "$f" .cc)"); done
fi

if [[ $build -eq 1 ]]; then
  # -O1 with line tables, as OSS-Fuzz builds its targets: half the compile time of RelWithDebInfo's
  # -O2 -g under ASan + UBSan + coverage (index/image_index.cc: 39 s against 73 s), NDEBUG kept.
  cmake -S "$root" -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
    -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="-O1 -g1 -DNDEBUG" -DOXBOW_FUZZ=ON \
    -DOXBOW_BUILD_TESTS=OFF -DOXBOW_BUILD_BENCHMARKS=OFF >/dev/null
  cmake --build "$build_dir" --parallel "${OXBOW_JOBS:-$(nproc)}" --target fuzz_seeds "${targets[@]}"
fi
rm -rf "$build_dir/fuzz-seeds"
"$build_dir/tests/fuzz/fuzz_seeds" "$build_dir/fuzz-seeds" >/dev/null

export ASAN_OPTIONS=${ASAN_OPTIONS:-detect_leaks=1:abort_on_error=0}
export UBSAN_OPTIONS=${UBSAN_OPTIONS:-print_stacktrace=1:halt_on_error=1:abort_on_error=1}
# One target: fuzz for $seconds, then write its table row (and FAILED marker) under $results.
run_target() {
  local t=$1 corpus="$build_dir/fuzz-corpus/$1" artifacts="$build_dir/fuzz-artifacts/$1" seeds="$build_dir/fuzz-seeds/$1"
  local log="$build_dir/fuzz-$1.log" result execs files
  mkdir -p "$corpus" "$artifacts" "$seeds"
  if "$build_dir/tests/fuzz/$t" -max_total_time="$seconds" -timeout=25 -rss_limit_mb=2560 \
      -print_final_stats=1 -artifact_prefix="$artifacts/" "$corpus" "$seeds" >"$log" 2>&1; then
    result=clean
  else
    result="FAILED (log $log; input in $artifacts/)"
    touch "$results/$t.failed"
  fi
  execs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' || echo 0)
  files=$(find "$corpus" -type f | wc -l)
  printf '%-24s %8s %12s %10s %8s  %s\n' "$t" "$seconds" "${execs:-0}" "$(( ${execs:-0} / (seconds > 0 ? seconds : 1) ))" \
    "$files" "$result" >"$results/$t.row"
}

results=$(mktemp -d)
trap 'rm -rf "$results"' EXIT
start=$(date +%s)
for t in "${targets[@]}"; do
  while [[ $(jobs -rp | wc -l) -ge $parallel ]]; do wait -n || true; done
  run_target "$t" &
done
wait
failed=0
printf '%-24s %8s %12s %10s %8s  %s\n' target seconds executions exec/s corpus result
for t in "${targets[@]}"; do
  cat "$results/$t.row"
  if [[ -f "$results/$t.failed" ]]; then failed=1; tail -40 "$build_dir/fuzz-$t.log" >&2; fi
done
echo "fuzz.sh: ${#targets[@]} targets, $parallel at a time, $(( $(date +%s) - start )) s wall (load average $(cut -d' ' -f1-3 /proc/loadavg))"
exit $failed
