// Coverage feedback for libFuzzer from GCC-compiled code.
//
// oxbow is C++23 and needs GCC 12's libstdc++ <expected>, which Debian 12's clang 14 cannot compile, so
// the fuzz builds use GCC. GCC offers SanitizerCoverage's `-fsanitize-coverage=trace-pc` (a call to
// __sanitizer_cov_trace_pc at every basic block) and `trace-cmp` (comparison operands, which libFuzzer
// consumes directly), but not the inline 8-bit counters libFuzzer 14 reads, and libFuzzer 14 refuses
// trace-pc. The link renames the calls (-Wl,--wrap=__sanitizer_cov_trace_pc) to the function below,
// which counts AFL-style edges (hash(previous block) xor hash(this block)) in a 64 KiB counter map that
// it registers with libFuzzer as one module of 8-bit counters. Collisions in the map only make the
// feedback coarser; they never hide a crash. This file is compiled without instrumentation.
#include <cstddef>
#include <cstdint>

extern "C" void __sanitizer_cov_8bit_counters_init(uint8_t* start, uint8_t* stop);

namespace {

constexpr size_t kMapSize = size_t{1} << 16;
alignas(64) uint8_t edge_counters[kMapSize];
thread_local uintptr_t previous_block = 0;

}  // namespace

extern "C" __attribute__((no_sanitize("address", "undefined"))) void __wrap___sanitizer_cov_trace_pc() {
  const auto pc = reinterpret_cast<uintptr_t>(__builtin_return_address(0));
  const uintptr_t block = ((pc ^ (pc >> 17)) * uintptr_t{0x9E3779B97F4A7C15}) >> 48;
  ++edge_counters[(block ^ previous_block) & (kMapSize - 1)];
  previous_block = block >> 1;
}

// GCC's trace-cmp also reports floating-point comparisons, which libFuzzer has no hook for: ignored.
extern "C" void __sanitizer_cov_trace_cmpf(float, float) {}
extern "C" void __sanitizer_cov_trace_cmpd(double, double) {}

namespace {

struct RegisterCounters {
  RegisterCounters() { __sanitizer_cov_8bit_counters_init(edge_counters, edge_counters + kMapSize); }
} register_counters;

}  // namespace
