// NamedSampler, TrainDistributed and WithHammingDistributed on one rank (vocab::SingleProcess) and on
// several ranks as threads of this process (ThreadRanks below); several processes under mpirun are
// tested end to end in tests/mpi_test.cc.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <barrier>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <optional>
#include <random>
#include <thread>
#include <vector>

#include "sift/base/log.h"
#include "tests/support/temp_dir.h"
#include "vocab/distributed.h"

namespace oxbow::vocab {
namespace {

namespace fs = std::filesystem;

// Seeded blobs around a few centres: `rows` x `dim` values per image.
std::vector<float> ImageRows(int image, size_t rows, size_t dim = 16) {
  std::mt19937 rng(static_cast<unsigned>(image) + 11);
  std::normal_distribution<float> noise(0, 0.05f);
  std::vector<float> out(rows * dim);
  for (size_t r = 0; r < rows; ++r)
    for (size_t d = 0; d < dim; ++d) out[r * dim + d] = static_cast<float>((r + d) % 5) * 0.2f + noise(rng);
  return out;
}

// `size` ranks as threads of this process: every collective leaves each rank's contribution in a shared
// slot, waits for all, combines the slots in rank order and waits again before a slot is reused.
class ThreadRanks {
 public:
  explicit ThreadRanks(int size) : size_(size), barrier_(size), slots_(static_cast<size_t>(size)) {}

  // Runs body(comm) on every rank, each on its own thread; returns when all have returned.
  void Run(const std::function<void(Communicator&)>& body) {
    std::vector<std::thread> threads;
    threads.reserve(static_cast<size_t>(size_));
    for (int r = 0; r < size_; ++r) {
      threads.emplace_back([this, r, &body] {
        Rank comm(*this, r);
        body(comm);
      });
    }
    for (auto& t : threads) t.join();
  }

 private:
  class Rank final : public Communicator {
   public:
    Rank(ThreadRanks& ranks, int rank) : ranks_(ranks), rank_(rank) {}
    int rank() const override { return rank_; }
    int size() const override { return ranks_.size_; }
    void SumInPlace(std::span<int64_t> values) override {
      const std::vector<uint8_t> all = Allgather({reinterpret_cast<const uint8_t*>(values.data()), values.size_bytes()});
      std::vector<int64_t> sum(values.size(), 0);
      for (int r = 0; r < size(); ++r) {
        std::vector<int64_t> part(values.size());
        std::memcpy(part.data(), all.data() + r * values.size_bytes(), values.size_bytes());
        for (size_t i = 0; i < sum.size(); ++i) sum[i] += part[i];
      }
      std::copy(sum.begin(), sum.end(), values.begin());
    }
    double Max(double value) override {
      const std::vector<uint8_t> all = Allgather({reinterpret_cast<const uint8_t*>(&value), sizeof(value)});
      double out = value;
      for (int r = 0; r < size(); ++r) {
        double v;
        std::memcpy(&v, all.data() + r * sizeof(v), sizeof(v));
        out = std::max(out, v);
      }
      return out;
    }
    void Broadcast(std::span<uint8_t> bytes) override {
      const std::vector<uint8_t> all = Allgather(bytes);
      std::copy_n(all.begin(), bytes.size(), bytes.begin());  // rank 0's part comes first
    }
    std::vector<uint8_t> Allgather(std::span<const uint8_t> bytes) override {
      ranks_.slots_[static_cast<size_t>(rank_)].assign(bytes.begin(), bytes.end());
      ranks_.barrier_.arrive_and_wait();
      std::vector<uint8_t> out;
      for (const auto& slot : ranks_.slots_) out.insert(out.end(), slot.begin(), slot.end());
      ranks_.barrier_.arrive_and_wait();
      return out;
    }

   private:
    ThreadRanks& ranks_;
    int rank_;
  };

