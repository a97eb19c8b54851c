// PartitionOf (the routing every builder and front must agree on) and the global frequency file.
#include "api/partition.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "sift/base/hash.h"
#include "tests/support/temp_dir.h"

namespace oxbow::api {
namespace {

namespace fs = std::filesystem;

TEST(Partition, IsFnv1a64OfTheIdModuloP) {
  // Published FNV-1a 64 test vectors: a change here would move every stored image to another partition.
  EXPECT_EQ(Fnv1a64(""), 0xcbf29ce484222325ull);
  EXPECT_EQ(Fnv1a64("a"), 0xaf63dc4c8601ec8cull);
  EXPECT_EQ(Fnv1a64("foobar"), 0x85944171f73967e8ull);
  EXPECT_EQ(PartitionOf("a", 7), 0xaf63dc4c8601ec8cull % 7);
  EXPECT_EQ(PartitionOf("foobar", 3), 0x85944171f73967e8ull % 3);
  EXPECT_EQ(PartitionOf("anything", 1), 0u);
  EXPECT_THROW(PartitionOf("a", 0), InvariantError);
  EXPECT_EQ(PartitionFolder("/c", 2), "/c/partition-2");
}

TEST(Partition, SpreadsIdsOverAllPartitions) {
  std::vector<int> counts(4, 0);
  for (int i = 0; i < 4000; ++i) ++counts[PartitionOf("img" + std::to_string(i), 4)];
  for (int c : counts) EXPECT_NEAR(c, 1000, 150);
}

class GlobalFrequenciesFile : public ::testing::Test {
 protected:
  void SetUp() override {
    path_ = (dir_ / "global-frequencies.oxdf").string();
  }
  oxbow::testing::TempDir temp_;  // removed with its contents after the test
  fs::path dir_{temp_.path()};
  std::string path_;
};

TEST_F(GlobalFrequenciesFile, RoundTrips) {
  const GlobalFrequencies f{3, 1, 0x1234abcdull, 10, {0, 3, 10, 1}};
  ASSERT_TRUE(WriteGlobalFrequencies(path_, f));
  auto back = ReadGlobalFrequencies(path_);
  ASSERT_TRUE(back) << back.error().ToString();
  EXPECT_EQ(*back, f);
}

TEST_F(GlobalFrequenciesFile, RefusesDamagedMissingAndInconsistentFiles) {
  EXPECT_EQ(ReadGlobalFrequencies(path_).error().code, ErrorCode::kNotFound);
  ASSERT_TRUE(WriteGlobalFrequencies(path_, {2, 0, 7, 5, {1, 2, 5}}));
  {
    std::fstream file(path_, std::ios::in | std::ios::out | std::ios::binary);
    file.seekp(-3, std::ios::end);
    file.put('\x7f');
  }
  EXPECT_EQ(ReadGlobalFrequencies(path_).error().code, ErrorCode::kCorruptData);
  ASSERT_TRUE(WriteGlobalFrequencies(path_, {2, 2, 7, 5, {1}}));  // partition outside the cluster
  EXPECT_EQ(ReadGlobalFrequencies(path_).error().code, ErrorCode::kCorruptData);
  ASSERT_TRUE(WriteGlobalFrequencies(path_, {2, 0, 7, 5, {6}}));  // more images with a word than images
  EXPECT_EQ(ReadGlobalFrequencies(path_).error().code, ErrorCode::kCorruptData);
}

}  // namespace
}  // namespace oxbow::api
