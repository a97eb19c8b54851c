#include "vocab/vocabulary.h"

#include <gtest/gtest.h>
#include <opencv2/features2d.hpp>
#include <opencv2/imgcodecs.hpp>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <random>

#include "sift/base/binary_io.h"
#include "sift/base/log.h"
#include "tests/support/temp_dir.h"
#include "vocab/kernels.h"

namespace oxbow::vocab {
namespace {

namespace fs = std::filesystem;

// A file in this test binary's temporary folder (removed at exit).
std::string TempPath(const std::string& name) {
  static const oxbow::testing::TempDir dir("oxbow-vocabulary-test");
  return (dir / name).string();
}

// RootSIFT descriptors of real photos (cv::SIFT as the stand-in extractor; opencv-doc is always installed).
std::vector<float> RealDescriptors() {
  std::vector<float> out;
  auto sift = cv::SIFT::create(1500);
  for (const char* name : {"graf1.png", "box_in_scene.png", "leuvenA.jpg"}) {
    const cv::Mat image = cv::imread(std::string("/usr/share/doc/opencv-doc/examples/data/") + name, cv::IMREAD_GRAYSCALE);
    if (image.empty()) continue;
    std::vector<cv::KeyPoint> keypoints;
    cv::Mat desc;
    sift->detectAndCompute(image, cv::noArray(), keypoints, desc);
    for (int r = 0; r < desc.rows; ++r) {
      const float* d = desc.ptr<float>(r);
      double l1 = 0;
      for (int i = 0; i < 128; ++i) l1 += d[i];
      for (int i = 0; i < 128; ++i) out.push_back(static_cast<float>(std::sqrt(d[i] / std::max(l1, 1e-12))));
    }
  }
  return out;
}

// A realistic vocabulary without training: words are real descriptors plus a little noise.
std::vector<float> WordsFrom(const std::vector<float>& descriptors, size_t k, uint32_t seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> noise(0.f, 0.01f);
  const size_t n = descriptors.size() / 128;
  std::vector<float> words(k * 128);
  for (size_t w = 0; w < k; ++w) {
    const size_t src = (w * 7919) % n;
    for (int d = 0; d < 128; ++d) words[w * 128 + d] = descriptors[src * 128 + d] + noise(rng);
  }
  return words;
}

class VocabularyTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    log::SetLevel(log::Level::kWarning);
    descriptors_ = new std::vector<float>(RealDescriptors());
  }
  static void TearDownTestSuite() { delete descriptors_; }
  static const std::vector<float>& descriptors() { return *descriptors_; }
  static std::vector<float>* descriptors_;
};
std::vector<float>* VocabularyTest::descriptors_ = nullptr;

TEST_F(VocabularyTest, FileRoundTrip) {
  ASSERT_GT(descriptors().size(), 128u * 1000);
  auto vocab = Vocabulary::FromCentroids(WordsFrom(descriptors(), 500, 1), 128, sift::DescriptorKind::kRootSift,
                                         "sift peak=0.0067 edge=10");
  ASSERT_TRUE(vocab) << vocab.error().ToString();
  const std::string path = TempPath("roundtrip.vocab");
  ASSERT_TRUE(vocab->Write(path));
  auto back = Vocabulary::Read(path);
  ASSERT_TRUE(back) << back.error().ToString();
  EXPECT_EQ(back->size(), 500u);
  EXPECT_EQ(back->dimension(), 128);
  EXPECT_EQ(back->descriptor_kind(), sift::DescriptorKind::kRootSift);
  EXPECT_EQ(back->extractor_settings(), "sift peak=0.0067 edge=10");
  EXPECT_EQ(back->fingerprint(), vocab->fingerprint());
  EXPECT_EQ(back->num_lists(), vocab->num_lists());
  EXPECT_TRUE(std::equal(back->centroids().begin(), back->centroids().end(), vocab->centroids().begin(),
                         vocab->centroids().end()));
  std::vector<uint32_t> a(2000), b(2000);
  const std::span<const float> queries(descriptors().data(), 2000 * 128);
  vocab->Quantize(queries, a);
  back->Quantize(queries, b);
  EXPECT_EQ(a, b);
  fs::remove(path);
}