  int size_;
  std::barrier<> barrier_;
  std::vector<std::vector<uint8_t>> slots_;
};

std::string FileBytes(const Vocabulary& vocabulary, const fs::path& path) {
  EXPECT_TRUE(vocabulary.Write(path.string()));
  return oxbow::testing::FileBytes(path);
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
  std::vector<float> Centroids(const DistributedTrainOptions& options) {
    SingleProcess comm;
    auto result = TrainDistributed(sample_, comm, sift::DescriptorKind::kSift, "test", options);
    EXPECT_TRUE(result) << result.error().ToString();
    EXPECT_TRUE(result->finished);
    const auto c = result->vocabulary->centroids();
    return {c.begin(), c.end()};
  }

  oxbow::testing::TempDir temp_;  // removed with its contents after the test
  fs::path dir_{temp_.path()};
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

// ---- Hamming embedding ---------------------------------------------------------------------------

constexpr int kDim = 128;

// 128-d rows around 12 centres, with repeated rows (equal projected values: ties at the median), and a
// vocabulary of those centres plus 4 words far from every row (no row reaches them).
class DistributedHamming : public ::testing::Test {
 protected:
  void SetUp() override {
    log::SetLevel(log::Level::kWarning);
    std::mt19937 rng(5);
    std::normal_distribution<float> normal(0, 1);
    std::vector<float> centres(16 * kDim);
    for (float& v : centres) v = normal(rng);
    for (size_t c = 12; c < 16; ++c)
      for (size_t d = 0; d < kDim; ++d) centres[c * kDim + d] += 50.0f;
    const size_t rows = 1500;
    rows_.resize(rows * kDim);
    for (size_t r = 0; r < rows; ++r) {
      const size_t from = r % 7 == 3 ? r - 1 : r;  // every seventh row repeats its predecessor
      for (size_t d = 0; d < kDim; ++d)
        rows_[r * kDim + d] = from == r ? centres[(r % 12) * kDim + d] + 0.3f * normal(rng) : rows_[from * kDim + d];
    }
    // One word with a single row (its median is that row), from a centre no other row is near.
    for (size_t d = 0; d < kDim; ++d) rows_.push_back(centres[11 * kDim + d] - 20.0f);
    centres.insert(centres.end(), rows_.end() - kDim, rows_.end());
    QuantizerBuildOptions build;
    build.num_lists = 4;
    vocabulary_ = Vocabulary::FromCentroids(centres, kDim, sift::DescriptorKind::kSift, "test", build).value();
  }

  // Row i goes to rank (i * 7 + i / 5) mod ranks, each rank's rows in reverse order.
  DistributedSample Share(int rank, int ranks) const {
    DistributedSample out;
    out.dimension = kDim;
    const size_t n = rows_.size() / kDim;
    out.total_rows = n;
    for (size_t i = n; i-- > 0;) {
      if (static_cast<int>((i * 7 + i / 5) % static_cast<size_t>(ranks)) != rank) continue;
      out.position.push_back(static_cast<uint32_t>(i));
      out.descriptors.insert(out.descriptors.end(), rows_.begin() + static_cast<ptrdiff_t>(i * kDim),
                             rows_.begin() + static_cast<ptrdiff_t>((i + 1) * kDim));
    }
    return out;
  }

  oxbow::testing::TempDir temp_;  // removed with its contents after the test
  fs::path dir_{temp_.path()};
  std::vector<float> rows_;
  std::optional<Vocabulary> vocabulary_;
};

TEST_F(DistributedHamming, EqualsWithHammingOnAllRowsForAnyNumberOfRanks) {
  QuantizerOptions quantizer;
  quantizer.num_probes = 2;
  const Vocabulary expected = vocabulary_->WithHamming(rows_, 7, quantizer).value();
  const std::string expected_bytes = FileBytes(expected, dir_ / "expected.oxvoc");
  for (int ranks : {1, 2, 3}) {
    ThreadRanks threads(ranks);
    std::vector<std::optional<Vocabulary>> got(static_cast<size_t>(ranks));
    threads.Run([&](Communicator& comm) {
      auto v = WithHammingDistributed(*vocabulary_, Share(comm.rank(), ranks), comm, 7, quantizer);
      EXPECT_TRUE(v) << v.error().ToString();
      if (v) got[static_cast<size_t>(comm.rank())] = std::move(*v);
    });
    for (int r = 0; r < ranks; ++r) {
      ASSERT_TRUE(got[static_cast<size_t>(r)].has_value());
      EXPECT_TRUE(got[static_cast<size_t>(r)]->has_hamming());
      EXPECT_EQ(got[static_cast<size_t>(r)]->fingerprint(), expected.fingerprint()) << ranks << " ranks, rank " << r;
    }
    EXPECT_TRUE(FileBytes(*got[0], dir_ / "got.oxvoc") == expected_bytes) << ranks << " ranks";
  }
  SingleProcess one;
  const Vocabulary single = WithHammingDistributed(*vocabulary_, Share(0, 1), one, 7, quantizer).value();
  EXPECT_EQ(single.fingerprint(), expected.fingerprint());
  // Another seed: another projection.
  EXPECT_NE(WithHammingDistributed(*vocabulary_, Share(0, 1), one, 8, quantizer)->fingerprint(), expected.fingerprint());
}

TEST_F(DistributedHamming, MediansAreTheMiddleValueWithNegativesTiesAndSingleRows) {
  // Through the signatures: above the median of a word's projected values (the value at sorted position
  // count / 2) lie count - count / 2 - 1 values when they are distinct, fewer when the median repeats;
  // and a word's single row has a signature of zeros (its value is the median).
  SingleProcess one;
  const Vocabulary v = WithHammingDistributed(*vocabulary_, Share(0, 1), one, 3).value();
  const size_t n = rows_.size() / kDim;
  std::vector<uint32_t> words(n);
  v.Quantize(rows_, words);
  std::vector<uint64_t> signatures(n);
  v.Signatures(rows_, words, signatures);
  const uint32_t single_word = words.back();
  EXPECT_EQ(std::count(words.begin(), words.end(), single_word), 1);
  EXPECT_EQ(signatures.back(), 0u) << "the single row is its own median";
  std::vector<size_t> count(v.size(), 0);
  std::vector<std::array<size_t, kHammingBits>> above(v.size(), std::array<size_t, kHammingBits>{});
  for (size_t i = 0; i < n; ++i) {
    ++count[words[i]];
    for (int b = 0; b < kHammingBits; ++b) above[words[i]][b] += (signatures[i] >> b) & 1;
  }
  size_t used_words = 0;
  for (size_t w = 0; w < v.size(); ++w) {
    if (count[w] < 2) continue;
    ++used_words;
    for (int b = 0; b < kHammingBits; ++b) {
      EXPECT_LE(above[w][b], count[w] - count[w] / 2 - 1) << "word " << w << " bit " << b;
      // A value occurs at most twice (a repeated row), so one other copy of the median may lie above it.
      EXPECT_GE(above[w][b] + 1, count[w] - count[w] / 2 - 1) << "word " << w << " bit " << b;
    }
  }
  EXPECT_EQ(used_words, 12u);
}

TEST_F(DistributedHamming, EveryRankRefusesWhatOneRankSees) {
  ThreadRanks threads(2);
  std::vector<std::optional<ErrorCode>> codes(2);
  threads.Run([&](Communicator& comm) {
    DistributedSample share = Share(comm.rank(), 2);
    if (comm.rank() == 1) share.descriptors[3] = std::numeric_limits<float>::infinity();
    auto v = WithHammingDistributed(*vocabulary_, share, comm, 1);
    if (!v) codes[static_cast<size_t>(comm.rank())] = v.error().code;
  });
  EXPECT_EQ(codes[0], ErrorCode::kInvalidArgument);
  EXPECT_EQ(codes[1], ErrorCode::kInvalidArgument);
  SingleProcess one;
  DistributedSample empty;
  empty.dimension = kDim;
  EXPECT_EQ(WithHammingDistributed(*vocabulary_, empty, one, 1).error().code, ErrorCode::kInvalidArgument);
}

TEST(DistributedTrainHamming, TheVocabularyFileIsTheSameOnOneAndThreeRanksAndAsWithHammingAfterTraining) {
  log::SetLevel(log::Level::kWarning);
  const oxbow::testing::TempDir temp;
  const fs::path dir = temp.path();
  SampleOptions sample_options;
  sample_options.max_per_image = 80;
  sample_options.max_total = 500;
  DistributedTrainOptions options;
  options.train.num_words = 30;
  options.train.max_iterations = 4;
  options.train.seed = 3;
  options.train.num_threads = 1;
  options.train.quantizer.num_threads = 1;
  options.hamming = true;
  // Images dealt round-robin over the ranks, as `vocab train --mpi` does.
  const auto train = [&](int ranks, const DistributedTrainOptions& o) {
    ThreadRanks threads(ranks);
    std::vector<std::optional<Vocabulary>> got(static_cast<size_t>(ranks));
    DistributedSample whole;
    threads.Run([&](Communicator& comm) {
      NamedSampler sampler(sample_options, kDim);
      for (int image = comm.rank(); image < 8; image += comm.size())
        sampler.AddImage("img" + std::to_string(image), ImageRows(image, 120, kDim));
      const DistributedSample sample = sampler.Finish(comm);
      if (comm.size() == 1) whole = sample;
      auto result = TrainDistributed(sample, comm, sift::DescriptorKind::kSift, "test", o);
      EXPECT_TRUE(result) << result.error().ToString();
      if (result && result->vocabulary) got[static_cast<size_t>(comm.rank())] = std::move(*result->vocabulary);
    });
    return std::make_pair(got, whole);
  };
  const auto [one, sample] = train(1, options);
  const auto [three, unused] = train(3, options);
  ASSERT_TRUE(one[0].has_value());
  EXPECT_TRUE(one[0]->has_hamming());
  const std::string bytes = FileBytes(*one[0], dir / "np1.oxvoc");
  for (const auto& v : three) {
    ASSERT_TRUE(v.has_value()) << "every rank holds the vocabulary";
    EXPECT_TRUE(FileBytes(*v, dir / "np3.oxvoc") == bytes);
  }
  // The same centroids trained without the parameters, then WithHamming on the whole sample in one
  // process: the same file.
  options.hamming = false;
  const auto [plain, unused_sample] = train(1, options);
  ASSERT_TRUE(plain[0].has_value());
  EXPECT_FALSE(plain[0]->has_hamming());
  QuantizerOptions quantizer;
  quantizer.num_threads = 1;
  EXPECT_TRUE(FileBytes(plain[0]->WithHamming(sample.descriptors, 3, quantizer).value(), dir / "after.oxvoc") == bytes);
}

}  // namespace
}  // namespace oxbow::vocab
