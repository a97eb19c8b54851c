// Hamming-embedding parameters of a vocabulary (Vocabulary::WithHamming, Signatures, file format 2).
#include <gtest/gtest.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <filesystem>
#include <limits>
#include <random>

#include "sift/base/binary_io.h"
#include "sift/base/log.h"
#include "tests/support/random_descriptors.h"
#include "tests/support/temp_dir.h"
#include "vocab/vocabulary.h"

namespace oxbow::vocab {
namespace {

namespace fs = std::filesystem;
constexpr int kDim = 128;
constexpr size_t kWords = 32;

// A file in this test binary's temporary folder (removed at exit).
std::string TempPath(const std::string& name) {
  static const oxbow::testing::TempDir dir("oxbow-vocabulary-hamming-test");
  return (dir / name).string();
}


// `per_word` descriptors around every centroid (per-dimension noise sigma).
std::vector<float> SampleAround(std::span<const float> centroids, size_t per_word, float sigma, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<float> g(0, sigma);
  std::vector<float> out;
  const size_t k = centroids.size() / kDim;
  for (size_t w = 0; w < k; ++w) {
    for (size_t i = 0; i < per_word; ++i) {
      for (int d = 0; d < kDim; ++d) out.push_back(centroids[w * kDim + d] + g(rng));
    }
  }
  return out;
}

class HammingVocabularyTest : public ::testing::Test {
 protected:
  void SetUp() override {
    log::SetLevel(log::Level::kWarning);
    auto v = Vocabulary::FromCentroids(testing::RandomUnitRows(kWords, kDim, 1), kDim, sift::DescriptorKind::kRootSift, "x");
    ASSERT_TRUE(v) << v.error().ToString();
    plain_ = std::make_unique<Vocabulary>(*v);
    sample_ = SampleAround(v->centroids(), 101, 0.03f, 2);
    auto he = v->WithHamming(sample_, 7, QuantizerOptions{.exact = true});
    ASSERT_TRUE(he) << he.error().ToString();
    hamming_ = std::make_unique<Vocabulary>(*he);
  }
  std::unique_ptr<Vocabulary> plain_, hamming_;
  std::vector<float> sample_;
};

TEST_F(HammingVocabularyTest, MediansSplitEachWordsSampleInHalves) {
  EXPECT_FALSE(plain_->has_hamming());
  EXPECT_TRUE(hamming_->has_hamming());
  const size_t n = sample_.size() / kDim;
  std::vector<uint32_t> words(n);
  hamming_->Quantize(sample_, words, {.exact = true});
  std::vector<uint64_t> signatures(n);
  hamming_->Signatures(sample_, words, signatures);
  // Per word and bit: the median is one of the word's projected values, so exactly the values above it
  // set the bit: (count - 1) / 2 of them when they are distinct (count odd). Two float32 projections
  // can round to the median's value (which ones depends on the build's floating-point code: the
  // ASan build at -O1 has such a tie where the -O2 build has none), and a tie only lowers the count.
  std::vector<std::array<int, kHammingBits>> ones(kWords);
  std::vector<int> count(kWords, 0);
  for (size_t i = 0; i < n; ++i) {
    ++count[words[i]];
    for (int b = 0; b < kHammingBits; ++b) ones[words[i]][b] += static_cast<int>(signatures[i] >> b & 1);
  }
  int exact = 0;
  for (size_t w = 0; w < kWords; ++w) {
    ASSERT_EQ(count[w], 101) << "the sample's descriptors stay in their word";
    for (int b = 0; b < kHammingBits; ++b) {
      EXPECT_LE(ones[w][b], 50) << "word " << w << " bit " << b;
      EXPECT_GE(ones[w][b], 48) << "word " << w << " bit " << b;
      exact += ones[w][b] == 50;
    }
  }
  EXPECT_GE(exact, static_cast<int>(kWords * kHammingBits) - 3) << "more ties than float32 rounding explains";
}

TEST_F(HammingVocabularyTest, NearDescriptorsHaveNearSignatures) {
  const std::vector<float> a = SampleAround(hamming_->centroids().first(kDim), 200, 0.03f, 11);
  std::vector<float> near = a;
  std::mt19937_64 rng(3);
  std::normal_distribution<float> tiny(0, 0.002f);
  for (float& v : near) v += tiny(rng);
  const std::vector<float> other = SampleAround(hamming_->centroids().first(kDim), 200, 0.03f, 12);
  const std::vector<uint32_t> words(200, 0);
  std::vector<uint64_t> sa(200), sn(200), so(200);
  hamming_->Signatures(a, words, sa);
  hamming_->Signatures(near, words, sn);
  hamming_->Signatures(other, words, so);
  double near_sum = 0, other_sum = 0;
  for (size_t i = 0; i < 200; ++i) {
    near_sum += std::popcount(sa[i] ^ sn[i]);
    other_sum += std::popcount(sa[i] ^ so[i]);
  }
  EXPECT_LT(near_sum / 200, 6);        // a small perturbation flips few bits
  EXPECT_GT(other_sum / 200, 24);      // independent descriptors of the word: about half of the 64
  EXPECT_LT(other_sum / 200, 40);
}

TEST_F(HammingVocabularyTest, FileFormatsRoundTripAndOldFilesStayVersionOne) {
  EXPECT_NE(hamming_->fingerprint(), plain_->fingerprint());
  const std::string plain_path = TempPath("plain.oxvoc"), he_path = TempPath("he.oxvoc");
  ASSERT_TRUE(plain_->Write(plain_path));
  ASSERT_TRUE(hamming_->Write(he_path));
  auto plain_container = io::ReadContainerFile(plain_path, "OXBWVOCB", 1, 2);
  auto he_container = io::ReadContainerFile(he_path, "OXBWVOCB", 1, 2);
  ASSERT_TRUE(plain_container && he_container);
  EXPECT_EQ(plain_container->version, 1u);  // older builds still read vocabularies without embedding
  EXPECT_EQ(he_container->version, 2u);
  auto plain = Vocabulary::Read(plain_path);
  auto he = Vocabulary::Read(he_path);
  ASSERT_TRUE(plain && he);
  EXPECT_FALSE(plain->has_hamming());
  EXPECT_EQ(plain->fingerprint(), plain_->fingerprint());
  ASSERT_TRUE(he->has_hamming());
  EXPECT_EQ(he->fingerprint(), hamming_->fingerprint());
  const size_t n = sample_.size() / kDim;
  std::vector<uint32_t> words(n);
  hamming_->Quantize(sample_, words);
  std::vector<uint64_t> a(n), b(n);
  hamming_->Signatures(sample_, words, a);
  he->Signatures(sample_, words, b);
  EXPECT_EQ(a, b);
  // Same seed, same sample: the same parameters; another seed: another projection.
  auto again = plain_->WithHamming(sample_, 7, {.exact = true});
  auto reseeded = plain_->WithHamming(sample_, 8, {.exact = true});
  ASSERT_TRUE(again && reseeded);
  EXPECT_EQ(again->fingerprint(), hamming_->fingerprint());
  EXPECT_NE(reseeded->fingerprint(), hamming_->fingerprint());
  // A truncated embedding is damage, not a smaller vocabulary.
  auto container = *he_container;
  container.payload.resize(container.payload.size() - 4);
  ASSERT_TRUE(io::WriteContainerFile(he_path, "OXBWVOCB", 2, 0, container.payload));
  auto truncated = Vocabulary::Read(he_path);
  ASSERT_FALSE(truncated);
  EXPECT_EQ(truncated.error().code, ErrorCode::kCorruptData);
  fs::remove(plain_path);
  fs::remove(he_path);
}

TEST_F(HammingVocabularyTest, RefusesUnusableSamples) {
  EXPECT_FALSE(plain_->WithHamming({}, 1));
  EXPECT_FALSE(plain_->WithHamming(std::span<const float>(sample_).first(100), 1));
  std::vector<float> bad = sample_;
  bad[5] = std::nanf("");
  EXPECT_FALSE(plain_->WithHamming(bad, 1));
}

TEST_F(HammingVocabularyTest, ThePiecesGiveWhatWithHammingGives) {
  // The projection and the projected values WithHamming uses, and parameters set from them.
  const std::vector<float> projection = plain_->HammingProjection(7);
  ASSERT_EQ(projection.size(), size_t{kHammingBits} * kDim);
  const size_t n = sample_.size() / kDim;
  std::vector<float> projected(n * kHammingBits);
  plain_->ProjectForHamming(projection, sample_, projected);
  std::vector<uint32_t> words(n);
  plain_->Quantize(sample_, words, QuantizerOptions{.exact = true});
  // Each word's medians from the pieces (the value at sorted position count / 2, as WithHamming takes).
  std::vector<float> medians(kWords * kHammingBits);
  for (size_t w = 0; w < kWords; ++w) {
    for (int b = 0; b < kHammingBits; ++b) {
      std::vector<float> column;
      for (size_t i = 0; i < n; ++i)
        if (words[i] == w) column.push_back(projected[i * kHammingBits + b]);
      ASSERT_FALSE(column.empty());
      std::sort(column.begin(), column.end());
      medians[w * kHammingBits + b] = column[column.size() / 2];
    }
  }
  const auto rebuilt = plain_->WithHammingParameters(projection, medians);
  ASSERT_TRUE(rebuilt) << rebuilt.error().ToString();
  EXPECT_EQ(rebuilt->fingerprint(), hamming_->fingerprint());
  std::vector<uint64_t> a(n), b(n);
  rebuilt->Signatures(sample_, words, a);
  hamming_->Signatures(sample_, words, b);
  EXPECT_EQ(a, b);

  EXPECT_FALSE(plain_->WithHammingParameters(projection, std::vector<float>(medians.begin(), medians.end() - 1)));
  EXPECT_FALSE(plain_->WithHammingParameters(std::vector<float>(projection.begin() + 1, projection.end()), medians));
  medians[3] = std::numeric_limits<float>::infinity();
  EXPECT_FALSE(plain_->WithHammingParameters(projection, medians));
}

}  // namespace
}  // namespace oxbow::vocab
