// Segments (segment.h): both ways of writing a batch code the same lists, the two table layouts, and
// merges with and without removed images.
#include "index/postings/segment.h"

#include <gtest/gtest.h>

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <random>
#include <utility>
#include <vector>

namespace oxbow::index::postings {
namespace {

using Postings = std::vector<std::pair<uint32_t, uint32_t>>;  // (image, tf) in image order

Postings ListOf(const Segment& segment, uint32_t word) {
  Postings out;
  segment.ForEach(word, [&](uint32_t image, uint32_t tf) { out.emplace_back(image, tf); });
  return out;
}

std::vector<uint8_t> BytesOf(const Segment& segment, uint32_t word) {
  const auto [p, end] = segment.List(word);
  return {p, end};
}

// `count` random bags of up to 12 of `vocab` words, with a tf up to 300 now and then.
std::vector<BagOfWords> RandomBags(std::mt19937_64& rng, size_t count, size_t vocab) {
  std::vector<BagOfWords> bags(count);
  for (BagOfWords& bag : bags) {
    std::map<uint32_t, uint32_t> counts;
    for (int k = 0; k < 12; ++k) counts[static_cast<uint32_t>(rng() % vocab)] += rng() % 16 == 0 ? 1 + rng() % 300 : 1;
    for (const auto& [w, c] : counts) {
      bag.words.push_back(w);
      bag.counts.push_back(c);
    }
  }
  return bags;
}

std::vector<const BagOfWords*> Pointers(const std::vector<BagOfWords>& bags) {
  std::vector<const BagOfWords*> out;
  out.reserve(bags.size());
  for (const BagOfWords& bag : bags) out.push_back(&bag);
  return out;
}

// The postings of every word as the bags give them.
std::map<uint32_t, Postings> Expected(const std::vector<uint32_t>& images, const std::vector<BagOfWords>& bags,
                                      const std::function<bool(uint32_t)>& keep = nullptr) {
  std::map<uint32_t, Postings> out;
  for (size_t i = 0; i < images.size(); ++i) {
    if (keep && !keep(images[i])) continue;
    for (size_t k = 0; k < bags[i].words.size(); ++k) out[bags[i].words[k]].emplace_back(images[i], bags[i].counts[k]);
  }
  return out;
}

// A batch is written in two passes when large next to the vocabulary, from sorted triples otherwise:
// the same bags give the same lists, byte for byte, both with consecutive numbers (no gap takes the
// escape) and with numbers far apart (gaps escaped).
TEST(PostingSegment, LargeAndSmallBatchesCodeTheSameLists) {
  std::mt19937_64 rng(3);
  constexpr size_t kWords = 40;
  const std::vector<BagOfWords> bags = RandomBags(rng, 50, kWords);
  for (const uint32_t spacing : {1u, 40000u}) {
    std::vector<uint32_t> images;
    for (uint32_t i = 0; i < bags.size(); ++i) images.push_back(1000 + i * spacing + i / 7);
    // About 550 postings: a large batch for 40 words, a small one for 10,000 (the same words used).
    const auto large = BuildSegment(images, Pointers(bags), kWords);
    const auto small = BuildSegment(images, Pointers(bags), 10'000);
    EXPECT_EQ(large->first_image, images.front());
    EXPECT_EQ(large->end_image, images.back() + 1);
    uint64_t total = 0;
    for (const BagOfWords& bag : bags) total += bag.words.size();
    EXPECT_EQ(large->num_postings, total);
    EXPECT_EQ(small->num_postings, total);
    EXPECT_TRUE(large->dense);
    EXPECT_FALSE(small->dense) << "40 of 10,000 words: sparse";
    const auto expected = Expected(images, bags);
    EXPECT_EQ(large->Words(), small->Words());
    for (uint32_t w = 0; w < kWords; ++w) {
      const auto it = expected.find(w);
      EXPECT_EQ(ListOf(*large, w), it == expected.end() ? Postings{} : it->second) << "word " << w;
      EXPECT_EQ(BytesOf(*large, w), BytesOf(*small, w)) << "word " << w << ", spacing " << spacing;
    }
    EXPECT_EQ(large->size(), small->size());
    EXPECT_TRUE(ListOf(*small, 9999).empty());
  }
}

TEST(PostingSegment, LayoutIsDenseFromAnEighthOfTheVocabulary) {
  const BagOfWords bag{{2, 5, 7}, {1, 1, 3}};
  const std::vector<uint32_t> image = {4};
  for (const auto& [vocabulary, dense] : std::vector<std::pair<size_t, bool>>{{24, true}, {25, false}}) {
    // Under a quarter of the vocabulary's postings: written from triples, then ChooseLayout decides.
    const auto segment = BuildSegment(image, std::vector<const BagOfWords*>{&bag}, vocabulary * 4 + 1);
    EXPECT_FALSE(segment->dense);
    auto copy = std::make_shared<Segment>(*segment);
    copy->ChooseLayout(vocabulary);
    EXPECT_EQ(copy->dense, dense) << vocabulary << " words";
    EXPECT_EQ(ListOf(*copy, 7), (Postings{{4, 3}}));
    EXPECT_TRUE(ListOf(*copy, 6).empty());
    EXPECT_EQ(copy->Words(), (std::vector<uint32_t>{2, 5, 7}));
  }
}

// A merge joins consecutive segments word by word; without a liveness test it copies the lists and
// codes again only their first postings, with one it drops the images it rejects. Either way the lists
// are those of one segment written from the kept bags at once.
TEST(PostingSegment, MergesKeepTheLiveImagesLists) {
  std::mt19937_64 rng(5);
  constexpr size_t kWords = 30;
  std::vector<uint32_t> images;
  std::vector<BagOfWords> bags;
  std::vector<std::shared_ptr<const Segment>> segments;
  uint32_t next = 3;
  for (const size_t count : {20, 1, 35, 2}) {
    std::vector<uint32_t> ids;
    for (size_t i = 0; i < count; ++i) ids.push_back(next += (i == 0 ? 33000 : 1 + static_cast<uint32_t>(rng() % 3)));
    const std::vector<BagOfWords> batch = RandomBags(rng, count, kWords);
    segments.push_back(BuildSegment(ids, Pointers(batch), kWords));
    images.insert(images.end(), ids.begin(), ids.end());
    bags.insert(bags.end(), batch.begin(), batch.end());
  }
  const auto whole = BuildSegment(images, Pointers(bags), kWords);
  const auto joined = MergeSegments(segments, kWords, nullptr);
  EXPECT_EQ(joined->num_postings, whole->num_postings);
  EXPECT_EQ(joined->first_image, images.front());
  EXPECT_EQ(joined->end_image, images.back() + 1);
  for (uint32_t w = 0; w < kWords; ++w) EXPECT_EQ(BytesOf(*joined, w), BytesOf(*whole, w)) << "word " << w;

  const auto live = [](uint32_t image) { return image % 4 != 1; };
  std::vector<uint32_t> kept_images;
  std::vector<BagOfWords> kept_bags;
  for (size_t i = 0; i < images.size(); ++i) {
    if (!live(images[i])) continue;
    kept_images.push_back(images[i]);
    kept_bags.push_back(bags[i]);
  }
  const auto filtered = MergeSegments(segments, kWords, live);
  const auto expected = Expected(images, bags, live);
  uint64_t kept = 0;
  for (uint32_t w = 0; w < kWords; ++w) {
    const auto it = expected.find(w);
    EXPECT_EQ(ListOf(*filtered, w), it == expected.end() ? Postings{} : it->second) << "word " << w;
    kept += it == expected.end() ? 0 : it->second.size();
  }
  EXPECT_EQ(filtered->num_postings, kept);
  EXPECT_LT(kept, whole->num_postings);
  // The first list posting of each word counts from the merged segment's first image, as in one segment
  // written from the kept bags (which starts at the first kept image).
  const auto rewritten = BuildSegment(kept_images, Pointers(kept_bags), kWords);
  for (uint32_t w = 0; w < kWords; ++w) EXPECT_EQ(ListOf(*filtered, w), ListOf(*rewritten, w)) << "word " << w;
}

}  // namespace
}  // namespace oxbow::index::postings
