// Vector code paths and the CPU a build runs on.
//
// OXBOW_AVX2 is defined when AVX2+FMA code is compiled in: with -march=native on a CPU that has them
// (OXBOW_NATIVE=ON, the default) or in a portable build for x86-64-v3 (OXBOW_NATIVE=OFF: the Docker
// image, the packages), or, in a baseline x86-64 build (OXBOW_PORTABLE_MARCH=x86-64), by function attribute: functions marked OXBOW_AVX2_TARGET are compiled for those
// instructions and must only run where Avx2FmaAvailable() is true; the rest of the build stays baseline
// x86-64. Without FMA instructions every std::fma is a call into libm: SIFT extraction measured 13x
// slower and the vocabulary's quantiser about 50x slower than with the vector paths.
#pragma once

#if defined(__AVX2__) && defined(__FMA__)
#define OXBOW_AVX2 1
#define OXBOW_AVX2_TARGET
#elif defined(__x86_64__) && defined(__GNUC__)
#define OXBOW_AVX2 1
#define OXBOW_AVX2_DISPATCH 1
#define OXBOW_AVX2_TARGET __attribute__((target("avx2,fma")))
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

}  // namespace oxbow