// Reads of files with the same content share one copy in memory (the collections of a server over one
// vocabulary); a file of other content does not.
TEST_F(VocabularyTest, ReadsOfTheSameContentShareOneCopy) {
  auto vocab = Vocabulary::FromCentroids(WordsFrom(descriptors(), 300, 1), 128, sift::DescriptorKind::kRootSift, "s");
  auto other = Vocabulary::FromCentroids(WordsFrom(descriptors(), 300, 2), 128, sift::DescriptorKind::kRootSift, "s");
  ASSERT_TRUE(vocab && other);
  const std::string a = TempPath("shared-a.vocab"), b = TempPath("shared-b.vocab"), c = TempPath("shared-c.vocab");
  ASSERT_TRUE(vocab->Write(a) && vocab->Write(b) && other->Write(c));
  auto first = Vocabulary::Read(a);
  auto second = Vocabulary::Read(b);
  auto third = Vocabulary::Read(c);
  ASSERT_TRUE(first && second && third);
  EXPECT_EQ(first->centroids().data(), second->centroids().data());
  EXPECT_NE(first->centroids().data(), third->centroids().data());
  EXPECT_NE(first->fingerprint(), third->fingerprint());
  for (const auto& path : {a, b, c}) fs::remove(path);
}

TEST_F(VocabularyTest, RefusesDamagedTruncatedForeignAndNewerFiles) {
  auto vocab = Vocabulary::FromCentroids(WordsFrom(descriptors(), 64, 2), 128, sift::DescriptorKind::kSift, "x");
  ASSERT_TRUE(vocab);
  const std::string path = TempPath("damaged.vocab");
  ASSERT_TRUE(vocab->Write(path));
  std::vector<char> bytes;
  {
    std::ifstream in(path, std::ios::binary);
    bytes.assign(std::istreambuf_iterator<char>(in), {});
  }
  auto write = [&](const std::vector<char>& b) {
    std::ofstream out(path, std::ios::binary | std::ios::trunc);
    out.write(b.data(), static_cast<std::streamsize>(b.size()));
  };
  // One flipped bit in the centroids.
  auto flipped = bytes;
  flipped[bytes.size() - 100] ^= 0x10;
  write(flipped);
  auto r1 = Vocabulary::Read(path);
  ASSERT_FALSE(r1);
  EXPECT_EQ(r1.error().code, ErrorCode::kCorruptData);
  EXPECT_NE(r1.error().message.find(path), std::string::npos) << "the message names the file";
  // Truncated.
  write(std::vector<char>(bytes.begin(), bytes.begin() + bytes.size() / 2));
  auto r2 = Vocabulary::Read(path);
  ASSERT_FALSE(r2);
  EXPECT_EQ(r2.error().code, ErrorCode::kCorruptData);
  // Foreign file (another container magic, and plain text).
  ASSERT_TRUE(io::WriteContainerFile(path, "OXBWFEAT", 1, 0, std::vector<uint8_t>(64, 1)));
  auto r3 = Vocabulary::Read(path);
  ASSERT_FALSE(r3);
  EXPECT_EQ(r3.error().code, ErrorCode::kCorruptData);
  write(std::vector<char>(100, 'a'));
  EXPECT_FALSE(Vocabulary::Read(path));
  // A newer format version.
  ASSERT_TRUE(io::WriteContainerFile(path, "OXBWVOCB", 3, 0,
                                     std::vector<uint8_t>(bytes.begin() + io::kHeaderBytes, bytes.end())));
  auto r4 = Vocabulary::Read(path);
  ASSERT_FALSE(r4);
  EXPECT_EQ(r4.error().code, ErrorCode::kIncompatible);
  // A valid container whose payload lies about its sizes.
  std::vector<uint8_t> payload(bytes.begin() + io::kHeaderBytes, bytes.end());
  payload[4] ^= 0x01;  // num_words
  ASSERT_TRUE(io::WriteContainerFile(path, "OXBWVOCB", 1, 0, payload));
  auto r5 = Vocabulary::Read(path);
  ASSERT_FALSE(r5);
  EXPECT_EQ(r5.error().code, ErrorCode::kCorruptData);
  fs::remove(path);
  auto r6 = Vocabulary::Read(path);
  ASSERT_FALSE(r6);
  EXPECT_EQ(r6.error().code, ErrorCode::kNotFound);
}

