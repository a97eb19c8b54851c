#include "sift/features_io.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <random>
#include <sstream>
#include <string>

#include "sift/base/binary_io.h"
#include "sift/sift.h"
#include "tests/support/temp_dir.h"

namespace oxbow::sift {
namespace {

namespace fs = std::filesystem;

class FeaturesIoTest : public ::testing::Test {
 protected:
  std::string Path(const std::string& name) const { return (dir_ / name).string(); }

  // Seeded random features: 37 keypoints with unit-norm non-negative descriptors.
  static FeatureFile RandomFile() {
    std::mt19937 rng(42);
    std::uniform_real_distribution<float> u(0.0f, 1.0f);
    FeatureFile file;
    file.features.image_width = 640;
    file.features.image_height = 480;
    file.features.kind = DescriptorKind::kRootSift;
    for (int i = 0; i < 37; ++i) {
      file.features.keypoints.push_back({u(rng) * 640, u(rng) * 480, 1 + u(rng) * 10, u(rng) * 6.28f, u(rng), i % 5 - 1});
      float norm2 = 0;
      std::vector<float> d(kDescriptorDim);
      for (float& v : d) {
        v = u(rng);
        norm2 += v * v;
      }
      for (float& v : d) file.features.descriptors.push_back(v / std::sqrt(norm2));
    }
    file.extractor_fingerprint = 0x0123456789abcdefull;
    file.extractor_description = "oxbow-sift/1;test";
    return file;
  }

