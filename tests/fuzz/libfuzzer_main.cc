// main() of the OXBOW_FUZZ builds: hands the command line to libFuzzer (LLVM's runtime from
// libclang-rt-14-dev, linked as libclang_rt.fuzzer_no_main), which calls LLVMFuzzerTestOneInput.
#include <cstddef>
#include <cstdint>

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size);
extern "C" int LLVMFuzzerRunDriver(int* argc, char*** argv, int (*callback)(const uint8_t* data, size_t size));

int main(int argc, char** argv) { return LLVMFuzzerRunDriver(&argc, &argv, LLVMFuzzerTestOneInput); }
