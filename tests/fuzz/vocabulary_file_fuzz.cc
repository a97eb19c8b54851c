// Fuzz target: the vocabulary reader (vocab::Vocabulary::Read). The first input byte picks how the rest
// is presented: 0 as a whole file (container checks first), 1 as a payload wrapped in a valid "OXBWVOCB"
// version-1 container (correct CRCs), so mutations reach the payload parser and the quantiser build.
// A vocabulary that reads must quantise: every descriptor gets a word id < size().
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>
#include <vector>

#include "sift/base/binary_io.h"
#include "tests/fuzz/fuzz_support.h"
#include "vocab/vocabulary.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace oxbow;
  fuzz::InputSplitter input({data, size});
  const uint8_t mode = input.Byte() % 2;
  const auto rest = input.Rest();
  std::string path;
  if (mode == 0) {
    path = fuzz::WriteScratchFile("vocabulary.oxvoc", rest);
  } else {
    path = (fuzz::ScratchDir() / "wrapped.oxvoc").string();
    fuzz::CheckSetup(io::WriteContainerFile(path, "OXBWVOCB", 1, 0, rest), "write container");
  }
  auto vocabulary = vocab::Vocabulary::Read(path);
  if (!vocabulary) {
    if (vocabulary.error().code == ErrorCode::kInternal) std::abort();
    return 0;
  }
  if (vocabulary->size() == 0 || vocabulary->dimension() <= 0 ||
      vocabulary->centroids().size() != vocabulary->size() * static_cast<size_t>(vocabulary->dimension())) {
    std::abort();
  }
  // Quantise the first centroids themselves (at most 4): a valid vocabulary maps them to valid words.
  const size_t n = std::min<size_t>(4, vocabulary->size());
  const auto centroids = vocabulary->centroids().first(n * static_cast<size_t>(vocabulary->dimension()));
  std::vector<uint32_t> words(n);
  vocabulary->Quantize(centroids, words);
  for (uint32_t w : words) {
    if (w >= vocabulary->size()) std::abort();
  }
  return 0;
}
