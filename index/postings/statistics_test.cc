// Collection statistics (statistics.h): idf, the norm sums, and their refresh.
#include "index/postings/statistics.h"

#include <gtest/gtest.h>

#include <cmath>
#include <map>
#include <random>
#include <vector>

#include "index/postings/testing.h"

namespace oxbow::index {
namespace {

using postings::testing::AddAll;
using postings::testing::AllScores;
using postings::testing::RandomBag;
using postings::testing::ReferenceScores;

// Idf, its tables, t(tf) and an image's norm from its sums, against the definition: N = 8 and n_w = 0,
// 1, 2, 8 for words 0..3.
TEST(CollectionStatistics, IdfTablesAndNormsFollowTheDefinition) {
  CowArray<uint32_t> df;
  {
    CowArray<uint32_t>::Editor editor(&df);
    editor.Resize(4, 0);
    editor.Mutable(1) = 1;
    editor.Mutable(2) = 2;
    editor.Mutable(3) = 8;
  }
  for (const bool sqrt_tf : {true, false}) {
    const postings::CollectionStatistics statistics(sqrt_tf, df, 8);
    EXPECT_TRUE(std::isinf(statistics.Idf(0)));
    EXPECT_DOUBLE_EQ(statistics.Idf(1), std::log(8.0));
    EXPECT_DOUBLE_EQ(statistics.Idf(2), std::log(4.0));
    EXPECT_EQ(statistics.Idf(3), 0.0);
    const auto squared = statistics.IdfSquaredTable();
    ASSERT_EQ(squared->size(), 4u);
    EXPECT_EQ((*squared)[0], 0.0) << "n_w = 0: no finite idf";
    EXPECT_DOUBLE_EQ((*squared)[1], std::log(8.0) * std::log(8.0));
    EXPECT_EQ((*squared)[3], 0.0);
    // NOLINTNEXTLINE(performance-unnecessary-copy-initialization): the copy is what is tested
    const postings::CollectionStatistics copy = statistics;
    EXPECT_EQ(copy.IdfSquaredTable(), squared) << "made once, shared by copies";
    const auto log_df = statistics.LogDfTable();
    EXPECT_EQ((*log_df)[0], 0.0);
    EXPECT_DOUBLE_EQ((*log_df)[2], std::log(2.0));
    for (const uint32_t tf : {1u, 3u, 255u, 256u, 1000u}) {  // from the table and beyond it
      const double t = sqrt_tf ? std::sqrt(static_cast<double>(tf)) : static_cast<double>(tf);
      EXPECT_FLOAT_EQ(statistics.TermWeight(tf), static_cast<float>(t)) << tf;
    }
    // Word 0 is unknown to the statistics (left out), word 3 is in every image (idf 0).
    BagOfWords bag;
    bag.words = {0, 1, 2, 3};
    bag.counts = {5, 2, 1, 3};
    postings::ImageState state;
    state.live = 1;
    statistics.SetSums(bag, *log_df, &state);
    const auto t = [&](double tf) { return sqrt_tf ? std::sqrt(tf) : tf; };
    const double v1 = t(2) * std::log(8.0), v2 = t(1) * std::log(4.0);
    EXPECT_NEAR(statistics.Norm(state), std::sqrt(v1 * v1 + v2 * v2), 1e-12);
    // The same sums under another N: the norm follows without a pass over the words.
    const postings::CollectionStatistics larger(sqrt_tf, df, 16);
    const double w1 = t(2) * std::log(16.0), w2 = t(1) * std::log(8.0), w3 = t(3) * std::log(2.0);
    EXPECT_NEAR(larger.Norm(state), std::sqrt(w1 * w1 + w2 * w2 + w3 * w3), 1e-12);
    state.live = 0;
    EXPECT_EQ(statistics.Norm(state), 0.0);
  }
}

void ExpectScores(const InvertedFile& file, const std::map<uint32_t, BagOfWords>& live,
                  const std::map<uint32_t, BagOfWords>& statistics, std::mt19937_64& rng, size_t vocab) {
  for (int q = 0; q < 10; ++q) {
    const BagOfWords query = RandomBag(rng, vocab);
    const auto got = AllScores(file, query);
    for (const auto& [id, score] : ReferenceScores(live, query, vocab, true, &statistics)) {
      ASSERT_NEAR(got.count(id) ? got.at(id) : 0.0, score, 1e-6) << "image " << id;
    }
  }
}

// Above exact_statistics_postings, writes keep the statistics of the last refresh (idf, norms) until
// the images changed since exceed statistics_refresh_fraction of the live images then.
TEST(CollectionStatistics, StatisticsAreThoseOfTheLastRefreshUntilTheNext) {
  std::mt19937_64 rng(7);
  const size_t vocab = 300;
  const TfIdfOptions options{.exact_statistics_postings = 0, .statistics_refresh_fraction = 0.5};
  std::map<uint32_t, BagOfWords> live;
  InvertedFile file = AddAll(InvertedFile(vocab, options), &live, 0, 40, rng, vocab);  // empty: refreshed
  EXPECT_EQ(file.changes_since_refresh(), 0u);
  const std::map<uint32_t, BagOfWords> refreshed = live;
  ExpectScores(file, live, refreshed, rng, vocab);

  // 10 more and 2 removed: 12 <= 0.5 * 40, so scores still use the 40 images' statistics.
  file = AddAll(file, &live, 40, 10, rng, vocab);
  const std::vector<uint32_t> gone = {3, 41};
  const std::vector<const BagOfWords*> gone_bags = {&live[3], &live[41]};
  file = file.WithRemoved(gone, gone_bags);
  live.erase(3);
  live.erase(41);
  EXPECT_EQ(file.changes_since_refresh(), 12u);
  EXPECT_EQ(file.num_images(), 48u);
  std::vector<uint32_t> df(vocab, 0);  // the live counts are current even though the statistics are not
  for (const auto& [id, bag] : live) {
    for (uint32_t w : bag.words) ++df[w];
  }
  for (uint32_t w = 0; w < vocab; ++w) ASSERT_EQ(file.DocumentFrequency(w), df[w]) << w;
  ExpectScores(file, live, refreshed, rng, vocab);

  // An explicit refresh gives the live images' statistics (as Build).
  const InvertedFile exact = file.WithRefreshedStatistics(1);
  EXPECT_EQ(exact.changes_since_refresh(), 0u);
  ExpectScores(exact, live, live, rng, vocab);

  // 9 more: 21 > 0.5 * 40 refreshes by itself.
  file = AddAll(file, &live, 50, 9, rng, vocab);
  EXPECT_EQ(file.changes_since_refresh(), 0u);
  ExpectScores(file, live, live, rng, vocab);
}

// The refresh's result does not depend on the thread count (fixed summation groups).
TEST(CollectionStatistics, RefreshIsIndependentOfThreads) {
  std::mt19937_64 rng(9);
  const size_t vocab = 20000;
  const TfIdfOptions options{.exact_statistics_postings = 0, .statistics_refresh_fraction = 1};
  std::map<uint32_t, BagOfWords> live;
  const InvertedFile file = AddAll(InvertedFile(vocab, options), &live, 0, 300, rng, vocab);
  const InvertedFile one = file.WithRefreshedStatistics(1);
  const InvertedFile three = file.WithRefreshedStatistics(3);
  for (const auto& [id, bag] : live) ASSERT_EQ(one.Norm(id), three.Norm(id)) << id;
}

// The refresh walks the images in blocks, resuming every posting list where the previous block left it:
// every image of a collection spanning several blocks and segments, with removed images among them, gets
// the norm of its tf-idf vector computed from the definition.
TEST(CollectionStatistics, RefreshGivesEveryImageItsNormAcrossImageBlocks) {
  std::mt19937_64 rng(11);
  const size_t vocab = 5000;
  const TfIdfOptions options{.exact_statistics_postings = 0, .statistics_refresh_fraction = 1};
  std::map<uint32_t, BagOfWords> live;
  InvertedFile file(vocab, options);
  constexpr uint32_t kBatch = 12000;  // four batches: several segments, images beyond two 16384-image blocks
  for (uint32_t first = 0; first < 4 * kBatch; first += kBatch) {
    std::vector<uint32_t> ids;
    std::vector<const BagOfWords*> bags;
    for (uint32_t i = first; i < first + kBatch; ++i) {
      std::uniform_int_distribution<uint32_t> word(0, static_cast<uint32_t>(vocab - 1));
      std::uniform_int_distribution<uint32_t> frequent(0, 3);  // in most images, twice in a quarter of them
      const std::vector<uint32_t> words = {word(rng), word(rng), word(rng), frequent(rng), frequent(rng)};
      live[i] = BagOfWords::FromWords(words);
      ids.push_back(i);
      bags.push_back(&live[i]);
    }
    file = file.WithAdded(ids, bags);
  }
  std::vector<uint32_t> gone;
  std::vector<const BagOfWords*> gone_bags;
  for (uint32_t i = 5; i < 4 * kBatch; i += 997) {
    gone.push_back(i);
    gone_bags.push_back(&live[i]);
  }
  file = file.WithRemoved(gone, gone_bags);
  for (uint32_t i : gone) live.erase(i);
  const InvertedFile refreshed = file.WithRefreshedStatistics(2);
  std::vector<double> df(vocab, 0);
  for (const auto& [id, bag] : live) {
    for (uint32_t w : bag.words) df[w] += 1;
  }
  const auto n = static_cast<double>(live.size());
  for (const auto& [id, bag] : live) {
    double sq = 0;
    for (size_t k = 0; k < bag.words.size(); ++k) {
      const double x = std::sqrt(static_cast<double>(bag.counts[k])) * std::log(n / df[bag.words[k]]);
      sq += x * x;
    }
    ASSERT_NEAR(refreshed.Norm(id), std::sqrt(sq), 1e-9 * std::sqrt(sq)) << "image " << id;
  }
}

}  // namespace
}  // namespace oxbow::index
