// Shared helpers of the fuzz targets in tests/fuzz/ (see tests/fuzz/CMakeLists.txt for how they are built).
//
// Every target defines `extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size)` and
// follows the libFuzzer contract: it must return 0, must not leak, and any crash, sanitizer report,
// uncaught exception or abort is a bug in oxbow (bad input must come back as an error value). The same
// sources are linked either with libFuzzer (OXBOW_FUZZ builds, tests/fuzz/libfuzzer_main.cc) or with a
// replay driver (every build, tests/fuzz/replay_main.cc) that runs the kept regression inputs as a ctest.
//
// Readers that take a path get their bytes through a scratch folder that lives as long as the process
// (under /dev/shm when it exists, so a run does not wear the disk). Not thread-safe: libFuzzer calls a
// target from one thread.
#pragma once

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "sift/base/error.h"
#include "sift/types.h"
#include "vocab/vocabulary.h"

namespace oxbow::fuzz {

// A folder unique to this process, created on first use and removed at exit.
const std::filesystem::path& ScratchDir();

// Writes `bytes` to ScratchDir()/name (replacing it) and returns the full path. Aborts when the write
// fails (that is the harness's environment failing, not oxbow).
std::string WriteScratchFile(const std::string& name, std::span<const uint8_t> bytes);

// Reads the next length-prefixed piece of the input (one byte length 0..255 then that many bytes), so a
// target can carve several fields out of one input; returns "" once the input is used up.
class InputSplitter {
 public:
  explicit InputSplitter(std::span<const uint8_t> data) : data_(data) {}
  uint8_t Byte();                              // 0 when exhausted
  std::string_view Piece();                    // length-prefixed piece
  std::span<const uint8_t> Rest();             // everything not consumed yet
  bool empty() const { return pos_ >= data_.size(); }

 private:
  std::span<const uint8_t> data_;
  size_t pos_ = 0;
};

// The fuzz targets' fixed vocabulary: `words` deterministic pseudo-random RootSIFT-like centroids
// (seeded, identical in every process), descriptor kind RootSIFT, extractor settings of the default
// SiftOptions with RootSIFT descriptors. The seed generator builds its index seeds with it so that they open in the targets.
const vocab::Vocabulary& FuzzVocabulary();
inline constexpr int kFuzzVocabularyWords = 64;

// A small deterministic feature set (keypoints spread over a 320 x 240 image, descriptors of the
// vocabulary's kind) used to query an index that opened.
sift::FeatureSet FuzzQueryFeatures();

// Aborts with a message when `status` is an error (harness set-up only, never for fuzzed data).
void CheckSetup(const Status& status, std::string_view what);

}  // namespace oxbow::fuzz
