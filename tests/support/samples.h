// Sample photos and a small vocabulary for the api/ unit tests and the tests in tests/: the opencv-doc
// sample photos (installed with Debian's opencv-doc package, which scripts/install-deps.sh installs),
// fast extractor settings, and a vocabulary trained in-process on a few of them. Needs oxbow_sift and
// oxbow_vocab. Header-only; tests only.
#pragma once

#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "sift/base/error.h"
#include "sift/sift.h"
#include "vocab/vocabulary.h"

namespace oxbow::testing {

inline const char* kSampleDir = "/usr/share/doc/opencv-doc/examples/data";

inline std::string SamplePath(const std::string& name) { return std::string(kSampleDir) + "/" + name; }

inline std::vector<uint8_t> ReadBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::vector<uint8_t>(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

// Fast extractor settings for tests: no 2x first octave, at most 1000 features, RootSIFT.
inline sift::SiftOptions TestSiftOptions() {
  sift::SiftOptions options;
  options.upsample_first_octave = false;
  options.max_features = 1000;
  options.descriptor = sift::DescriptorKind::kRootSift;
  return options;
}

// Trains a `words`-word vocabulary on the features of `images` (file names in kSampleDir) with
// `options` (TestSiftOptions unless given) and writes it to `path`. Seconds on one core for ~4 images
// and 64 words.
inline Result<vocab::Vocabulary> BuildTestVocabulary(const std::vector<std::string>& images, size_t words,
                                                     const std::string& path,
                                                     const sift::SiftOptions& options = TestSiftOptions()) {
  auto extractor = sift::SiftExtractor::Create(options);
  if (!extractor) return std::unexpected(extractor.error());
  std::vector<float> descriptors;
  for (const auto& name : images) {
    auto features = extractor->ExtractFromFile(SamplePath(name));
    if (!features) return std::unexpected(features.error());
    descriptors.insert(descriptors.end(), features->descriptors.begin(), features->descriptors.end());
  }
  vocab::TrainOptions train;
  train.num_words = words;
  train.max_iterations = 10;
  auto vocabulary = vocab::Train(descriptors, sift::kDescriptorDim, sift::DescriptorKind::kRootSift,
                                 options.Describe(), train);
  if (!vocabulary) return std::unexpected(vocabulary.error());
  if (auto written = vocabulary->Write(path); !written) return std::unexpected(written.error());
  return vocabulary;
}

}  // namespace oxbow::testing