// Centroid values far beyond a unit descriptor's overflow the quantiser's scores (inf - inf = NaN):
// such a file is refused when read. A descriptor whose scores are all NaN (NaN values) leaves the
// memory and the other descriptors of its batch alone (it probed list number `num_lists`, out of
// bounds, before).
TEST_F(VocabularyTest, RefusesHugeCentroidsAndQuantisesOverflowingDescriptorsSafely) {
  std::vector<float> centroids = WordsFrom(descriptors(), 64, 3);
  auto vocab = Vocabulary::FromCentroids(centroids, 128, sift::DescriptorKind::kSift, "x");
  ASSERT_TRUE(vocab);
  centroids[5] = 3e37f;
  // FromCentroids takes finite values (the test writes the file with it); reading the file refuses them.
  auto huge = Vocabulary::FromCentroids(centroids, 128, sift::DescriptorKind::kSift, "x");
  ASSERT_TRUE(huge) << huge.error().ToString();
  const std::string path = TempPath("huge.vocab");
  ASSERT_TRUE(huge->Write(path));
  auto back = Vocabulary::Read(path);
  ASSERT_FALSE(back);
  EXPECT_EQ(back.error().code, ErrorCode::kCorruptData);
  EXPECT_NE(back.error().message.find("beyond"), std::string::npos) << back.error().message;
  fs::remove(path);
  std::vector<float> queries(descriptors().begin(), descriptors().begin() + 40 * 128);
  std::vector<uint32_t> alone(40);
  vocab->Quantize(queries, alone);
  for (size_t i = 128 * 10; i < 128 * 11; ++i) queries[i] = std::numeric_limits<float>::quiet_NaN();  // descriptor 10
  std::vector<uint32_t> mixed(40);
  vocab->Quantize(queries, mixed);
  for (size_t i = 0; i < 40; ++i) {
    if (i != 10) {
      EXPECT_EQ(mixed[i], alone[i]) << i;
    }
  }
}

TEST_F(VocabularyTest, FromCentroidsRefusesBadMatrices) {
  EXPECT_FALSE(Vocabulary::FromCentroids({}, 128, sift::DescriptorKind::kSift, ""));
  EXPECT_FALSE(Vocabulary::FromCentroids(std::vector<float>(130, 0.f), 128, sift::DescriptorKind::kSift, ""));
  std::vector<float> nan(256, 0.f);
  nan[3] = NAN;
  EXPECT_FALSE(Vocabulary::FromCentroids(nan, 128, sift::DescriptorKind::kSift, ""));
  EXPECT_FALSE(Vocabulary::FromCentroids(std::vector<float>(256, 0.f), 128, sift::DescriptorKind::kSift, "",
                                         {.num_lists = 3}));
}

// The default quantiser agrees with the exact nearest word on at least 95% of real descriptors
// (a 2000-word vocabulary, real RootSIFT queries not used to make the words), and exact mode on all.
// Recall grows with the probes, and probing every coarse list is an exhaustive search: exact again.
TEST_F(VocabularyTest, QuantizerAgreesWithExactNearestWord) {
  const size_t n = descriptors().size() / 128;
  const size_t k = 2000;
  auto vocab = Vocabulary::FromCentroids(WordsFrom(descriptors(), k, 3), 128, sift::DescriptorKind::kRootSift, "");
  ASSERT_TRUE(vocab);
  std::vector<uint32_t> truth(n), fast(n), exact(n), fast_mt(n), fast_one(n);
  const auto c = vocab->centroids();
  for (size_t i = 0; i < n; ++i) {
    double best = INFINITY;
    for (size_t w = 0; w < k; ++w) {
      double d = 0;
      for (int j = 0; j < 128; ++j) {
        const double diff = double(descriptors()[i * 128 + j]) - c[w * 128 + j];
        d += diff * diff;
      }
      if (d < best) best = d, truth[i] = static_cast<uint32_t>(w);
    }
  }
  vocab->Quantize(descriptors(), fast);
  vocab->Quantize(descriptors(), fast_mt, {.num_threads = 3});
  vocab->Quantize(descriptors(), fast_one, {.num_threads = 1});
  vocab->Quantize(descriptors(), exact, {.exact = true});
  // The thread count also sets the batches (equal shares per thread): neither may change a word.
  EXPECT_EQ(fast, fast_mt) << "results must not depend on the thread count";
  EXPECT_EQ(fast, fast_one) << "results must not depend on the thread count";
  const auto agreeing = [&](const std::vector<uint32_t>& words) {
    size_t agree = 0;
    for (size_t i = 0; i < n; ++i) agree += words[i] == truth[i];
    return agree;
  };
  // A disagreement of the exact mode can only be a float tie.
  EXPECT_GE(agreeing(exact), n - n / 1000) << "exact mode may differ only on float ties";
  EXPECT_GE(static_cast<double>(agreeing(fast)) / n, 0.95) << agreeing(fast) << " of " << n;

  const int lists = static_cast<int>(vocab->num_lists());
  size_t previous = 0;
  for (int probes : {1, 4, 16, lists}) {
    std::vector<uint32_t> words(n);
    vocab->Quantize(descriptors(), words, {.num_probes = probes});
    const size_t agree = agreeing(words);
    std::printf("%d of %d lists probed: recall@1 %.4f\n", probes, lists, static_cast<double>(agree) / n);
    EXPECT_GE(agree, previous) << probes << " probes found fewer nearest words than fewer probes did";
    previous = agree;
  }
  EXPECT_GE(previous, n - n / 1000) << "probing every list must find the exact nearest word (up to float ties)";
}

