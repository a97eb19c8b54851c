#!/usr/bin/env bash
# The hardening phases of the README's test command (scripts/test.sh, and so CI, runs this after the
# normal build and ctest unless OXBOW_TEST_HARDENING=0; can also be run alone after
# scripts/install-deps.sh):
#   asan  ASan + UBSan build (GCC, -O1) of every test, whole ctest suite       build dir build-asan
#   tsan  TSan build of the concurrency tests (HTTP server, index readers/writers, service)  build-tsan
#   tidy  clang-tidy 16 over every source file, profile .clang-tidy, warnings as errors (scripts/clang-tidy.sh)
#   fuzz  every libFuzzer target of tests/fuzz for OXBOW_FUZZ_SECONDS (default 60) s each, one target
#         per core at a time (scripts/fuzz.sh)
# OXBOW_HARDENING_PHASES="tidy asan tsan fuzz" picks phases (that is the default order: clang-tidy needs
# no build, so its findings come first); OXBOW_JOBS the build parallelism. Every phase runs even when
# an earlier one fails; prints each phase's time and result at the end and exits non-zero when any
# failed.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
phases=${OXBOW_HARDENING_PHASES:-tidy asan tsan fuzz}
jobs=${OXBOW_JOBS:-$(nproc)}
timings=()
# The concurrency tests run under TSan: the worker pool, many threads on one index / service / server, slow clients, and
# kill -9 under concurrent writers. The tests in tests/ run the TSan-built `oxbow` of the same build
# folder as a child (OXBOW_BINARY), which inherits TSAN_OPTIONS: log_path collects the reports of every
# process (a child's report would otherwise go only to its log), and any report fails the phase.
tsan_tests=(http_server_test collections_test image_index_test checkpointer_test geometry_parts_test loader_test service_test slow_clients_test crash_torture_test parallel_test)

# Test executables of a configured build folder (GoogleTest suites *_test and fuzz replays *_replay);
# benchmarks are not built.
test_targets() {
  ninja -C "$1" -t targets all | sed -n 's/^\([a-z0-9_]*_\(test\|replay\)\): phony$/\1/p' | grep -v '^cmake_' | sort -u
}

# configure DIR SANITIZERS [UNITY]: unity builds (ON, the default) for building and testing; clang-tidy
# needs build-asan's compile database with one command per source (OFF), so its phase configures that.
configure() {
  cmake -S "$root" -B "$1" -G Ninja -DCMAKE_BUILD_TYPE=Release -DCMAKE_CXX_FLAGS_RELEASE="-O1 -g1" \
    -DOXBOW_SANITIZE="$2" -DOXBOW_UNITY_BUILD="${3:-ON}" >/dev/null
}

run_phase() {
  local name=$1 start status=0
  start=$(date +%s)
  echo "==== hardening phase: $name" >&2
  # In the background so that set -e still stops the phase at its first failing step (a subshell on the
  # left of || would run with errexit ignored).
  "phase_$name" &
  wait $! || status=$?
  timings+=("$(printf '%-5s %5d s  %s' "$name" "$(( $(date +%s) - start ))" "$([[ $status -eq 0 ]] && echo passed || echo "FAILED (exit $status)")")")
  if [[ $status -ne 0 ]]; then failed=1; fi
}

phase_asan() {
  local dir=$root/build-asan
  configure "$dir" "address;undefined"
  mapfile -t targets < <(test_targets "$dir")
  cmake --build "$dir" --parallel "$jobs" --target oxbow "${targets[@]}"
  (cd "$dir" && ASAN_OPTIONS=detect_leaks=1:detect_stack_use_after_return=1 \
    UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1 \
    ctest --output-on-failure --parallel "$jobs" --timeout 1800 -E '^browser_')
}

phase_tsan() {
  local dir=$root/build-tsan
  configure "$dir" "thread"
  cmake --build "$dir" --parallel "$jobs" --target oxbow "${tsan_tests[@]}"
  local regex reports=$dir/tsan-reports status=0
  regex="^($(IFS='|'; echo "${tsan_tests[*]}"))\$"
  rm -rf "$reports" && mkdir -p "$reports"
  (cd "$dir" && TSAN_OPTIONS="halt_on_error=1:second_deadlock_stack=1:suppressions=$root/tests/tsan.supp:log_path=$reports/tsan" \
    ctest --output-on-failure --parallel "$jobs" --timeout 1800 -R "$regex") || status=$?
  if compgen -G "$reports/tsan.*" >/dev/null; then
    cat "$reports"/tsan.* >&2
    echo "tsan: ThreadSanitizer reports above (files in $reports)" >&2
    status=1
  fi
  return "$status"
}

phase_tidy() {
  configure "$root/build-asan" "address;undefined" OFF
  "$root/scripts/clang-tidy.sh" "$root/build-asan"
}

phase_fuzz() {
  "$root/scripts/fuzz.sh" --seconds "${OXBOW_FUZZ_SECONDS:-60}"
}

failed=0
for p in $phases; do run_phase "$p"; done
echo "hardening phases (wall time, result; load average $(cut -d' ' -f1-3 /proc/loadavg)):" >&2
for t in "${timings[@]}"; do echo "  $t" >&2; done
exit "$failed"
