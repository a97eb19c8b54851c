// Packed words + geometry (storage/feature_store.h): round trip, the reference layout, PackBlob.
#include "index/storage/test_support.h"

#include <gtest/gtest.h>

namespace oxbow::index {
namespace {

using namespace test_support;  // NOLINT(google-build-using-namespace): the tests' shared fixtures

class FeatureStoreTest : public IndexFixture {};
TEST_F(FeatureStoreTest, PackedFeaturesRoundTrip) {
  std::mt19937_64 rng(10);
  const auto f = RandomImage(rng, 200, 1000, 700);
  std::vector<uint32_t> words(f.size());
  vocabulary_.Quantize(f.descriptors, words);
  const PackedFeatures packed = PackedFeatures::Pack(f.keypoints, words, 1000, 700);
  ASSERT_EQ(packed.size(), f.size());
  const auto blob = packed.Serialize();
  const auto back = PackedFeatures::Deserialize(blob, "test");
  ASSERT_TRUE(back);
  EXPECT_EQ(back->Words(), packed.Words());
  // Every original keypoint has a dequantised twin within the documented error.
  size_t matched = 0;
  for (size_t i = 0; i < f.size(); ++i) {
    for (size_t j = 0; j < back->size(); ++j) {
      const auto k = back->keypoint(j);
      if (back->word(j) == words[i] && std::abs(k.x - f.keypoints[i].x) < 0.01f &&
          std::abs(k.y - f.keypoints[i].y) < 0.01f) {
        EXPECT_NEAR(std::log2(k.scale / f.keypoints[i].scale), 0, 1.0 / 32 + 1e-6);
        double d = std::fmod(std::abs(k.orientation - f.keypoints[i].orientation), 2 * std::numbers::pi);
        d = std::min(d, 2 * std::numbers::pi - d);
        EXPECT_LE(d, std::numbers::pi / 256 + 1e-5);
        ++matched;
        break;
      }
    }
  }
  EXPECT_EQ(matched, f.size());
  auto damaged = blob;
  damaged[damaged.size() - 3] ^= 0x40;
  EXPECT_EQ(PackedFeatures::Deserialize(damaged, "test").error().code, ErrorCode::kCorruptData);
  auto truncated = blob;
  truncated.resize(blob.size() - 9);
  EXPECT_EQ(PackedFeatures::Deserialize(truncated, "test").error().code, ErrorCode::kCorruptData);
  auto future = blob;
  future[4] = 7;
  EXPECT_EQ(PackedFeatures::Deserialize(future, "test").error().code, ErrorCode::kIncompatible);
}

// Pack's bytes against the layout written out with libm's rounding and a stable sort: the radix sort
// and the rounding without libm must give exactly these. Words span all 24 bits (three radix passes)
// with many repeats (ties keep input order); coordinates include exact halves of a quantisation step.
TEST_F(FeatureStoreTest, BytesEqualTheReferenceLayout) {
  std::mt19937_64 rng(12);
  for (const uint32_t max_word : {7u, 100'000u, kMaxPackedWord}) {
    const int width = 65535, height = 480;  // x = m + 0.5 is then exactly half a quantisation step
    std::vector<sift::Keypoint> keypoints;
    std::vector<uint32_t> words;
    std::vector<uint64_t> signatures;
    std::uniform_real_distribution<float> unit(0.0f, 1.0f);
    for (int i = 0; i < 3000; ++i) {
      sift::Keypoint k;
      k.x = i % 7 == 0 ? static_cast<float>(i % 65534) + 0.5f : unit(rng) * width;
      k.y = i % 5 == 0 ? static_cast<float>(height) : unit(rng) * height * 1.1f - 0.05f * height;
      k.scale = i % 11 == 0 ? 0.01f : std::exp2(unit(rng) * 12.0f - 4.5f);
      k.orientation = (unit(rng) - 0.5f) * 20.0f;
      keypoints.push_back(k);
      words.push_back(i % 3 == 0 ? max_word : static_cast<uint32_t>(rng() % (max_word + 1)));
      signatures.push_back(rng());
    }
    const PackedFeatures packed = PackedFeatures::Pack(keypoints, words, width, height, signatures);
    std::vector<size_t> order(words.size());
    std::iota(order.begin(), order.end(), size_t{0});
    std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) { return words[a] < words[b]; });
    ASSERT_EQ(packed.bytes().size(), words.size() * kPackedFeatureBytes);
    int halves = 0;
    for (size_t j = 0; j < order.size(); ++j) {
      const size_t i = order[j];
      const sift::Keypoint& k = keypoints[i];
      const double qx = std::clamp(static_cast<double>(k.x) / width, 0.0, 1.0) * 65535.0;
      halves += qx - std::floor(qx) == 0.5 ? 1 : 0;
      const auto x = static_cast<uint16_t>(std::round(std::clamp(static_cast<double>(k.x) / width, 0.0, 1.0) * 65535.0));
      const auto y = static_cast<uint16_t>(std::round(std::clamp(static_cast<double>(k.y) / height, 0.0, 1.0) * 65535.0));
      const double log_scale = std::log2(static_cast<double>(k.scale));
      const int sc = static_cast<int>(std::clamp(std::round((log_scale + 4.0) * 16.0), 0.0, 255.0));
      double turns = static_cast<double>(k.orientation) / (2 * std::numbers::pi);
      turns -= std::floor(turns);
      const int o = static_cast<int>(std::lround(turns * 256.0)) & 255;
      const std::array<uint8_t, kPackedFeatureBytes> expected = {
          static_cast<uint8_t>(words[i]), static_cast<uint8_t>(words[i] >> 8), static_cast<uint8_t>(words[i] >> 16),
          static_cast<uint8_t>(x),        static_cast<uint8_t>(x >> 8),        static_cast<uint8_t>(y),
          static_cast<uint8_t>(y >> 8),   static_cast<uint8_t>(sc),            static_cast<uint8_t>(o)};
      const auto got = packed.bytes().subspan(j * kPackedFeatureBytes, kPackedFeatureBytes);
      ASSERT_TRUE(std::equal(got.begin(), got.end(), expected.begin())) << "feature " << j << ", max word " << max_word;
      ASSERT_EQ(packed.signature(j), signatures[i]) << "feature " << j;
    }
    EXPECT_GT(halves, 300) << "the exact halves this test relies on";
  }
}

// The BLOB a batch add makes in place (PackBlob) is what Serialize() of Pack gives, byte for byte, and
// the features it returns read as Pack's; the buffer has no byte left unwritten.
TEST_F(FeatureStoreTest, PackBlobWritesSerializeBytesInPlace) {
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  for (const bool with_signatures : {false, true}) {
    for (const size_t n : {size_t{0}, size_t{1}, size_t{2500}}) {
      std::vector<sift::Keypoint> keypoints(n);
      std::vector<uint32_t> words(n);
      std::vector<uint64_t> signatures;
      for (size_t i = 0; i < n; ++i) {
        keypoints[i].x = unit(rng) * 640;
        keypoints[i].y = unit(rng) * 480;
        keypoints[i].scale = std::exp2(unit(rng) * 6.0f);
        keypoints[i].orientation = unit(rng) * 6.0f;
        words[i] = static_cast<uint32_t>(rng() % 5000);
        if (with_signatures) signatures.push_back(rng());
      }
      const std::vector<uint8_t> expected = PackedFeatures::Pack(keypoints, words, 640, 480, signatures).Serialize();
      ASSERT_EQ(PackedFeatures::BlobBytes(n, with_signatures), expected.size());
      for (const uint8_t fill : {uint8_t{0x00}, uint8_t{0xA5}}) {
        auto buffer = std::make_shared<std::vector<uint8_t>>(expected.size(), fill);
        const PackedFeatures packed = PackedFeatures::PackBlob(keypoints, words, 640, 480, signatures, *buffer, buffer);
        EXPECT_EQ(*buffer, expected) << n << " features, signatures " << with_signatures << ", fill " << int{fill};
        const auto read = PackedFeatures::Deserialize(*buffer, "the test's BLOB");
        ASSERT_TRUE(read.has_value()) << read.error().message;
        ASSERT_EQ(packed.size(), n);
        EXPECT_EQ(packed.has_signatures(), with_signatures || n == 0);
        for (size_t i = 0; i < n; ++i) {
          ASSERT_EQ(packed.word(i), read->word(i));
          ASSERT_EQ(packed.keypoint(i).x, read->keypoint(i).x);
          if (with_signatures) {
            ASSERT_EQ(packed.signature(i), read->signature(i));
          }
        }
      }
    }
  }
}

}  // namespace
}  // namespace oxbow::index