TEST_F(VocabularyTest, QuantizeMultiReturnsSortedNearestWords) {
  const size_t k = 300;
  auto vocab = Vocabulary::FromCentroids(WordsFrom(descriptors(), k, 4), 128, sift::DescriptorKind::kRootSift, "");
  ASSERT_TRUE(vocab);
  const size_t n = 500;
  const int m = 5;
  const std::span<const float> queries(descriptors().data(), n * 128);
  std::vector<uint32_t> words(n * m), single(n);
  std::vector<float> dist(n * m);
  vocab->QuantizeMulti(queries, m, words, dist, {.exact = true});
  vocab->Quantize(queries, single, {.exact = true});
  const auto c = vocab->centroids();
  for (size_t i = 0; i < n; ++i) {
    EXPECT_EQ(words[i * m], single[i]);
    std::vector<float> all(k);
    for (size_t w = 0; w < k; ++w) all[w] = internal::SquaredL2(queries.data() + i * 128, c.data() + w * 128, 128);
    std::vector<float> sorted = all;
    std::partial_sort(sorted.begin(), sorted.begin() + m, sorted.end());
    for (int j = 0; j < m; ++j) {
      EXPECT_FLOAT_EQ(dist[i * m + j], all[words[i * m + j]]);
      EXPECT_NEAR(dist[i * m + j], sorted[j], 1e-6);
      if (j > 0) {
        EXPECT_LE(dist[i * m + j - 1], dist[i * m + j]);
      }
    }
  }
  // Asking for more words than exist fills the tail.
  std::vector<uint32_t> w2(2 * (k + 2));
  std::vector<float> d2(2 * (k + 2));
  vocab->QuantizeMulti(queries.subspan(0, 256), static_cast<int>(k + 2), w2, d2, {.exact = true});
  EXPECT_EQ(w2[k], k);
  EXPECT_TRUE(std::isinf(d2[k + 1]));
  EXPECT_LT(w2[k - 1], k);
}

// The quantiser shares a search's coarse lists out between its threads, each keeping its own k best
// words per descriptor, merged at the end: the k best words and their distances must not depend on the
// thread count (more descriptors than one round of 2048 per thread, so rounds are tested too), and
// probing every list must give what the exhaustive search gives.
TEST_F(VocabularyTest, QuantizeMultiDoesNotDependOnThreads) {
  const size_t k = 1500;
  auto vocab = Vocabulary::FromCentroids(WordsFrom(descriptors(), k, 6), 128, sift::DescriptorKind::kRootSift, "");
  ASSERT_TRUE(vocab);
  const size_t n = std::min<size_t>(descriptors().size() / 128, 5000);
  ASSERT_GT(n, 2048u) << "too few test descriptors for more than one round";
  const std::span<const float> queries(descriptors().data(), n * 128);
  const int m = 3;
  std::vector<uint32_t> words_one(n * m), words(n * m);
  std::vector<float> dist_one(n * m), dist(n * m);
  vocab->QuantizeMulti(queries, m, words_one, dist_one, {.num_threads = 1, .num_probes = 4});
  for (int threads : {2, 3, 5}) {
    vocab->QuantizeMulti(queries, m, words, dist, {.num_threads = threads, .num_probes = 4});
    EXPECT_EQ(words, words_one) << threads << " threads";
    EXPECT_EQ(dist, dist_one) << threads << " threads";
  }
  const int lists = static_cast<int>(vocab->num_lists());
  std::vector<uint32_t> exact_words(n * m);
  std::vector<float> exact_dist(n * m);
  vocab->QuantizeMulti(queries, m, exact_words, exact_dist, {.num_threads = 2, .exact = true});
  vocab->QuantizeMulti(queries, m, words, dist, {.num_threads = 2, .num_probes = lists});
  EXPECT_EQ(words, exact_words) << "every list probed must be the exhaustive search";
  EXPECT_EQ(dist, exact_dist);
}

TEST_F(VocabularyTest, QuantizeChecksSizes) {
  auto vocab = Vocabulary::FromCentroids(WordsFrom(descriptors(), 10, 5), 128, sift::DescriptorKind::kSift, "");
  ASSERT_TRUE(vocab);
  std::vector<uint32_t> words(3);
  EXPECT_THROW(vocab->Quantize(std::span<const float>(descriptors().data(), 2 * 128), words), InvariantError);
  EXPECT_THROW(vocab->Quantize(std::span<const float>(descriptors().data(), 3 * 128), words, {.num_probes = 0}),
               InvariantError);
}

}  // namespace
}  // namespace oxbow::vocab