  oxbow::testing::TempDir temp_;  // removed with its contents after the test
  fs::path dir_{temp_.path()};
};

TEST_F(FeaturesIoTest, RoundTripIsExact) {
  const FeatureFile file = RandomFile();
  ASSERT_TRUE(WriteFeatureFile(Path("a.oxfeat"), file));
  auto read = ReadFeatureFile(Path("a.oxfeat"));
  ASSERT_TRUE(read) << read.error().ToString();
  EXPECT_EQ(read->extractor_fingerprint, file.extractor_fingerprint);
  EXPECT_EQ(read->extractor_description, file.extractor_description);
  EXPECT_EQ(read->features.image_width, 640);
  EXPECT_EQ(read->features.image_height, 480);
  EXPECT_EQ(read->features.kind, DescriptorKind::kRootSift);
  ASSERT_EQ(read->features.size(), file.features.size());
  EXPECT_EQ(read->features.descriptors, file.features.descriptors);
  for (size_t i = 0; i < file.features.size(); ++i) {
    const Keypoint &a = file.features.keypoints[i], &b = read->features.keypoints[i];
    EXPECT_EQ(a.x, b.x);
    EXPECT_EQ(a.y, b.y);
    EXPECT_EQ(a.scale, b.scale);
    EXPECT_EQ(a.orientation, b.orientation);
    EXPECT_EQ(a.response, b.response);
    EXPECT_EQ(a.octave, b.octave);
  }
  // An empty feature set round-trips too.
  FeatureFile empty;
  empty.features.image_width = 3;
  empty.features.image_height = 2;
  ASSERT_TRUE(WriteFeatureFile(Path("empty.oxfeat"), empty));
  auto read_empty = ReadFeatureFile(Path("empty.oxfeat"));
  ASSERT_TRUE(read_empty);
  EXPECT_EQ(read_empty->features.size(), 0u);
}

TEST_F(FeaturesIoTest, DamagedFilesAreRefused) {
  ASSERT_TRUE(WriteFeatureFile(Path("a.oxfeat"), RandomFile()));
  auto bytes = io::ReadWholeFile(Path("a.oxfeat"));
  ASSERT_TRUE(bytes);
  // One flipped bit in the payload: the CRC catches it.
  auto damaged = *bytes;
  damaged[damaged.size() / 2] ^= 0x10;
  ASSERT_TRUE(io::WriteFileAtomically(Path("damaged.oxfeat"), damaged));
  auto read = ReadFeatureFile(Path("damaged.oxfeat"));
  ASSERT_FALSE(read);
  EXPECT_EQ(read.error().code, ErrorCode::kCorruptData);
  EXPECT_NE(read.error().message.find("damaged.oxfeat"), std::string::npos);
  // Truncated.
  std::vector<uint8_t> truncated(bytes->begin(), bytes->begin() + static_cast<long>(bytes->size() - 100));
  ASSERT_TRUE(io::WriteFileAtomically(Path("truncated.oxfeat"), truncated));
  read = ReadFeatureFile(Path("truncated.oxfeat"));
  ASSERT_FALSE(read);
  EXPECT_EQ(read.error().code, ErrorCode::kCorruptData);
  // Missing.
  read = ReadFeatureFile(Path("missing.oxfeat"));
  ASSERT_FALSE(read);
  EXPECT_EQ(read.error().code, ErrorCode::kNotFound);
}

TEST_F(FeaturesIoTest, ForeignAndOtherVersionFilesAreRefused) {
  const std::vector<uint8_t> payload = EncodeFeaturePayload(RandomFile());
  ASSERT_TRUE(io::WriteContainerFile(Path("vocab.bin"), "OXBWVOCB", 1, 0, payload));
  auto foreign = ReadFeatureFile(Path("vocab.bin"));
  ASSERT_FALSE(foreign);
  EXPECT_EQ(foreign.error().code, ErrorCode::kCorruptData);

  ASSERT_TRUE(io::WriteContainerFile(Path("v2.oxfeat"), kFeatureFileMagic, kFeatureFileVersion + 1, 0, payload));
  auto newer = ReadFeatureFile(Path("v2.oxfeat"));
  ASSERT_FALSE(newer);
  EXPECT_EQ(newer.error().code, ErrorCode::kIncompatible);

  ASSERT_TRUE(io::WriteContainerFile(Path("flags.oxfeat"), kFeatureFileMagic, kFeatureFileVersion, 4, payload));
  auto flagged = ReadFeatureFile(Path("flags.oxfeat"));
  ASSERT_FALSE(flagged);
  EXPECT_EQ(flagged.error().code, ErrorCode::kIncompatible);

  const std::string text = "just some text that is long enough to look like a header of forty bytes or more\n";
  ASSERT_TRUE(io::WriteFileAtomically(Path("text.oxfeat"), std::span(reinterpret_cast<const uint8_t*>(text.data()), text.size())));
  auto not_features = ReadFeatureFile(Path("text.oxfeat"));
  ASSERT_FALSE(not_features);
  EXPECT_EQ(not_features.error().code, ErrorCode::kCorruptData);
}

TEST_F(FeaturesIoTest, InconsistentPayloadIsRefusedEvenWithAValidChecksum) {
  std::vector<uint8_t> payload = EncodeFeaturePayload(RandomFile());
  // The keypoint count sits after 4+4+1+1+2+8 bytes and the length-prefixed description.
  const size_t count_at = 20 + 4 + RandomFile().extractor_description.size();
  payload[count_at] += 1;  // claims 38 keypoints, holds 37
  ASSERT_TRUE(io::WriteContainerFile(Path("count.oxfeat"), kFeatureFileMagic, kFeatureFileVersion, 0, payload));
  auto read = ReadFeatureFile(Path("count.oxfeat"));
  ASSERT_FALSE(read);
  EXPECT_EQ(read.error().code, ErrorCode::kCorruptData);
  EXPECT_NE(read.error().message.find("count"), std::string::npos) << read.error().message;

  std::vector<uint8_t> kind = EncodeFeaturePayload(RandomFile());
  kind[8] = 9;  // descriptor kind
  auto bad_kind = DecodeFeaturePayload(kind, "test");
  ASSERT_FALSE(bad_kind);
  EXPECT_EQ(bad_kind.error().code, ErrorCode::kCorruptData);
}

TEST_F(FeaturesIoTest, ColmapTextFormat) {
  const FeatureFile file = RandomFile();
  ASSERT_TRUE(WriteColmapFeatures(Path("img.jpg.txt"), file.features));
  std::ifstream in(Path("img.jpg.txt"));
  size_t n = 0, dim = 0;
  ASSERT_TRUE(in >> n >> dim);
  EXPECT_EQ(n, file.features.size());
  EXPECT_EQ(dim, 128u);
  std::vector<uint8_t> bytes;
  DescriptorsToUint8(file.features, &bytes);
  for (size_t i = 0; i < n; ++i) {
    double x, y, scale, orientation;
    ASSERT_TRUE(in >> x >> y >> scale >> orientation);
    EXPECT_NEAR(x, file.features.keypoints[i].x + 0.5, 1e-3);  // COLMAP's corner origin
    EXPECT_NEAR(y, file.features.keypoints[i].y + 0.5, 1e-3);
    EXPECT_NEAR(scale, file.features.keypoints[i].scale, 1e-4);
    EXPECT_NEAR(orientation, file.features.keypoints[i].orientation, 1e-4);
    for (int d = 0; d < 128; ++d) {
      int v;
      ASSERT_TRUE(in >> v);
      ASSERT_EQ(v, bytes[i * 128 + static_cast<size_t>(d)]);
    }
  }
  std::string rest;
  EXPECT_FALSE(in >> rest);
}

// The text is exactly printf's "%.6g" for the four numbers and the decimal bytes, for values of every
// length: negative, large, tiny, whole, at the edge of %.6g's switch to exponents, and all 256 bytes.
TEST_F(FeaturesIoTest, ColmapTextIsPrintfsText) {
  FeatureSet f;
  f.kind = DescriptorKind::kSift;
  const float values[] = {0.0f, -0.5f, 1.0f, 123456.0f, 999999.5f, 1234567.0f, -7654321.0f, 1e-5f, -3.4e38f,
                          2.5e-38f, 0.1f, 1.0f / 3.0f, 6.2831853f, 99999.95f};
  std::mt19937 rng(7);
  for (size_t i = 0; i < std::size(values); ++i) {
    const float v = values[i], w = values[(i + 5) % std::size(values)];
    f.keypoints.push_back({v, w, std::fabs(w) + 1.0f, v, 1.0f, 0});
    for (int d = 0; d < kDescriptorDim; ++d) f.descriptors.push_back(static_cast<float>(rng() % 1000) / 1000.0f);
  }
  // One descriptor with every byte value 0..255 spread over two keypoints' 256 dimensions.
  for (int half = 0; half < 2; ++half) {
    f.keypoints.push_back({1.0f, 2.0f, 3.0f, 0.0f, 1.0f, 0});
    for (int d = 0; d < kDescriptorDim; ++d) f.descriptors.push_back(static_cast<float>(half * 128 + d) / 512.0f);
  }
  ASSERT_TRUE(WriteColmapFeatures(Path("exact.txt"), f));
  const std::string written = oxbow::testing::FileBytes(Path("exact.txt"));

  std::vector<uint8_t> bytes;
  DescriptorsToUint8(f, &bytes);
  std::string expected = std::to_string(f.size()) + " 128\n";
  char buf[128];
  for (size_t i = 0; i < f.size(); ++i) {
    const Keypoint& k = f.keypoints[i];
    std::snprintf(buf, sizeof buf, "%.6g %.6g %.6g %.6g", k.x + 0.5, k.y + 0.5, k.scale, k.orientation);
    expected += buf;
    for (int d = 0; d < kDescriptorDim; ++d) expected += " " + std::to_string(bytes[i * kDescriptorDim + static_cast<size_t>(d)]);
    expected += "\n";
  }
  EXPECT_EQ(written, expected);
  // The byte values cover 0..255 (the last two keypoints), so every entry of the writer's table is used.
  std::vector<bool> seen(256, false);
  for (uint8_t b : bytes) seen[b] = true;
  EXPECT_EQ(std::count(seen.begin(), seen.end(), true), 256);
}

}  // namespace
}  // namespace oxbow::sift
