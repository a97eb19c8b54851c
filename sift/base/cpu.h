// Vector code paths and the CPU a build runs on.
//
// OXBOW_AVX2 is defined when AVX2+FMA code is compiled in: with -march=native on a CPU that has them
// (OXBOW_NATIVE=ON, the default) or in a portable build for x86-64-v3 (OXBOW_NATIVE=OFF: the Docker
// image, the packages), or, in a baseline x86-64 build (OXBOW_PORTABLE_MARCH=x86-64), by function attribute: functions marked OXBOW_AVX2_TARGET are compiled for those
// instructions and must only run where Avx2FmaAvailable() is true; the rest of the build stays baseline
// x86-64. Without FMA instructions every std::fma is a call into libm: SIFT extraction measured 13x
// slower and the vocabulary's quantiser about 50x slower than with the vector paths.
//
// OXBOW_AVX512 is defined when AVX-512 (F, DQ, VL, BW) code is compiled in: with -march=native on a CPU
// that has it, where it is the only vector path taken (OXBOW_AVX512_ALWAYS; the AVX2 paths it replaces
// are not compiled), or, in a portable build, by function attribute: functions marked
// OXBOW_AVX512_TARGET must only run where Avx512Available() is true, and the AVX2 paths serve the other
// CPUs. Every AVX-512 path computes its AVX2 and scalar paths' formulas bit for bit, so the features do
// not depend on which one runs.
#pragma once

#include <atomic>

#if defined(__AVX2__) && defined(__FMA__)
#define OXBOW_AVX2 1
#define OXBOW_AVX2_TARGET
#elif defined(__x86_64__) && defined(__GNUC__)
#define OXBOW_AVX2 1
#define OXBOW_AVX2_DISPATCH 1
#define OXBOW_AVX2_TARGET __attribute__((target("avx2,fma")))
#endif

#if defined(OXBOW_AVX2) && defined(__AVX512F__) && defined(__AVX512DQ__) && defined(__AVX512VL__) && defined(__AVX512BW__)
#define OXBOW_AVX512 1
#define OXBOW_AVX512_ALWAYS 1
#define OXBOW_AVX512_TARGET
#elif defined(OXBOW_AVX2) && defined(__x86_64__) && defined(__GNUC__)
#define OXBOW_AVX512 1
#define OXBOW_AVX512_DISPATCH 1
#define OXBOW_AVX512_TARGET __attribute__((target("avx2,fma,avx512f,avx512dq,avx512vl,avx512bw")))
#endif

// Around the AVX-512 code: GCC 12's unmasked AVX-512 intrinsics pass a deliberately undefined vector
// (_mm512_undefined_ps) as the operand their full mask discards, and GCC reports it as "may be used
// uninitialized" wherever they are inlined (GCC bug 105593). Between these two macros it does not.
#if defined(__GNUC__) && !defined(__clang__)
#define OXBOW_AVX512_BEGIN _Pragma("GCC diagnostic push") _Pragma("GCC diagnostic ignored \"-Wmaybe-uninitialized\"")
#define OXBOW_AVX512_END _Pragma("GCC diagnostic pop")
#else
#define OXBOW_AVX512_BEGIN
#define OXBOW_AVX512_END
#endif

namespace oxbow {

// True when the OXBOW_AVX2_TARGET code may run here: compiled in for this CPU, or compiled by attribute
// and this CPU has AVX2 and FMA.
inline bool Avx2FmaAvailable() {
#if defined(OXBOW_AVX2_DISPATCH)
  static const bool available = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  return available;
#elif defined(OXBOW_AVX2)
  return true;
#else
  return false;
#endif
}

namespace internal {
// Set by AllowAvx512; read by Avx512Available.
inline std::atomic<bool> avx512_allowed{true};
}  // namespace internal

// True when the OXBOW_AVX512_TARGET code may run here: compiled in for this CPU, or compiled by attribute,
// this CPU has AVX-512 F, DQ, VL and BW, and AllowAvx512(false) has not been called. Implies
// Avx2FmaAvailable().
inline bool Avx512Available() {
#if defined(OXBOW_AVX512_DISPATCH)
  static const bool cpu = Avx2FmaAvailable() && __builtin_cpu_supports("avx512f") &&
                          __builtin_cpu_supports("avx512dq") && __builtin_cpu_supports("avx512vl") &&
                          __builtin_cpu_supports("avx512bw");
  return cpu && internal::avx512_allowed.load(std::memory_order_relaxed);
#elif defined(OXBOW_AVX512)
  return true;
#else
  return false;
#endif
}

// Where the AVX-512 paths are chosen at run time (OXBOW_AVX512_DISPATCH), false makes every later
// extraction take the AVX2 paths instead, so that tests and benchmarks can compare the two on one CPU.
// Without effect elsewhere. Results are the same either way.
inline void AllowAvx512(bool allowed) { internal::avx512_allowed.store(allowed, std::memory_order_relaxed); }

}  // namespace oxbow
