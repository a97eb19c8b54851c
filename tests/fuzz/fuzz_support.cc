#include "tests/fuzz/fuzz_support.h"

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <random>
#include <system_error>

#include "sift/sift.h"
#include "tests/support/temp_dir.h"

namespace oxbow::fuzz {
namespace {

// The harness's folder, in memory (/dev/shm) where there is one, removed at exit.
oxbow::testing::TempDir MakeScratch() {
  std::error_code ec;
  const std::filesystem::path base = std::filesystem::exists("/dev/shm", ec) ? std::filesystem::path("/dev/shm")
                                                                             : std::filesystem::temp_directory_path();
  try {
    return oxbow::testing::TempDir("oxbow-fuzz", base);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "fuzz harness: %s\n", e.what());
    std::abort();
  }
}

}  // namespace

const std::filesystem::path& ScratchDir() {
  static const oxbow::testing::TempDir scratch = MakeScratch();
  static const std::filesystem::path dir = scratch.path();
  return dir;
}

std::string WriteScratchFile(const std::string& name, std::span<const uint8_t> bytes) {
  std::string path = (ScratchDir() / name).string();
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
  out.close();
  if (!out) {
    std::fprintf(stderr, "fuzz harness: cannot write %s\n", path.c_str());
    std::abort();
  }
  return path;
}

uint8_t InputSplitter::Byte() { return pos_ < data_.size() ? data_[pos_++] : 0; }

std::string_view InputSplitter::Piece() {
  const size_t wanted = Byte();  // read before data_.size() - pos_ is computed
  const size_t length = std::min(wanted, data_.size() - pos_);
  std::string_view piece(reinterpret_cast<const char*>(data_.data() + pos_), length);
  pos_ += length;
  return piece;
}

std::span<const uint8_t> InputSplitter::Rest() {
  auto rest = data_.subspan(pos_);
  pos_ = data_.size();
  return rest;
}

void CheckSetup(const Status& status, std::string_view what) {
  if (status) return;
  std::fprintf(stderr, "fuzz harness set-up failed (%.*s): %s\n", static_cast<int>(what.size()), what.data(),
               status.error().ToString().c_str());
  std::abort();
}

namespace {

// A unit-L2 RootSIFT-like vector: square roots of a normalised random histogram.
std::vector<float> RandomRootSift(std::mt19937& rng) {
  std::uniform_real_distribution<float> uniform(0.0f, 1.0f);
  std::vector<float> v(sift::kDescriptorDim);
  float sum = 0;
  for (float& x : v) {
    x = uniform(rng) * uniform(rng);
    sum += x;
  }
  for (float& x : v) x = std::sqrt(x / sum);
  return v;
}

}  // namespace

const vocab::Vocabulary& FuzzVocabulary() {
  static const vocab::Vocabulary vocabulary = [] {
    std::mt19937 rng(20240509);
    std::vector<float> centroids;
    for (int w = 0; w < kFuzzVocabularyWords; ++w) {
      auto v = RandomRootSift(rng);
      centroids.insert(centroids.end(), v.begin(), v.end());
    }
    sift::SiftOptions extractor;
    extractor.descriptor = sift::DescriptorKind::kRootSift;
    auto made = vocab::Vocabulary::FromCentroids(std::move(centroids), sift::kDescriptorDim,
                                                 sift::DescriptorKind::kRootSift, extractor.Describe());
    if (!made) CheckSetup(std::unexpected(made.error()), "fuzz vocabulary");
    return std::move(*made);
  }();
  return vocabulary;
}

sift::FeatureSet FuzzQueryFeatures() {
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> x(0.0f, 319.0f), y(0.0f, 239.0f), scale(1.5f, 12.0f), angle(0.0f, 6.28f);
  sift::FeatureSet features;
  features.image_width = 320;
  features.image_height = 240;
  features.kind = sift::DescriptorKind::kRootSift;
  for (int i = 0; i < 40; ++i) {
    sift::Keypoint k;
    k.x = x(rng);
    k.y = y(rng);
    k.scale = scale(rng);
    k.orientation = angle(rng);
    features.keypoints.push_back(k);
    auto d = RandomRootSift(rng);
    features.descriptors.insert(features.descriptors.end(), d.begin(), d.end());
  }
  return features;
}

}  // namespace oxbow::fuzz
