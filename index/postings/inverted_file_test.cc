// The inverted file (inverted_file.h): adds, removes and merges against a rebuild and the definition.
#include "index/postings/inverted_file.h"

#include <gtest/gtest.h>

#include <iterator>
#include <map>
#include <random>
#include <span>
#include <vector>

#include "index/postings/testing.h"

namespace oxbow::index {
namespace {

using postings::testing::AllScores;
using postings::testing::Bag;
using postings::testing::RandomBag;
using postings::testing::ReferenceScores;

// The images of `live` (numbers below num_numbers) built at once, as one segment.
InvertedFile BuildOf(const std::map<uint32_t, BagOfWords>& live, size_t vocab, const TfIdfOptions& options,
                     uint32_t num_numbers) {
  return InvertedFile::Build(vocab, options, num_numbers, [&](uint32_t image, BagOfWords* bag) {
    const auto it = live.find(image);
    if (it == live.end()) return false;
    *bag = it->second;
    return true;
  });
}

// For 20 random queries, `file` scores every image as `built` does and as the definition over `live`.
void ExpectScoresOfBuildAndDefinition(const InvertedFile& file, const InvertedFile& built,
                                      const std::map<uint32_t, BagOfWords>& live, std::mt19937_64& rng, size_t vocab) {
  for (int q = 0; q < 20; ++q) {
    const BagOfWords query = RandomBag(rng, vocab);
    const auto got = AllScores(file, query);
    const auto expected = AllScores(built, query);
    ASSERT_EQ(got.size(), expected.size());
    for (const auto& [id, score] : expected) {
      ASSERT_TRUE(got.count(id)) << "image " << id;
      EXPECT_NEAR(got.at(id), score, 1e-6) << "image " << id;
    }
    for (const auto& [id, score] : ReferenceScores(live, query, vocab, true)) {
      EXPECT_NEAR(got.count(id) ? got.at(id) : 0.0, score, 1e-6) << "image " << id;
    }
  }
}

TEST(InvertedFile, RandomAddRemoveSequenceEqualsRebuild) {
  std::mt19937_64 rng(12345);
  const size_t vocab = 500;
  for (int merge_factor : {2, 8}) {
    const TfIdfOptions options{.sqrt_tf = true, .merge_factor = merge_factor};
    InvertedFile file(vocab, options);
    std::map<uint32_t, BagOfWords> live;
    uint32_t next_number = 0;
    for (int step = 0; step < 400; ++step) {
      std::uniform_int_distribution<int> op(0, 9);
      if (op(rng) < 3 && !live.empty()) {
        // Remove one or two random live images.
        std::vector<uint32_t> ids;
        std::vector<const BagOfWords*> bags;
        auto it = live.begin();
        std::advance(it, std::uniform_int_distribution<size_t>(0, live.size() - 1)(rng));
        ids.push_back(it->first);
        bags.push_back(&it->second);
        file = file.WithRemoved(ids, bags);
        live.erase(it);
      } else {
        // Add a batch of 1..3 images.
        std::vector<uint32_t> ids;
        std::vector<BagOfWords> new_bags;
        const int n = std::uniform_int_distribution<int>(1, 3)(rng);
        for (int i = 0; i < n; ++i) {
          ids.push_back(next_number++);
          new_bags.push_back(RandomBag(rng, vocab));
        }
        std::vector<const BagOfWords*> bags;
        bags.reserve(new_bags.size());
        for (auto& b : new_bags) bags.push_back(&b);
        file = file.WithAdded(ids, bags);
        for (size_t i = 0; i < ids.size(); ++i) live[ids[i]] = new_bags[i];
      }
    }
    ASSERT_GT(live.size(), 100u);
    const InvertedFile rebuilt = BuildOf(live, vocab, options, next_number);
    EXPECT_EQ(file.num_images(), rebuilt.num_images());
    EXPECT_EQ(file.Stats().num_features, rebuilt.Stats().num_features);
    for (uint32_t w = 0; w < vocab; ++w) ASSERT_EQ(file.DocumentFrequency(w), rebuilt.DocumentFrequency(w));
    for (const auto& [id, bag] : live) EXPECT_NEAR(file.Norm(id), rebuilt.Norm(id), 1e-9 * (1 + rebuilt.Norm(id)));
    ExpectScoresOfBuildAndDefinition(file, rebuilt, live, rng, vocab);
    EXPECT_GE(file.Stats().num_segments, 1u);
  }
}

// Merges of segments with no removed image copy each list and code again only its first posting (its
// gap from the previous segment's last image), and a batch's segment is sized without previous images
// when its numbers lie closer than the escape: batches of every size, numbers with gaps below, at and
// above the 16-bit escape between and within batches, many merges (factor 2): every image's score is
// that of the same collection built at once, and of the definition.
TEST(InvertedFile, MergesWithoutRemovalsKeepEveryPosting) {
  std::mt19937_64 rng(777);
  const size_t vocab = 300;
  // Statistics refreshed once at the end (not at every add, as below exact_statistics_postings).
  const TfIdfOptions options{.sqrt_tf = true, .merge_factor = 2, .exact_statistics_postings = 0};
  InvertedFile file(vocab, options);
  // Its twin is read back from its checkpoint form every few batches, so that its merges chain lists
  // read back from those bytes onto lists made in this process. Both must stay the same bytes.
  InvertedFile reread(vocab, options);
  const auto bytes_of = [](const InvertedFile& f) {
    std::vector<uint8_t> out;
    f.Serialize([&](std::span<const uint8_t> part) { out.insert(out.end(), part.begin(), part.end()); });
    return out;
  };
  std::map<uint32_t, BagOfWords> live;
  uint32_t next_number = 5;
  const std::vector<uint32_t> jumps = {1, 1, 2, 3, 32766, 32767, 32768, 32769};
  for (int batch = 0; batch < 32; ++batch) {
    std::vector<uint32_t> ids;
    std::vector<BagOfWords> new_bags;
    const int n = std::uniform_int_distribution<int>(1, 40)(rng);
    for (int i = 0; i < n; ++i) {
      ids.push_back(next_number);
      next_number += (i == 0 || rng() % 24 == 0) ? jumps[rng() % jumps.size()] : 1 + static_cast<uint32_t>(rng() % 2);
      new_bags.push_back(RandomBag(rng, vocab));
    }
    std::vector<const BagOfWords*> bags;
    bags.reserve(new_bags.size());
    for (const BagOfWords& b : new_bags) bags.push_back(&b);
    file = file.WithAdded(ids, bags);
    reread = reread.WithAdded(ids, bags);
    if (batch % 8 == 7) {  // (the whole form holds every number's sums: millions after the jumps)
      const std::vector<uint8_t> bytes = bytes_of(reread);
      ASSERT_TRUE(bytes == bytes_of(file)) << "batch " << batch;
      auto read = InvertedFile::Deserialize(bytes, vocab, options);
      ASSERT_TRUE(read) << read.error().ToString();
      reread = std::move(*read);
    }
    for (size_t i = 0; i < ids.size(); ++i) live[ids[i]] = new_bags[i];
  }
  EXPECT_LT(file.num_segments(), 20u);  // merged
  file = file.WithRefreshedStatistics(1);
  const InvertedFile built = BuildOf(live, vocab, options, next_number);
  EXPECT_EQ(file.Stats().num_postings, built.Stats().num_postings);
  ExpectScoresOfBuildAndDefinition(file, built, live, rng, vocab);
}

TEST(InvertedFile, RemovingEverythingLeavesAnEmptyIndex) {
  InvertedFile file(10, {});
  const BagOfWords b0 = Bag({1, 2}), b1 = Bag({2, 3});
  const std::vector<uint32_t> ids = {0, 1};
  const std::vector<const BagOfWords*> bags = {&b0, &b1};
  file = file.WithAdded(ids, bags).WithRemoved(ids, bags);
  EXPECT_EQ(file.num_images(), 0u);
  EXPECT_EQ(file.DocumentFrequency(2), 0u);
  EXPECT_TRUE(AllScores(file, Bag({1, 2, 3})).empty());
  EXPECT_EQ(file.Stats().num_postings, 0u);  // dead postings compacted away
}

TEST(InvertedFile, OptionsAreChecked) {
  EXPECT_TRUE(TfIdfOptions{.max_document_frequency = 0}.Check().has_value());
  EXPECT_TRUE(TfIdfOptions{.merge_factor = 1}.Check().has_value());
  EXPECT_TRUE(TfIdfOptions{.max_document_frequency = 1.5}.Check().has_value());
  EXPECT_FALSE(TfIdfOptions{}.Check().has_value());
}

}  // namespace
}  // namespace oxbow::index
