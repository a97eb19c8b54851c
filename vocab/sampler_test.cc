#include <gtest/gtest.h>

#include <map>
#include <vector>

#include "vocab/vocabulary.h"

namespace oxbow::vocab {
namespace {

// Image i has `rows` descriptors of dimension 2 whose values encode (image, row).
std::vector<float> ImageRows(int image, int rows) {
  std::vector<float> v;
  for (int r = 0; r < rows; ++r) {
    v.push_back(static_cast<float>(image));
    v.push_back(static_cast<float>(r));
  }
  return v;
}

TEST(SamplerTest, CapsPerImageAndInTotal) {
  SampleOptions options;
  options.max_per_image = 10;
  options.max_total = 35;
  DescriptorSampler sampler(options, 2);
  for (int i = 0; i < 8; ++i) sampler.AddImage(ImageRows(i, i == 3 ? 4 : 50));
  EXPECT_EQ(sampler.images_seen(), 8u);
  EXPECT_EQ(sampler.rows_seen(), 7u * 10 + 4);
  ASSERT_EQ(sampler.size(), 35u);
  std::map<int, int> per_image;
  std::map<std::pair<int, int>, int> seen;
  const auto& d = sampler.descriptors();
  for (size_t r = 0; r < sampler.size(); ++r) {
    ++per_image[static_cast<int>(d[2 * r])];
    const std::pair<int, int> key(static_cast<int>(d[2 * r]), static_cast<int>(d[2 * r + 1]));
    EXPECT_EQ(++seen[key], 1) << "a row sampled twice";
  }
  for (auto [image, count] : per_image) EXPECT_LE(count, image == 3 ? 4 : 10);
}

TEST(SamplerTest, DeterministicForSeedAndDifferentAcrossSeeds) {
  auto run = [](uint64_t seed) {
    SampleOptions options;
    options.max_per_image = 7;
    options.max_total = 20;
    options.seed = seed;
    DescriptorSampler sampler(options, 2);
    for (int i = 0; i < 10; ++i) sampler.AddImage(ImageRows(i, 30));
    return sampler.TakeDescriptors();
  };
  EXPECT_EQ(run(5), run(5));
  EXPECT_NE(run(5), run(6));
}

// Every image should be about equally represented when all images have the same size: over many seeds
// each of 10 images gets close to a tenth of the reservoir.
TEST(SamplerTest, ReservoirIsUniformOverImages) {
  std::vector<int> per_image(10, 0);
  int total = 0;
  for (uint64_t seed = 1; seed <= 200; ++seed) {
    SampleOptions options;
    options.max_per_image = 20;
    options.max_total = 50;
    options.seed = seed;
    DescriptorSampler sampler(options, 2);
    for (int i = 0; i < 10; ++i) sampler.AddImage(ImageRows(i, 40));
    for (size_t r = 0; r < sampler.size(); ++r) ++per_image[static_cast<int>(sampler.descriptors()[2 * r])];
    total += static_cast<int>(sampler.size());
  }
  for (int count : per_image) EXPECT_NEAR(count, total / 10.0, total * 0.015);  // 1000 expected, +-150
}

TEST(SamplerTest, OptionsCheck) {
  SampleOptions options;
  EXPECT_FALSE(options.Check());
  options.max_total = 0;
  EXPECT_TRUE(options.Check());
}

}  // namespace
}  // namespace oxbow::vocab
