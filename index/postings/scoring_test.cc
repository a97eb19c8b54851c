// TF-IDF scoring (scoring.h): scores against the definition, the query vector and its stop list, top-k
// selection, term groups, the posting budget, and scoring a subset of images from their bags.
#include "index/postings/scoring.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <random>
#include <set>
#include <vector>

#include "index/postings/testing.h"

namespace oxbow::index {
namespace {

using postings::testing::AllScores;
using postings::testing::Bag;
using postings::testing::RandomBag;
using postings::testing::ReferenceScores;

TEST(TfIdfScoring, HandComputedCosineOnTinyCorpus) {
  // d0 = {0, 1}, d1 = {1, 2}, d2 = {2, 3}; N = 3; idf: w0 = w3 = log 3, w1 = w2 = log 1.5.
  for (bool sqrt_tf : {false, true}) {
    InvertedFile file(5, TfIdfOptions{.sqrt_tf = sqrt_tf});
    const BagOfWords b0 = Bag({0, 1}), b1 = Bag({1, 2}), b2 = Bag({2, 3});
    const std::vector<uint32_t> ids = {0, 1, 2};
    const std::vector<const BagOfWords*> bags = {&b0, &b1, &b2};
    file = file.WithAdded(ids, bags);
    EXPECT_NEAR(file.Idf(0), std::log(3.0), 1e-12);
    EXPECT_NEAR(file.Idf(1), std::log(1.5), 1e-12);
    EXPECT_TRUE(std::isinf(file.Idf(4)));
    EXPECT_NEAR(file.Norm(1), std::sqrt(2.0) * std::log(1.5), 1e-12);

    const auto scores = AllScores(file, Bag({0, 1}));
    ASSERT_EQ(scores.size(), 2u);  // d2 shares no word with the query
    EXPECT_NEAR(scores.at(0), 1.0, 1e-6);
    // cos(q, d1) = log1.5^2 / (sqrt(log3^2 + log1.5^2) * sqrt(2) log1.5) = 0.244829...
    EXPECT_NEAR(scores.at(1), 0.2448290, 1e-6);
  }
}

TEST(TfIdfScoring, TermFrequencyWeighting) {
  // Query {0,0,1}: with sqrt-tf the repeated word counts sqrt(2), raw tf counts 2.
  const BagOfWords b0 = Bag({0, 0, 1}), b1 = Bag({1, 2}), b2 = Bag({2, 3});
  const std::map<uint32_t, BagOfWords> corpus = {{0, b0}, {1, b1}, {2, b2}};
  for (bool sqrt_tf : {false, true}) {
    InvertedFile file(4, TfIdfOptions{.sqrt_tf = sqrt_tf});
    const std::vector<uint32_t> ids = {0, 1, 2};
    const std::vector<const BagOfWords*> bags = {&b0, &b1, &b2};
    file = file.WithAdded(ids, bags);
    const BagOfWords query = Bag({0, 1, 1, 1});
    const auto expected = ReferenceScores(corpus, query, 4, sqrt_tf);
    const auto got = AllScores(file, query);
    for (const auto& [id, score] : got) EXPECT_NEAR(score, expected.at(id), 1e-6) << id;
    EXPECT_GT(expected.at(0), 0);
  }
}

TEST(TfIdfScoring, MatchesDenseReferenceOnRandomCorpus) {
  std::mt19937_64 rng(7);
  const size_t vocab = 300;
  std::map<uint32_t, BagOfWords> corpus;
  for (uint32_t i = 0; i < 120; ++i) corpus[i] = RandomBag(rng, vocab);
  const InvertedFile file = InvertedFile::Build(vocab, {}, 120, [&](uint32_t image, BagOfWords* bag) {
    *bag = corpus.at(image);
    return true;
  });
  EXPECT_EQ(file.num_images(), 120u);
  for (int q = 0; q < 10; ++q) {
    const BagOfWords query = RandomBag(rng, vocab);
    const auto expected = ReferenceScores(corpus, query, vocab, true);
    const auto got = AllScores(file, query);
    for (const auto& [id, score] : expected) {
      const double g = got.count(id) ? got.at(id) : 0.0;
      EXPECT_NEAR(g, score, 1e-6) << "image " << id;
    }
  }
}

TEST(TfIdfScoring, StopListDropsFrequentQueryWords) {
  // Word 0 is in 3 of 4 images (df 0.75); with max_document_frequency 0.5 it is not used.
  const BagOfWords b0 = Bag({0, 1}), b1 = Bag({0, 2}), b2 = Bag({0, 3}), b3 = Bag({4});
  const std::vector<uint32_t> ids = {0, 1, 2, 3};
  const std::vector<const BagOfWords*> bags = {&b0, &b1, &b2, &b3};
  InvertedFile all = InvertedFile(5, {}).WithAdded(ids, bags);
  // No floor (the default floor of 10,000 images keeps every word of this 4-image collection).
  InvertedFile stopped =
      InvertedFile(5, TfIdfOptions{.max_document_frequency = 0.5, .stop_list_min_images = 0}).WithAdded(ids, bags);
  EXPECT_EQ(all.QueryVector(Bag({0, 1})).size(), 2u);
  const auto q = stopped.QueryVector(Bag({0, 1}));
  ASSERT_EQ(q.size(), 1u);
  EXPECT_EQ(q[0].word, 1u);
  EXPECT_EQ(AllScores(all, Bag({0})).size(), 3u);
  // A query of stop-listed words only is scored with them all rather than not at all.
  EXPECT_EQ(AllScores(stopped, Bag({0})), AllScores(all, Bag({0})));
}

TEST(TfIdfScoring, StopListFloorKeepsWordsOfFewImages) {
  // Word 0 is in 3 of 4 images: above max_document_frequency 0.5, but within a floor of 3 images.
  const BagOfWords b0 = Bag({0, 1}), b1 = Bag({0, 2}), b2 = Bag({0, 3}), b3 = Bag({4});
  const std::vector<uint32_t> ids = {0, 1, 2, 3};
  const std::vector<const BagOfWords*> bags = {&b0, &b1, &b2, &b3};
  const InvertedFile floor3 =
      InvertedFile(5, TfIdfOptions{.max_document_frequency = 0.5, .stop_list_min_images = 3}).WithAdded(ids, bags);
  const InvertedFile floor2 =
      InvertedFile(5, TfIdfOptions{.max_document_frequency = 0.5, .stop_list_min_images = 2}).WithAdded(ids, bags);
  EXPECT_EQ(floor3.QueryVector(Bag({0, 1})).size(), 2u);
  EXPECT_EQ(AllScores(floor3, Bag({0})).size(), 3u);
  const auto q = floor2.QueryVector(Bag({0, 1}));
  ASSERT_EQ(q.size(), 1u);
  EXPECT_EQ(q[0].word, 1u);
}

TEST(TfIdfScoring, DefaultStopListAdaptsToTheCollectionSize) {
  // Word 0 is in 95% of the images, word 1 in 50%, word 2 in 1%: with the defaults nothing is dropped
  // at 10,000 images (the floor), and the two frequent words are at 30,000 (10% of them is 3,000).
  for (const uint32_t n : {10'000u, 30'000u}) {
    const InvertedFile file = InvertedFile::Build(3, {}, n, [](uint32_t image, BagOfWords* bag) {
      bag->words.clear();
      bag->counts.clear();
      if (image % 20 != 0) bag->words.push_back(0);
      if (image % 2 == 0) bag->words.push_back(1);
      if (image % 100 == 0) bag->words.push_back(2);
      bag->counts.assign(bag->words.size(), 1);
      return true;
    });
    std::vector<uint32_t> kept;
    for (const QueryTerm& t : file.QueryVector(Bag({0, 1, 2}))) kept.push_back(t.word);
    EXPECT_EQ(kept, (n <= 10'000 ? std::vector<uint32_t>{0, 1, 2} : std::vector<uint32_t>{2})) << n << " images";
  }
}

TEST(TfIdfScoring, StrongestTermsKeepsTheLargestWeightsInWordOrder) {
  const std::vector<QueryTerm> terms = {{1, 0.1f}, {3, 0.5f}, {4, 0.2f}, {7, 0.5f}, {9, 0.3f}, {12, 0.2f}};
  auto words = [](const std::vector<QueryTerm>& t) {
    std::vector<uint32_t> w;
    w.reserve(t.size());
    for (const QueryTerm& x : t) w.push_back(x.word);
    return w;
  };
  EXPECT_EQ(words(StrongestTerms(terms, 3)), (std::vector<uint32_t>{3, 7, 9}));
  // A tie at the cut keeps the smaller word.
  EXPECT_EQ(words(StrongestTerms(terms, 4)), (std::vector<uint32_t>{3, 4, 7, 9}));
  EXPECT_EQ(words(StrongestTerms(terms, 6)), words(terms));
  EXPECT_EQ(words(StrongestTerms(terms, 10)), words(terms));
  EXPECT_TRUE(StrongestTerms(terms, 0).empty());
}

TEST(TfIdfScoring, FractionalQueryVectorMatchesCountsAndReference) {
  std::mt19937_64 rng(5);
  const size_t vocab = 60;
  std::map<uint32_t, BagOfWords> corpus;
  for (uint32_t i = 0; i < 20; ++i) corpus[i] = RandomBag(rng, vocab);
  for (bool sqrt_tf : {true, false}) {
    const InvertedFile file = InvertedFile::Build(vocab, {.sqrt_tf = sqrt_tf}, 20, [&](uint32_t image, BagOfWords* bag) {
      *bag = corpus.at(image);
      return true;
    });
    const BagOfWords& query = corpus.at(3);
    std::vector<float> tf(query.counts.begin(), query.counts.end());
    const auto a = file.QueryVector(query);
    const auto b = file.QueryVector(query.words, tf);
    ASSERT_EQ(a.size(), b.size());
    for (size_t i = 0; i < a.size(); ++i) {
      EXPECT_EQ(a[i].word, b[i].word);
      EXPECT_FLOAT_EQ(a[i].weight, b[i].weight);
    }
    // A half count weighs t(0.5) relative to t(1) = 1: compare two single-word queries' raw weights
    // through a two-word query where one word has tf 0.5 and the other tf 1.
    std::vector<uint32_t> words;
    for (uint32_t w : query.words) {
      if (file.Idf(w) > 0 && words.size() < 2) words.push_back(w);
    }
    ASSERT_EQ(words.size(), 2u);
    const uint32_t w1 = words[0], w2 = words[1];
    const std::vector<float> half = {0.5f, 1.0f};
    const auto v = file.QueryVector(words, half);
    ASSERT_EQ(v.size(), 2u);
    const double expected = (sqrt_tf ? std::sqrt(0.5) : 0.5) * file.Idf(w1) / file.Idf(w2);
    EXPECT_NEAR(v[0].weight / v[1].weight, expected, 1e-5);
  }
}

TEST(TfIdfScoring, TopKIsOrderedAndTruncated) {
  std::mt19937_64 rng(3);
  const size_t vocab = 200;
  std::map<uint32_t, BagOfWords> corpus;
  for (uint32_t i = 0; i < 50; ++i) corpus[i] = RandomBag(rng, vocab);
  const InvertedFile file = InvertedFile::Build(vocab, {}, 50, [&](uint32_t image, BagOfWords* bag) {
    *bag = corpus.at(image);
    return true;
  }, 2);
  ScoreScratch scratch;
  const auto q = file.QueryVector(corpus.at(17));
  uint64_t candidates = 0;
  const auto top = file.Score(q, 5, &scratch, &candidates);
  ASSERT_EQ(top.size(), 5u);
  EXPECT_EQ(top[0].image, 17u);
  EXPECT_NEAR(top[0].score, 1.0, 1e-5);
  for (size_t i = 1; i < top.size(); ++i) EXPECT_GE(top[i - 1].score, top[i].score);
  EXPECT_GE(candidates, 5u);
  // The scratch accumulator is left zeroed for the next query.
  for (float v : scratch.accumulators[0]) ASSERT_EQ(v, 0.0f);
}

// A query that scans millions of postings is split into term groups scored on their own threads; the
// scores are the same for every thread count, equal the subset scorer's (same float operations), match
// a double-precision dot product, and leave every accumulator zeroed.
TEST(TfIdfScoring, LongQueriesScoreInGroupsIndependentlyOfThreads) {
  constexpr size_t kVocab = 400;
  constexpr uint32_t kImages = 40000;
  std::mt19937 rng(5);
  std::vector<BagOfWords> corpus(kImages);
  for (auto& bag : corpus) {
    for (uint32_t w = 0; w < kVocab; ++w) {
      if (rng() % 4 != 0) {  // 3 in 4 words: ~30k images per word
        bag.words.push_back(w);
        bag.counts.push_back(1 + rng() % 3);
      }
    }
  }
  const InvertedFile file = InvertedFile::Build(kVocab, {}, kImages, [&](uint32_t image, BagOfWords* bag) {
    *bag = corpus[image];
    return true;
  }, 2);
  const auto q = file.QueryVector(corpus[123]);
  const std::vector<size_t> groups = file.ScoreGroups(q);
  ASSERT_EQ(groups.size(), kMaxScoreGroups + 1) << "the query should scan enough postings for every group";
  EXPECT_EQ(groups.front(), 0u);
  EXPECT_EQ(groups.back(), q.size());
  ScoreScratch scratch;
  const auto one = file.Score(q, 50, &scratch, nullptr, nullptr, 1);
  for (const int threads : {2, 4}) {
    const auto many = file.Score(q, 50, &scratch, nullptr, nullptr, threads);
    ASSERT_EQ(many.size(), one.size());
    for (size_t i = 0; i < one.size(); ++i) {
      EXPECT_EQ(many[i].image, one[i].image);
      EXPECT_EQ(many[i].score, one[i].score);
    }
  }
  EXPECT_EQ(one[0].image, 123u);
  for (const auto& acc : scratch.accumulators) {
    for (float v : acc) ASSERT_EQ(v, 0.0f);
  }
  std::vector<uint32_t> images;
  std::vector<const BagOfWords*> bags;
  for (const ScoredImage& s : one) {
    images.push_back(s.image);
    bags.push_back(&corpus[s.image]);
  }
  std::vector<size_t> order(images.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::sort(order.begin(), order.end(), [&](size_t a, size_t b) { return images[a] < images[b]; });
  std::vector<uint32_t> sorted_images;
  std::vector<const BagOfWords*> sorted_bags;
  for (const size_t i : order) {
    sorted_images.push_back(images[i]);
    sorted_bags.push_back(bags[i]);
  }
  const std::vector<float> subset = InvertedFile::Subset(file, sorted_images, sorted_bags).Score(q);
  for (size_t k = 0; k < order.size(); ++k) {
    // Equal up to the rounding of a fused multiply-add, which the compiler may use in one loop only.
    const float expected = one[order[k]].score;
    EXPECT_NEAR(subset[k], expected, 1e-6 * expected) << "image " << sorted_images[k];
  }
  // Against the cosine computed in double precision from the bags.
  const auto weight = [&](uint32_t tf) { return std::sqrt(static_cast<double>(tf)); };
  for (const ScoredImage& s : one) {
    const BagOfWords& bag = corpus[s.image];
    double dot = 0, norm = 0;
    for (size_t k = 0; k < bag.words.size(); ++k) {
      const double v = weight(bag.counts[k]) * file.Idf(bag.words[k]);
      norm += v * v;
      for (const QueryTerm& t : q) {
        if (t.word == bag.words[k]) dot += t.weight * v;
      }
    }
    EXPECT_NEAR(s.score, dot / std::sqrt(norm), 1e-4) << "image " << s.image;
  }
}

TEST(TfIdfScoring, PostingBudgetKeepsTheTermsOfLargestContributionThatFit) {
  // Word w is in the images i with i % (w + 1) == 0 (w = 0: every image, weight 0, never scanned), so
  // rarer words have larger idf; the query weights every word alike, so the per-posting contribution
  // (weight x idf) ranks the words from the rarest down.
  constexpr size_t kVocab = 12;
  constexpr uint32_t kImages = 600;
  std::vector<BagOfWords> corpus(kImages);
  for (uint32_t i = 0; i < kImages; ++i) {
    for (uint32_t w = 0; w < kVocab; ++w) {
      if (i % (w + 1) == 0) {
        corpus[i].words.push_back(w);
        corpus[i].counts.push_back(1);
      }
    }
  }
  const InvertedFile file = InvertedFile::Build(kVocab, {}, kImages, [&](uint32_t image, BagOfWords* bag) {
    *bag = corpus[image];
    return true;
  });
  std::vector<QueryTerm> query;
  for (uint32_t w = 0; w < kVocab; ++w) query.push_back({w, 0.25f});
  uint64_t all = 0;
  for (uint32_t w = 1; w < kVocab; ++w) all += file.DocumentFrequency(w);
  EXPECT_EQ(file.ScannedPostings(query), all);
  const auto words = [](const std::vector<QueryTerm>& terms) {
    std::vector<uint32_t> out;
    out.reserve(terms.size());
    for (const QueryTerm& t : terms) out.push_back(t.word);
    return out;
  };
  // No limit, or a budget the query fits in: every term, as given.
  EXPECT_EQ(words(file.WithinPostingBudget(query, 0)), words(query));
  EXPECT_EQ(words(file.WithinPostingBudget(query, all)), words(query));
  const auto df = [&](uint32_t w) { return static_cast<uint64_t>(file.DocumentFrequency(w)); };
  ASSERT_LT(df(11), df(10));
  ASSERT_LT(df(10), df(9));
  ASSERT_LT(df(9), df(8));
  // The rarest three fit; the fourth and every later (more frequent) word do not fit what is left.
  const uint64_t three = df(11) + df(10) + df(9);
  EXPECT_EQ(words(file.WithinPostingBudget(query, three + df(8) - 1)), (std::vector<uint32_t>{9, 10, 11}));
  EXPECT_EQ(words(file.WithinPostingBudget(query, three + df(8))), (std::vector<uint32_t>{8, 9, 10, 11}));
  // The query's weights decide the order, not the frequencies alone, and a term that does not fit is
  // skipped while a later one that fits is still taken: with w11 weighted least it comes last, after
  // w8 .. w1, which do not fit once w10 and w9 are in.
  std::vector<QueryTerm> light = query;
  light[11].weight = 0.01f;
  EXPECT_EQ(words(file.WithinPostingBudget(light, three)), (std::vector<uint32_t>{9, 10, 11}));
  // A frequent word weighted far above the rest comes first.
  std::vector<QueryTerm> heavy = query;
  heavy[1].weight = 100.0f;
  EXPECT_EQ(words(file.WithinPostingBudget(heavy, df(1) + df(11))), (std::vector<uint32_t>{1, 11}));
  // The first term is kept even when it alone exceeds the budget.
  EXPECT_EQ(words(file.WithinPostingBudget(query, 1)), (std::vector<uint32_t>{11}));

  // Score() under a budget scores the kept terms only, with the full image norms.
  ScoreScratch scratch;
  const uint64_t budget = three + df(8);
  const std::vector<QueryTerm> kept = file.WithinPostingBudget(query, budget);
  const auto budgeted = file.Score(query, kImages, &scratch, nullptr, nullptr, 1, budget);
  const auto by_hand = file.Score(kept, kImages, &scratch);
  ASSERT_EQ(budgeted.size(), by_hand.size());
  for (size_t i = 0; i < budgeted.size(); ++i) {
    EXPECT_EQ(budgeted[i].image, by_hand[i].image);
    EXPECT_EQ(budgeted[i].score, by_hand[i].score);
  }
  // Image 5 holds w0 (weight 0) and w4, which the budget drops: listed without the budget only.
  const auto listed = [](const std::vector<ScoredImage>& r, uint32_t image) {
    return std::any_of(r.begin(), r.end(), [&](const ScoredImage& s) { return s.image == image; });
  };
  EXPECT_FALSE(listed(budgeted, 5));
  EXPECT_TRUE(listed(file.Score(query, kImages, &scratch), 5));
  // A budget the query fits in changes nothing.
  const auto exact = file.Score(query, kImages, &scratch);
  const auto roomy = file.Score(query, kImages, &scratch, nullptr, nullptr, 1, all);
  ASSERT_EQ(exact.size(), roomy.size());
  for (size_t i = 0; i < exact.size(); ++i) {
    EXPECT_EQ(exact[i].image, roomy[i].image);
    EXPECT_EQ(exact[i].score, roomy[i].score);
  }
}

TEST(TfIdfScoring, ScoresDecodeEveryGapCoding) {
  // Gaps below, at and above the escape of the 16-bit unit (2^15 - 1: the gap then follows in 4
  // bytes), small and large ones, with tf 1 and > 1, lists ending at the very end of the segment's bytes.
  const std::vector<uint32_t> numbers = {0,     1,     63,     64,     100,     8191,    8192,    8300,
                                         41066, 73833, 106601, 170000, 1100000, 1100001, 2200000, 2200001,
                                         2300000};
  constexpr size_t kVocab = 4;
  std::map<uint32_t, BagOfWords> corpus;
  for (size_t i = 0; i < numbers.size(); ++i) {
    std::vector<uint32_t> words = {0};  // word 0 everywhere: weight 0
    for (uint32_t w = 1; w < kVocab; ++w) {
      if ((i + w) % 3 != 0) words.insert(words.end(), 1 + (i * w) % 3, w);  // tf 1..3
    }
    corpus[numbers[i]] = BagOfWords::FromWords(words);
  }
  const InvertedFile file = InvertedFile::Build(kVocab, {}, numbers.back() + 1, [&](uint32_t image, BagOfWords* bag) {
    const auto it = corpus.find(image);
    if (it == corpus.end()) return false;
    *bag = it->second;
    return true;
  });
  for (uint32_t w = 1; w < kVocab; ++w) {
    const BagOfWords query = BagOfWords::FromWords(std::vector<uint32_t>{w, w, 1});
    const auto expected = ReferenceScores(corpus, query, kVocab, true);
    const auto got = AllScores(file, query);
    for (const auto& [image, score] : expected) {
      if (score == 0) {
        EXPECT_FALSE(got.count(image)) << "image " << image;
      } else {
        ASSERT_TRUE(got.count(image)) << "image " << image << ", word " << w;
        EXPECT_NEAR(got.at(image), score, 1e-5) << "image " << image << ", word " << w;
      }
    }
  }
}

// The best max_results over many chunks of images (selected in ranges on several threads and merged),
// with ties among identical images: the same list as sorting every score, for any thread count and
// any max_results, ties by image number.
TEST(TfIdfScoring, TopKOverManyImagesEqualsSortingEveryScore) {
  constexpr uint32_t kImages = 20000;
  constexpr size_t kVocab = 300;
  const auto bag_of = [](uint32_t image, BagOfWords* bag) {
    if (image % 11 == 3) return false;  // holes in the numbering
    // Images n and n + 5000 have the same bag (equal scores), so ties cross ranges.
    const uint32_t seed = image % 5000;
    std::vector<uint32_t> words;
    for (uint32_t k = 0; k < 12; ++k) words.push_back((seed * 37 + k * k * 13 + k) % kVocab);
    *bag = BagOfWords::FromWords(words);
    return true;
  };
  const InvertedFile file = InvertedFile::Build(kVocab, {}, kImages, bag_of, 2);
  ScoreScratch scratch;
  for (uint32_t q = 0; q < 4; ++q) {
    BagOfWords query;
    bag_of(q * 131 + 1, &query);
    const auto terms = file.QueryVector(query);
    const auto all = file.Score(terms, kImages, &scratch, nullptr, nullptr, 1);
    ASSERT_GT(all.size(), 1000u);
    for (size_t i = 1; i < all.size(); ++i) {
      ASSERT_TRUE(all[i - 1].score > all[i].score ||
                  (all[i - 1].score == all[i].score && all[i - 1].image < all[i].image))
          << i;
    }
    for (const size_t k : {size_t{1}, size_t{7}, size_t{100}, size_t{999}}) {
      for (const int threads : {1, 2, 3}) {
        uint64_t candidates = 0;
        const auto top = file.Score(terms, k, &scratch, &candidates, nullptr, threads);
        EXPECT_EQ(candidates, all.size());
        ASSERT_EQ(top.size(), k);
        for (size_t i = 0; i < k; ++i) {
          EXPECT_EQ(top[i].image, all[i].image) << "k " << k << ", threads " << threads << ", rank " << i;
          EXPECT_EQ(top[i].score, all[i].score);
        }
      }
    }
  }
}

// Score accumulates each segment in blocks of 65536 images: lists that run across several blocks and
// segments (a word of every third image, and one whose few images lie more than the 16-bit gap escape
// apart, in different blocks), a segment of 150,000 images from Build plus one added after it, with
// holes in the numbering, score every image as the definition does, on one thread and on two.
TEST(TfIdfScoring, ScoresAcrossImageBlocksAndSegmentsEqualTheDefinition) {
  constexpr size_t kVocab = 200;
  constexpr uint32_t kBuilt = 150'000, kAdded = 20'000;
  constexpr uint32_t kEvery3 = kVocab - 1, kSparse = kVocab - 2;
  const std::set<uint32_t> sparse_images = {5, 65'535, 65'536, 99'000, 140'001, 160'123};
  std::mt19937_64 rng(4242);
  std::map<uint32_t, BagOfWords> live;
  for (uint32_t i = 0; i < kBuilt + kAdded; ++i) {
    if (i % 13 == 7) continue;  // holes
    std::uniform_int_distribution<uint32_t> word(0, kVocab - 3);
    std::vector<uint32_t> words = {word(rng), word(rng), word(rng)};
    if (i % 3 == 0) words.push_back(kEvery3);
    if (sparse_images.count(i)) words.insert(words.end(), {kSparse, kSparse});
    live[i] = BagOfWords::FromWords(words);
  }
  const TfIdfOptions options{.sqrt_tf = true, .max_document_frequency = 1};
  InvertedFile file = InvertedFile::Build(kVocab, options, kBuilt, [&](uint32_t image, BagOfWords* bag) {
    const auto it = live.find(image);
    if (it == live.end()) return false;
    *bag = it->second;
    return true;
  });
  std::vector<uint32_t> ids;
  std::vector<const BagOfWords*> bags;
  for (auto it = live.lower_bound(kBuilt); it != live.end(); ++it) {
    ids.push_back(it->first);
    bags.push_back(&it->second);
  }
  file = file.WithAdded(ids, bags).WithRefreshedStatistics(2);
  ASSERT_EQ(file.Stats().num_segments, 2u);
  std::vector<uint32_t> query_words = {kEvery3, kSparse, kSparse, 3, 17, 17, 101};
  const BagOfWords query = BagOfWords::FromWords(query_words);
  const auto expected = ReferenceScores(live, query, kVocab, true);
  ScoreScratch scratch;
  const auto terms = file.QueryVector(query);
  for (const int threads : {1, 2}) {
    uint64_t candidates = 0;
    std::map<uint32_t, double> got;
    for (const auto& s : file.Score(terms, 1u << 30, &scratch, &candidates, nullptr, threads)) got[s.image] = s.score;
    size_t nonzero = 0;
    for (const auto& [id, score] : expected) {
      if (score == 0) continue;
      ++nonzero;
      ASSERT_TRUE(got.count(id)) << "image " << id << ", threads " << threads;
      EXPECT_NEAR(got.at(id), score, 1e-6) << "image " << id << ", threads " << threads;
    }
    EXPECT_EQ(got.size(), nonzero) << "threads " << threads;
    EXPECT_EQ(candidates, nonzero) << "threads " << threads;
    for (const uint32_t i : sparse_images) EXPECT_GT(got[i], got[i + 3]) << "image " << i;
  }
}

TEST(ScoringSubset, OnReusedBuffersScoresAsAFreshOne) {
  // Transitive verification builds each search's subset in the memory of the previous one
  // (Subset::Buffers): what that memory held must not leak into the next subset's scores.
  std::mt19937_64 rng(23);
  const size_t vocab = 300;
  std::vector<BagOfWords> corpus;
  std::vector<uint32_t> ids;
  std::vector<const BagOfWords*> corpus_bags;
  for (uint32_t i = 0; i < 60; ++i) corpus.push_back(RandomBag(rng, vocab));
  for (uint32_t i = 0; i < 60; ++i) {
    ids.push_back(i);
    corpus_bags.push_back(&corpus[i]);
  }
  const InvertedFile file = InvertedFile(vocab, TfIdfOptions{.stop_list_min_images = 0}).WithAdded(ids, corpus_bags);
  InvertedFile::Subset::Buffers buffers;
  // Subsets of different sizes in turn (larger, then smaller, then larger), each on the last one's memory.
  for (const size_t count : {50, 7, 33, 60, 1}) {
    std::vector<uint32_t> images;
    std::vector<const BagOfWords*> bags;
    for (size_t k = 0; k < count; ++k) {
      const auto i = static_cast<uint32_t>((k * 13 + count) % corpus.size());
      if (std::find(images.begin(), images.end(), i) != images.end()) continue;
      images.push_back(i);
      bags.push_back(&corpus[i]);
    }
    const InvertedFile::Subset fresh(file, images, bags);
    InvertedFile::Subset reused(file, images, bags, std::move(buffers));
    for (int q = 0; q < 5; ++q) {
      const auto terms = file.QueryVector(RandomBag(rng, vocab));
      EXPECT_EQ(reused.Score(terms), fresh.Score(terms)) << count << " images, query " << q;
    }
    buffers = std::move(reused).Release();
    EXPECT_GE(buffers.first.capacity(), vocab + 1);
  }
}

TEST(ScoringSubset, ScoresEqualScore) {
  // Several segments, a removed image and statistics older than the live images (no refresh after
  // the last adds), as a large index has them; also a stop list.
  std::mt19937_64 rng(19);
  const size_t vocab = 200;
  const TfIdfOptions options{.max_document_frequency = 0.3, .stop_list_min_images = 0, .merge_factor = 4,
                             .exact_statistics_postings = 0, .statistics_refresh_fraction = 1};
  InvertedFile file(vocab, options);
  std::vector<BagOfWords> corpus;
  for (uint32_t i = 0; i < 90; ++i) {
    corpus.push_back(RandomBag(rng, vocab));
    const std::vector<uint32_t> ids = {i};
    const std::vector<const BagOfWords*> bags = {&corpus.back()};
    file = file.WithAdded(ids, bags);
  }
  const std::vector<uint32_t> removed = {5};
  const std::vector<const BagOfWords*> removed_bags = {&corpus[5]};
  file = file.WithRemoved(removed, removed_bags);
  ASSERT_GT(file.Stats().num_segments, 1u);
  ASSERT_GT(file.changes_since_refresh(), 0u);
  ScoreScratch scratch;
  for (int q = 0; q < 10; ++q) {
    const auto terms = file.QueryVector(RandomBag(rng, vocab));
    ASSERT_FALSE(terms.empty());
    std::map<uint32_t, float> listed;
    for (const ScoredImage& s : file.Score(terms, corpus.size(), &scratch)) listed[s.image] = s.score;
    std::vector<uint32_t> images;
    std::vector<const BagOfWords*> bags;
    for (uint32_t i = 0; i < corpus.size(); ++i) {
      images.push_back(i);
      bags.push_back(&corpus[i]);
    }
    const std::vector<float> got = InvertedFile::Subset(file, images, bags).Score(terms);
    for (uint32_t i = 0; i < corpus.size(); ++i) {
      const float expected = listed.count(i) ? listed.at(i) : 0.0f;
      // Equal up to the rounding of a fused multiply-add, which the compiler may use in one loop only.
      EXPECT_NEAR(got[i], expected, 1e-6 * expected) << "query " << q << " image " << i;
      EXPECT_EQ(got[i] == 0, expected == 0) << "query " << q << " image " << i;
    }
  }
}

}  // namespace
}  // namespace oxbow::index
