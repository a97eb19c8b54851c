// A portable build for x86-64-v3 (OXBOW_PORTABLE_MARCH, CMakeLists.txt) may execute AVX2 and FMA
// instructions anywhere, which kill the process with SIGILL on an older CPU. This file is compiled for
// the x86-64 baseline and checks the CPU before any other code of the binary runs (the first of its
// constructors), so that such a machine gets a message instead.
#if defined(OXBOW_REQUIRED_MARCH) && defined(__x86_64__) && defined(__GNUC__)
#include <unistd.h>

namespace {

[[gnu::constructor(101)]] void RequireCpuLevel() {
  __builtin_cpu_init();  // constructors may run before the library's own initialisation
  if (__builtin_cpu_supports(OXBOW_REQUIRED_MARCH)) return;
  static constexpr char kMessage[] =
      "oxbow: error: this build needs an " OXBOW_REQUIRED_MARCH
      " CPU (AVX2 and FMA: Intel Haswell, AMD Excavator or later), and this one is older; build oxbow from "
      "source (bash scripts/build.sh: for this CPU), or with -DOXBOW_NATIVE=OFF -DOXBOW_PORTABLE_MARCH=x86-64\n";
  [[maybe_unused]] const ssize_t written = write(STDERR_FILENO, kMessage, sizeof(kMessage) - 1);
  _exit(1);
}

}  // namespace
#endif
