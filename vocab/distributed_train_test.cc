// NamedSampler and TrainDistributed on one rank (vocab::SingleProcess); several ranks under mpirun are
// tested end to end in tests/mpi_test.cc.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <random>
#include <vector>

#include "sift/base/log.h"
#include "vocab/distributed.h"

namespace oxbow::vocab {
namespace {

namespace fs = std::filesystem;

// Seeded blobs around a few centres: `rows` x 16 values per image.
std::vector<float> ImageRows(int image, size_t rows) {
  std::mt19937 rng(static_cast<unsigned>(image) + 11);
  std::normal_distribution<float> noise(0, 0.05f);
  std::vector<float> out(rows * 16);
  for (size_t r = 0; r < rows; ++r)
    for (size_t d = 0; d < 16; ++d) out[r * 16 + d] = static_cast<float>((r + d) % 5) * 0.2f + noise(rng);
  return out;
}

DistributedSample Sample(const std::vector<int>& order, const SampleOptions& options) {
  SingleProcess comm;
  NamedSampler sampler(options, 16);
  for (int image : order) sampler.AddImage("img" + std::to_string(image), ImageRows(image, 100));
  return sampler.Finish(comm);
}

TEST(NamedSampler, DependsOnNamesNotOnTheOrderImagesArrive) {
  SampleOptions options;
  options.max_per_image = 60;
  options.max_total = 200;
  const DistributedSample a = Sample({0, 1, 2, 3, 4}, options);
  const DistributedSample b = Sample({3, 0, 4, 2, 1}, options);
  ASSERT_EQ(a.total_rows, 200u);
  EXPECT_EQ(a.rows_seen, 300u);
  EXPECT_EQ(a.images_seen, 5u);
  EXPECT_EQ(a.descriptors, b.descriptors);
  EXPECT_EQ(a.position, b.position);
  EXPECT_EQ(a.identity, b.identity);
  options.seed = 2;
  EXPECT_NE(Sample({0, 1, 2, 3, 4}, options).identity, a.identity);
}

class DistributedTrain : public ::testing::Test {
 protected:
  void SetUp() override {
    log::SetLevel(log::Level::kWarning);
    dir_ = fs::temp_directory_path() / ("oxbow_kmeans_" + std::to_string(::getpid()));
    fs::create_directories(dir_);
    SampleOptions sample;
    sample.max_total = 400;
    sample_ = Sample({0, 1, 2, 3, 4, 5}, sample);
    options_.train.num_words = 40;
    options_.train.max_iterations = 6;
    options_.train.min_relative_improvement = 0;
    options_.train.assignment = AssignmentMethod::kInvertedFile;
    options_.train.ivf_probes = 1;  // approximate enough that a row's previous word matters
    options_.train.num_threads = 2;
    options_.train.quantizer.num_threads = 1;
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::vector<float> Centroids(const DistributedTrainOptions& options) {
    SingleProcess comm;
    auto result = TrainDistributed(sample_, comm, sift::DescriptorKind::kSift, "test", options);
    EXPECT_TRUE(result) << result.error().ToString();
    EXPECT_TRUE(result->finished);
    const auto c = result->vocabulary->centroids();
    return {c.begin(), c.end()};
  }

  fs::path dir_;
  DistributedSample sample_;
  DistributedTrainOptions options_;
};

TEST_F(DistributedTrain, ResumedFromItsCheckpointEqualsTheUninterruptedRun) {
  const std::vector<float> whole = Centroids(options_);
  DistributedTrainOptions stopped = options_;
  stopped.checkpoint_path = (dir_ / "k.checkpoint").string();
  stopped.stop_after_iterations = 2;
  SingleProcess comm;
  TrainReport report;
  auto first = TrainDistributed(sample_, comm, sift::DescriptorKind::kSift, "test", stopped, &report);
  ASSERT_TRUE(first) << first.error().ToString();
  EXPECT_FALSE(first->finished);
  EXPECT_EQ(report.iterations.size(), 2u);
  ASSERT_TRUE(fs::exists(stopped.checkpoint_path));
  stopped.stop_after_iterations = 0;
  auto second = TrainDistributed(sample_, comm, sift::DescriptorKind::kSift, "test", stopped, &report);
  ASSERT_TRUE(second) << second.error().ToString();
  EXPECT_EQ(second->resumed_after_iteration, 2);
  ASSERT_FALSE(report.iterations.empty());
  EXPECT_EQ(report.iterations.front().iteration, 3);
  const auto c = second->vocabulary->centroids();
  EXPECT_EQ(std::vector<float>(c.begin(), c.end()), whole);
  // More threads: the same centroids (integer sums).
  options_.train.num_threads = 3;
  EXPECT_EQ(Centroids(options_), whole);
}

TEST_F(DistributedTrain, RefusesDamagedAndForeignCheckpoints) {
  DistributedTrainOptions stopped = options_;
  stopped.checkpoint_path = (dir_ / "k.checkpoint").string();
  stopped.stop_after_iterations = 1;
  SingleProcess comm;
  ASSERT_TRUE(TrainDistributed(sample_, comm, sift::DescriptorKind::kSift, "test", stopped));
  stopped.train.seed = 9;  // other options
  auto foreign = TrainDistributed(sample_, comm, sift::DescriptorKind::kSift, "test", stopped);
  ASSERT_FALSE(foreign);
  EXPECT_EQ(foreign.error().code, ErrorCode::kIncompatible);
  stopped.train.seed = options_.train.seed;
  {
    std::fstream file(stopped.checkpoint_path, std::ios::in | std::ios::out | std::ios::binary);
    file.seekp(-5, std::ios::end);
    file.put('\x55');
  }
  auto damaged = TrainDistributed(sample_, comm, sift::DescriptorKind::kSift, "test", stopped);
  ASSERT_FALSE(damaged);
  EXPECT_EQ(damaged.error().code, ErrorCode::kCorruptData);
}

TEST_F(DistributedTrain, RefusesTooFewRowsAndNonFiniteValues) {
  SingleProcess comm;
  options_.train.num_words = 401;
  EXPECT_EQ(TrainDistributed(sample_, comm, sift::DescriptorKind::kSift, "", options_).error().code,
            ErrorCode::kInvalidArgument);
  options_.train.num_words = 40;
  sample_.descriptors[7] = std::numeric_limits<float>::quiet_NaN();
  EXPECT_EQ(TrainDistributed(sample_, comm, sift::DescriptorKind::kSift, "", options_).error().code,
            ErrorCode::kInvalidArgument);
}

}  // namespace
}  // namespace oxbow::vocab
