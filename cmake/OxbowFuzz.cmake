# Fuzzing support (OXBOW_FUZZ=ON): coverage instrumentation of every oxbow target and the libFuzzer
# runtime, for the targets in tests/fuzz/.
#
# oxbow needs GCC 12 (C++23 <expected> from libstdc++ 12, which Debian 12's clang 14 cannot compile), so
# the fuzz builds use GCC: every target is compiled with -fsanitize-coverage=trace-pc,trace-cmp plus the
# sanitizers of OXBOW_SANITIZE (address;undefined by default), and linked with
#   - oxbow_fuzz_coverage (tests/fuzz/coverage_shim.cc, not instrumented): turns GCC's trace-pc calls
#     into edge counters registered with libFuzzer (the link wraps __sanitizer_cov_trace_pc);
#   - libclang_rt.fuzzer_no_main from libclang-rt-14-dev (the fuzz targets get their main() from
#     tests/fuzz/libfuzzer_main.cc, which calls LLVMFuzzerRunDriver).
# oxbow_target_defaults (OxbowHelpers.cmake) links oxbow_fuzz_runtime into every target when OXBOW_FUZZ
# is on. Build only the fuzz targets in such a build folder (scripts/fuzz.sh does).
if(NOT OXBOW_FUZZ)
  return()
endif()
if(NOT CMAKE_CXX_COMPILER_ID STREQUAL "GNU")
  message(FATAL_ERROR "OXBOW_FUZZ uses GCC's -fsanitize-coverage=trace-pc (see cmake/OxbowFuzz.cmake)")
endif()
if(NOT OXBOW_SANITIZE)
  set(OXBOW_SANITIZE "address;undefined" CACHE STRING "Sanitizers to build with" FORCE)
endif()
file(GLOB _libfuzzer_candidates "/usr/lib/llvm-*/lib/clang/*/lib/linux/libclang_rt.fuzzer_no_main-x86_64.a")
list(SORT _libfuzzer_candidates)
list(POP_BACK _libfuzzer_candidates _libfuzzer_default)
set(OXBOW_LIBFUZZER "${_libfuzzer_default}" CACHE FILEPATH "libclang_rt.fuzzer_no_main archive (libclang-rt-14-dev)")
if(NOT EXISTS "${OXBOW_LIBFUZZER}")
  message(FATAL_ERROR "OXBOW_FUZZ needs libFuzzer's runtime: apt-get install libclang-rt-14-dev (or set OXBOW_LIBFUZZER)")
endif()
message(STATUS "oxbow fuzzing: libFuzzer runtime ${OXBOW_LIBFUZZER}")

add_library(oxbow_fuzz_coverage STATIC "${PROJECT_SOURCE_DIR}/tests/fuzz/coverage_shim.cc")
target_link_libraries(oxbow_fuzz_coverage PUBLIC "${OXBOW_LIBFUZZER}" Threads::Threads ${CMAKE_DL_LIBS})

add_library(oxbow_fuzz_runtime INTERFACE)
target_compile_options(oxbow_fuzz_runtime INTERFACE -fsanitize-coverage=trace-pc,trace-cmp)
target_link_options(oxbow_fuzz_runtime INTERFACE -Wl,--wrap=__sanitizer_cov_trace_pc)
target_link_libraries(oxbow_fuzz_runtime INTERFACE oxbow_fuzz_coverage)
