// Hamming embedding in the index: the match weight, the scoring of index/hamming.h, signatures in the
// packed features (BLOB version 2, geometry checkpoint version 2, old versions still read), and a
// query where the signatures decide the ranking.
#include "index/search/hamming.h"

#include <gtest/gtest.h>

#include <fcntl.h>
#include <sys/mman.h>
#include <unistd.h>

#include <algorithm>
#include <bit>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <random>
#include <thread>
#include <utility>
#include <vector>

#include "index/storage/checkpoint.h"
#include "index/storage/feature_store.h"
#include "index/image_index.h"
#include "index/search/rerank.h"
#include "index/storage/test_support.h"
#include "sift/base/log.h"
#include "tests/support/random_descriptors.h"
#include "tests/support/temp_dir.h"

namespace oxbow::index {
namespace {

namespace fs = std::filesystem;
constexpr int kDim = 128;
constexpr int kWords = 64;


std::vector<sift::Keypoint> RandomKeypoints(std::mt19937_64& rng, size_t n) {
  std::uniform_real_distribution<float> x(0, 600), s(1.5f, 12.0f), o(0, 6.28f);
  std::vector<sift::Keypoint> out;
  for (size_t i = 0; i < n; ++i) out.push_back({x(rng), x(rng) * 0.75f, s(rng), o(rng), 1.0f, 0});
  return out;
}

TEST(HammingWeightTest, GaussianOfTheDistanceUpToTheThreshold) {
  const HammingWeighting w{.threshold = 24, .sigma = 16};
  EXPECT_DOUBLE_EQ(HammingWeight(0xABCDull, 0xABCDull, w), 1.0);
  EXPECT_NEAR(HammingWeight(0, 0xFFull, w), std::exp(-64.0 / 256), 1e-12);      // h = 8
  EXPECT_NEAR(HammingWeight(0, 0xFFFFFFull, w), std::exp(-576.0 / 256), 1e-12);  // h = 24: still matches
  EXPECT_EQ(HammingWeight(0, 0x1FFFFFFull, w), 0.0);                            // h = 25
  EXPECT_EQ(HammingWeight(0, ~0ull, w), 0.0);
}

// Features of words `words` with the given signatures, at arbitrary positions.
PackedFeatures Packed(const std::vector<uint32_t>& words, const std::vector<uint64_t>& signatures) {
  std::mt19937_64 rng(words.size());
  return PackedFeatures::Pack(RandomKeypoints(rng, words.size()), words, 640, 480, signatures);
}

TEST(QuerySignaturesTest, ScoresMatchingSignaturesAndDownWeightsBursts) {
  // idf(w) = 1 + w, word 99 in no image (idf^2 0).
  auto idf_squared = std::make_shared<std::vector<double>>(100);
  for (uint32_t w = 0; w < 99; ++w) (*idf_squared)[w] = (1.0 + w) * (1.0 + w);
  const HammingWeighting weighting;
  // Query: words 1, 2, 99 (99 is in no image: ignored).
  const std::vector<uint32_t> words = {1, 2, 99};
  const std::vector<uint64_t> signatures = {0x0ull, 0xFFFF0000ull, 0x1ull};
  const QuerySignatures query(words, signatures, idf_squared, weighting);
  // The same image scores 1 (each feature matches itself only): N_q = 2^2 + 3^2 = N_d.
  EXPECT_NEAR(query.Score(Packed({1, 2}, {0x0ull, 0xFFFF0000ull})), 1.0, 1e-12);
  // Word 2's signature far away: only word 1 matches, 4 / sqrt(13 * 13).
  EXPECT_NEAR(query.Score(Packed({1, 2}, {0x0ull, 0x0000FFFFull})), 4.0 / 13, 1e-12);
  // Nothing shared.
  EXPECT_EQ(query.Score(Packed({3, 4}, {0x0ull, 0x0ull})), 0.0);
  // A burst: word 1 four times in the db image, all matching the query's one feature exactly. Each match
  // is s^2 / sqrt(S_i S_j) = 1 / sqrt(4 * 1): 4 matches vote 2 (sqrt(4)), not 4.
  const double burst = query.Score(Packed({1, 1, 1, 1}, {0, 0, 0, 0}));
  EXPECT_NEAR(burst, 4.0 * 2.0 / std::sqrt(13.0 * 16.0), 1e-12);
}

// The normalisation N_q^(1 - e) N_d^e: with e above 0.5 a candidate's own size counts more, so of two
// candidates with the same matches the smaller one ranks first; at 0.5 the score is symmetric.
TEST(QuerySignaturesTest, TheNormExponentSharesTheNormalisationBetweenQueryAndCandidate) {
  auto idf_squared = std::make_shared<std::vector<double>>(100);
  for (uint32_t w = 0; w < 100; ++w) (*idf_squared)[w] = 1.0;
  // The query: words 0..3 (N_q = 4). Candidate `small` holds words 0, 1 and one more (N_d = 3), `large`
  // words 0, 1 and ten more (N_d = 12); both match the query on words 0 and 1 exactly (votes 2).
  const std::vector<uint32_t> words = {0, 1, 2, 3};
  const std::vector<uint64_t> signatures = {0, 0, 0, 0};
  const PackedFeatures small = Packed({0, 1, 50}, {0, 0, 0});
  const PackedFeatures large = Packed({0, 1, 50, 51, 52, 53, 54, 55, 56, 57, 58, 59}, std::vector<uint64_t>(12, 0));
  const QuerySignatures symmetric(words, signatures, idf_squared, HammingWeighting{.norm_exponent = 0.5});
  EXPECT_NEAR(symmetric.Score(small), 2.0 / std::sqrt(4.0 * 3.0), 1e-12);
  EXPECT_NEAR(symmetric.Score(large), 2.0 / std::sqrt(4.0 * 12.0), 1e-12);
  const QuerySignatures candidate(words, signatures, idf_squared, HammingWeighting{.norm_exponent = 0.9});
  EXPECT_NEAR(candidate.Score(small), 2.0 / (std::pow(4.0, 0.1) * std::pow(3.0, 0.9)), 1e-12);
  EXPECT_NEAR(candidate.Score(large), 2.0 / (std::pow(4.0, 0.1) * std::pow(12.0, 0.9)), 1e-12);
  // The ratio small / large grows from (12 / 3)^0.5 = 2 to (12 / 3)^0.9.
  EXPECT_NEAR(candidate.Score(small) / candidate.Score(large), std::pow(4.0, 0.9), 1e-9);
  // e = 1: the share of the candidate's own self-score that matched; e = 0: the query's.
  const QuerySignatures share(words, signatures, idf_squared, HammingWeighting{.norm_exponent = 1.0});
  EXPECT_NEAR(share.Score(small), 2.0 / 3.0, 1e-12);
  const QuerySignatures query_share(words, signatures, idf_squared, HammingWeighting{.norm_exponent = 0.0});
  EXPECT_NEAR(query_share.Score(large), 2.0 / 4.0, 1e-12);
}

TEST(AggregatedWeightTest, CubeOfTheSimilarityAboveAQuarter) {
  EXPECT_DOUBLE_EQ(AggregatedWeight(0), 1.0);
  EXPECT_DOUBLE_EQ(AggregatedWeight(16), 0.125);  // u = 1/2
  EXPECT_GT(AggregatedWeight(23), 0.0);           // u = 0.28125
  EXPECT_EQ(AggregatedWeight(24), 0.0);           // u = 1/4: not above
  EXPECT_EQ(AggregatedWeight(64), 0.0);
}

// With asmk_weight, a word of an image is one majority signature: a burst votes once, and a word whose
// features mostly disagree with the query's does not vote even when one of them matches.
TEST(QuerySignaturesTest, AggregatedMatchingVotesOncePerWordWithTheMajoritySignature) {
  auto idf_squared = std::make_shared<std::vector<double>>(10, 1.0);
  const std::vector<uint32_t> words = {0, 1};
  const std::vector<uint64_t> signatures = {0x0ull, 0x0ull};
  const QuerySignatures plain(words, signatures, idf_squared, HammingWeighting{.threshold = 32});
  const QuerySignatures once(words, signatures, idf_squared, HammingWeighting{.threshold = 32, .asmk_weight = 1});
  const QuerySignatures twice(words, signatures, idf_squared, HammingWeighting{.threshold = 32, .asmk_weight = 2});
  // Word 0 three times in the image, the last two with the query's signature: the majority is the
  // query's (not the first feature's).
  // M_q = 2 (words 0 and 1), M_d = 2 (words 0 and 2): the aggregated score is 1 / sqrt(2 * 2).
  const PackedFeatures agreeing = Packed({0, 0, 0, 2}, {~0x0ull, 0x0ull, 0x0ull, 0x0ull});
  EXPECT_NEAR(once.Score(agreeing) - plain.Score(agreeing), 0.5, 1e-12);
  EXPECT_NEAR(twice.Score(agreeing) - plain.Score(agreeing), 1.0, 1e-12);
  // A burst of ten identical features is still one word: the same aggregated score.
  const PackedFeatures burst = Packed({0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 2}, std::vector<uint64_t>(11, 0x0ull));
  EXPECT_NEAR(once.Score(burst) - plain.Score(burst), 0.5, 1e-12);
  // Two of the three features far from the query's: Hamming embedding still matches the first, the
  // aggregated signature (the majority, all ones) does not match.
  const PackedFeatures disagreeing = Packed({0, 0, 0, 2}, {0x0ull, ~0x0ull, ~0x0ull, 0x0ull});
  EXPECT_GT(plain.Score(disagreeing), 0.0);
  EXPECT_NEAR(once.Score(disagreeing), plain.Score(disagreeing), 1e-12);
  // Four features: the majority (three far ones) does not match; a tie (two and two) takes the first's bits.
  const PackedFeatures four = Packed({0, 0, 0, 0, 2}, {0x0ull, ~0x0ull, ~0x0ull, ~0x0ull, 0x0ull});
  EXPECT_NEAR(once.Score(four), plain.Score(four), 1e-12);
  const PackedFeatures tie = Packed({0, 0, 0, 0, 2}, {0x0ull, ~0x0ull, 0x0ull, ~0x0ull, 0x0ull});
  EXPECT_NEAR(once.Score(tie) - plain.Score(tie), 0.5, 1e-12);
  const PackedFeatures tie_far = Packed({0, 0, 0, 0, 2}, {~0x0ull, 0x0ull, ~0x0ull, 0x0ull, 0x0ull});
  EXPECT_NEAR(once.Score(tie_far), plain.Score(tie_far), 1e-12);
  // The query's own aggregation: its word 0 three times, mostly far from the image's.
  const std::vector<uint32_t> split_words = {0, 0, 0, 1};
  const std::vector<uint64_t> split_signatures = {0x0ull, ~0x0ull, ~0x0ull, 0x0ull};
  const QuerySignatures split(split_words, split_signatures, idf_squared,
                              HammingWeighting{.threshold = 32, .asmk_weight = 1});
  const QuerySignatures split_plain(split_words, split_signatures, idf_squared, HammingWeighting{.threshold = 32});
  EXPECT_NEAR(split.Score(agreeing), split_plain.Score(agreeing), 1e-12);
  // With the candidate's N_d given, the same scores.
  const double self = 4;  // four features of idf^2 1
  EXPECT_NEAR(once.Score(agreeing, self), once.Score(agreeing), 1e-12);
}

// The majority signature of a burst of any length, on either side, is the bitwise vote (a tie takes
// the first feature's bit): the aggregated score of one word is 1 against the vote and lower against
// the vote with one bit flipped.
TEST(QuerySignaturesTest, AggregatedSignatureIsTheBitwiseVoteOfAnyBurst) {
  auto idf_squared = std::make_shared<std::vector<double>>(4, 1.0);
  std::mt19937_64 random(7);
  const double one_bit_off = std::pow(1.0 - 2.0 / 64, 3);
  for (size_t n = 1; n <= 70; ++n) {
    std::vector<uint64_t> burst(n);
    // Each bit set with probability 1/4: in a burst, bits that win the vote, lose it and tie.
    for (uint64_t& s : burst) {
      s = random();
      s &= random();
    }
    uint64_t vote = 0;
    for (int b = 0; b < 64; ++b) {
      size_t ones = 0;
      for (const uint64_t s : burst) ones += (s >> b) & 1;
      if (2 * ones > n || (2 * ones == n && ((burst[0] >> b) & 1) != 0)) vote |= uint64_t{1} << b;
    }
    const std::vector<uint32_t> burst_words(n, 0);
    for (const uint64_t single : {vote, vote ^ (uint64_t{1} << (n % 64))}) {
      const double expected = single == vote ? 1.0 : one_bit_off;
      const std::vector<uint32_t> one_word = {0};
      const std::vector<uint64_t> one_signature = {single};
      // The burst in the image.
      const QuerySignatures query(one_word, one_signature, idf_squared, {.threshold = 64, .asmk_weight = 1});
      const QuerySignatures plain(one_word, one_signature, idf_squared, {.threshold = 64});
      const PackedFeatures image = Packed(burst_words, burst);
      EXPECT_NEAR(query.Score(image) - plain.Score(image), expected, 1e-12) << "image burst of " << n;
      // The burst in the query.
      const QuerySignatures burst_query(burst_words, burst, idf_squared, {.threshold = 64, .asmk_weight = 1});
      const QuerySignatures burst_plain(burst_words, burst, idf_squared, {.threshold = 64});
      const PackedFeatures single_image = Packed(one_word, one_signature);
      EXPECT_NEAR(burst_query.Score(single_image) - burst_plain.Score(single_image), expected, 1e-12)
          << "query burst of " << n;
    }
  }
}

// The index scores a shortlist with each candidate's N_d given as its tf-idf norm squared (sqrt(tf)
// weighting, the default), which lets Score skip the candidate's words the query lacks: the norm must
// be N_d, and the score with it given must equal the one Score computes alone.
TEST(QuerySignaturesTest, TheNormSquaredIsTheCandidatesSelfScoreAndGivesTheSameScores) {
  std::mt19937_64 rng(11);
  constexpr uint32_t kVocabulary = 400, kImages = 40;
  std::vector<std::vector<uint32_t>> words(kImages);
  std::vector<std::vector<uint64_t>> signatures(kImages);
  for (uint32_t n = 0; n < kImages; ++n) {
    for (int f = 0; f < 300; ++f) {
      const uint64_t r = rng() % kVocabulary;
      words[n].push_back(static_cast<uint32_t>(r * r / kVocabulary));  // skewed: repeats and bursts
      signatures[n].push_back(rng());
    }
  }
  const InvertedFile file = InvertedFile::Build(kVocabulary, TfIdfOptions{}, kImages, [&](uint32_t n, BagOfWords* bag) {
    *bag = BagOfWords::FromWords(words[n]);
    return true;
  }, 1);
  ASSERT_TRUE(file.options().sqrt_tf);
  const auto idf_squared = file.IdfSquaredTable();
  // The query: image 0's features, half of their signatures a few bits off, plus words of image 1.
  std::vector<uint32_t> query_words = words[0];
  std::vector<uint64_t> query_signatures = signatures[0];
  for (size_t i = 0; i < query_signatures.size(); i += 2) query_signatures[i] ^= 0x10101ull;
  for (size_t i = 0; i < 50; ++i) {
    query_words.push_back(words[1][i]);
    query_signatures.push_back(signatures[1][i] ^ 0xF0ull);
  }
  const QuerySignatures query(query_words, query_signatures, idf_squared, HammingWeighting{});
  size_t positive = 0;
  for (uint32_t n = 0; n < kImages; ++n) {
    SCOPED_TRACE("image " + std::to_string(n));
    const PackedFeatures db = Packed(words[n], signatures[n]);
    double self = 0;
    for (const uint32_t w : words[n]) self += (*idf_squared)[w];
    const double norm = file.Norm(n);
    EXPECT_NEAR(norm * norm, self, 1e-9 * self);
    const double alone = query.Score(db), given = query.Score(db, norm * norm);
    EXPECT_NEAR(given, alone, 1e-12 * std::max(1.0, alone));
    positive += alone > 0 ? 1 : 0;
  }
  EXPECT_GE(positive, 2u);  // images 0 and 1 at least
  EXPECT_EQ(query.Score(Packed(words[2], signatures[2]), 0.0), 0.0);  // N_d 0: nothing to normalise by
}

TEST(PackedSignaturesTest, BlobAndCheckpointRoundTripAndOldFormatsStillLoad) {
  std::mt19937_64 rng(5);
  const std::vector<uint32_t> words = {7, 3, 7, 1, 3};
  const std::vector<uint64_t> signatures = {70, 30, 71, 10, 31};
  const auto keypoints = RandomKeypoints(rng, words.size());
  const PackedFeatures with = PackedFeatures::Pack(keypoints, words, 640, 480, signatures);
  const PackedFeatures without = PackedFeatures::Pack(keypoints, words, 640, 480);
  ASSERT_TRUE(with.has_signatures());
  EXPECT_TRUE(without.signature_bytes().empty());
  // Signatures follow their features into word order (ties in input order).
  const std::vector<uint64_t> sorted = {10, 30, 31, 70, 71};
  for (size_t i = 0; i < sorted.size(); ++i) EXPECT_EQ(with.signature(i), sorted[i]);
  EXPECT_EQ(with.MemoryBytes() - without.MemoryBytes(), words.size() * kSignatureBytes);

  const auto blob = with.Serialize();
  const auto old_blob = without.Serialize();
  EXPECT_EQ(blob[4], 2);      // version 2 with signatures
  EXPECT_EQ(old_blob[4], 1);  // version 1 without: what older builds wrote and read
  EXPECT_EQ(blob.size() - old_blob.size(), words.size() * kSignatureBytes);
  auto back = PackedFeatures::Deserialize(blob, "test");
  auto old_back = PackedFeatures::Deserialize(old_blob, "test");
  ASSERT_TRUE(back && old_back);
  EXPECT_EQ(back->Words(), with.Words());
  for (size_t i = 0; i < sorted.size(); ++i) EXPECT_EQ(back->signature(i), sorted[i]);
  EXPECT_TRUE(old_back->signature_bytes().empty());
  EXPECT_EQ(old_back->Words(), without.Words());
  auto damaged = blob;
  damaged[damaged.size() - 1] ^= 1;  // a signature bit: the checksum covers them
  EXPECT_EQ(PackedFeatures::Deserialize(damaged, "test").error().code, ErrorCode::kCorruptData);

  // Geometry files: version 3 (per-image checksums) is written; 1 (no signatures) and 2 (signatures),
  // what older builds wrote, are read.
  const oxbow::testing::TempDir temp;
  const fs::path dir = temp.path();
  for (const auto& [version, signed_images] : std::vector<std::pair<uint32_t, bool>>{
           {1, false}, {2, false}, {2, true}, {3, false}, {3, true}}) {
    SCOPED_TRACE("version " + std::to_string(version) + (signed_images ? " with signatures" : ""));
    std::vector<GeometryImage> images = {{2, without, std::nullopt}, {5, signed_images ? with : without, std::nullopt}};
    std::vector<uint8_t> file;
    SetGeometryFormatVersionForTesting(version);
    WriteGeometry(images, [&](std::span<const uint8_t> b) { file.insert(file.end(), b.begin(), b.end()); });
    SetGeometryFormatVersionForTesting(3);
    EXPECT_EQ(file[4], version);
    const std::string path = (dir / "geometry.oxck").string();
    std::ofstream(path, std::ios::binary).write(reinterpret_cast<const char*>(file.data()),
                                                static_cast<std::streamsize>(file.size()));
    auto mapped = MappedFile::Open(path);
    ASSERT_TRUE(mapped);
    auto read = ReadGeometry(*mapped, "test");
    ASSERT_TRUE(read) << read.error().ToString();
    ASSERT_EQ(read->size(), 2u);
    EXPECT_TRUE((*read)[0].features.signature_bytes().empty());
    EXPECT_EQ((*read)[1].features.Words(), with.Words());
    EXPECT_EQ((*read)[1].features.signature_bytes().empty(), !signed_images);
    if (signed_images) {
      for (size_t i = 0; i < sorted.size(); ++i) EXPECT_EQ((*read)[1].features.signature(i), sorted[i]);
    }
    for (const GeometryImage& image : *read) {
      EXPECT_EQ(image.checksum.has_value(), version == 3);
      if (image.checksum) {
        EXPECT_EQ(*image.checksum, ImageChecksum(image.features));
      }
    }
    if (version == 3) {
      EXPECT_NE(ImageChecksum(with), ImageChecksum(without)) << "the checksum covers the signatures";
    }
  }
}

// The features a search is about to read (its shortlist) are asked for at once: WillNeed on a view of
// a mapped geometry file whose pages are not in memory starts reading them, and the pages arrive
// without a fault (mincore sees them). Without the hint the pages stay on disk until first touched.
TEST(PackedSignaturesTest, WillNeedReadsAMappedImageIntoMemoryBeforeItsFirstUse) {
  std::mt19937_64 rng(9);
  const size_t n = 40000;  // 360 KB of records and 320 KB of signatures: many pages of each
  std::vector<uint32_t> words(n);
  std::vector<uint64_t> signatures(n);
  for (size_t i = 0; i < n; ++i) {
    words[i] = static_cast<uint32_t>(rng() % 5000);
    signatures[i] = rng();
  }
  const PackedFeatures packed = PackedFeatures::Pack(RandomKeypoints(rng, n), words, 640, 480, signatures);
  // Beside the test binary, not in /tmp: pages of a tmpfs file are always in memory.
  const oxbow::testing::TempDir temp("oxbow-willneed", fs::current_path());
  const fs::path dir = temp.path();
  const std::string path = (dir / "geometry.oxck").string();
  {
    std::vector<uint8_t> file;
    WriteGeometry(std::vector<GeometryImage>{{1, packed, std::nullopt}},
                  [&](std::span<const uint8_t> b) { file.insert(file.end(), b.begin(), b.end()); });
    std::ofstream(path, std::ios::binary).write(reinterpret_cast<const char*>(file.data()),
                                                static_cast<std::streamsize>(file.size()));
  }
  // Out of the page cache: written back, then dropped (clean pages no process maps).
  const int fd = ::open(path.c_str(), O_RDONLY);
  ASSERT_GE(fd, 0);
  ASSERT_EQ(::fdatasync(fd), 0);
  ASSERT_EQ(::posix_fadvise(fd, 0, 0, POSIX_FADV_DONTNEED), 0);
  ::close(fd);
  auto mapped = MappedFile::Open(path);
  ASSERT_TRUE(mapped);
  auto read = ReadGeometry(*mapped, "test");
  ASSERT_TRUE(read) << read.error().ToString();
  const PackedFeatures& view = (*read)[0].features;
  const auto page = static_cast<uintptr_t>(::sysconf(_SC_PAGESIZE));
  // Resident pages among those of `bytes` past its first page (ReadGeometry read the file's header,
  // which may share the first one).
  const auto resident = [&](std::span<const uint8_t> bytes) {
    const uint8_t* begin = bytes.data() + (page - (reinterpret_cast<uintptr_t>(bytes.data()) & (page - 1)));
    const uint8_t* end = bytes.data() + bytes.size();
    end -= reinterpret_cast<uintptr_t>(end) & (page - 1);
    std::vector<unsigned char> in(static_cast<size_t>(end - begin) / page);
    EXPECT_EQ(::mincore(const_cast<uint8_t*>(begin), static_cast<size_t>(end - begin), in.data()), 0);
    size_t count = 0;
    for (const unsigned char c : in) count += c & 1;
    return std::pair(count, in.size());
  };
  const auto [records_before, record_pages] = resident(view.bytes());
  const auto [signatures_before, signature_pages] = resident(view.signature_bytes());
  ASSERT_GT(record_pages, 50u);
  ASSERT_GT(signature_pages, 50u);
  if (records_before + signatures_before > (record_pages + signature_pages) / 2) {
    GTEST_SKIP() << "the file system of " << dir << " keeps files in memory (posix_fadvise dropped "
                 << "nothing): WillNeed cannot be observed there";
  }
  view.WillNeed();
  // The reads run in the background: wait for them (seconds at most; no timing is asserted).
  size_t records = 0, signed_pages = 0;
  for (int i = 0; i < 500; ++i) {
    records = resident(view.bytes()).first;
    signed_pages = resident(view.signature_bytes()).first;
    if (records == record_pages && signed_pages == signature_pages) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  EXPECT_EQ(records, record_pages);
  EXPECT_EQ(signed_pages, signature_pages);
  EXPECT_EQ(view.Words(), packed.Words());  // and they are the image's features
}

// ReadAt copies a part of a mapped file with pread (a search reads its shortlist so, without mapping
// the pages); anything outside the file, a size mismatch or a file read into memory is refused.
TEST(PackedSignaturesTest, ReadAtCopiesAPartOfAMappedFile) {
  const oxbow::testing::TempDir temp;
  const fs::path dir = temp.path();
  const std::string path = (dir / "f").string();
  std::vector<uint8_t> content(3 * 4096 + 17);
  for (size_t i = 0; i < content.size(); ++i) content[i] = static_cast<uint8_t>(i * 131 + 7);
  std::ofstream(path, std::ios::binary).write(reinterpret_cast<const char*>(content.data()),
                                              static_cast<std::streamsize>(content.size()));
  auto mapped = MappedFile::Open(path);
  ASSERT_TRUE(mapped);
  const std::span<const uint8_t> bytes = (*mapped)->bytes();
  std::vector<uint8_t> out(5000);
  ASSERT_TRUE((*mapped)->ReadAt(bytes.subspan(4000, 5000), out));
  EXPECT_TRUE(std::equal(out.begin(), out.end(), content.begin() + 4000));
  std::vector<uint8_t> tail(17);
  ASSERT_TRUE((*mapped)->ReadAt(bytes.last(17), tail));
  EXPECT_TRUE(std::equal(tail.begin(), tail.end(), content.end() - 17));
  EXPECT_FALSE((*mapped)->ReadAt(bytes.subspan(4000, 4999), out));                    // sizes differ
  EXPECT_FALSE((*mapped)->ReadAt(std::span(bytes.data() + bytes.size() - 16, 17), tail));  // past the end
  EXPECT_FALSE((*mapped)->ReadAt(std::span(content.data(), 17), tail));               // not in the file
  auto resident = MappedFile::Open(path, MappedFile::Use::kResident);
  ASSERT_TRUE(resident);
  EXPECT_FALSE((*resident)->ReadAt((*resident)->bytes().first(17), tail));  // read whole already
}

TEST(HammingRerankTest, TentativeMatchesNeedCloseSignatures) {
  // 30 features of distinct words, the db image a translated copy: they verify with every feature.
  std::mt19937_64 rng(8);
  std::vector<sift::Keypoint> query = RandomKeypoints(rng, 30), shifted = query;
  for (auto& k : shifted) k.x += 5;
  std::vector<uint32_t> words(30);
  for (uint32_t i = 0; i < 30; ++i) words[i] = i;
  std::vector<uint64_t> query_signatures(30), close(30), far(30);
  for (size_t i = 0; i < 30; ++i) {
    query_signatures[i] = rng();
    close[i] = query_signatures[i] ^ 0xFFull;  // 8 bits apart
    far[i] = ~query_signatures[i];             // 64 bits apart
  }
  const std::array<float, 4> region = {0, 0, 640, 480};
  const QueryGeometry plain(query, words, region);
  const QueryGeometry hamming(query, words, region, query_signatures, 24);
  const sift::HoughVerifyOptions verify;
  const auto db_close = PackedFeatures::Pack(shifted, words, 640, 480, close);
  const auto db_far = PackedFeatures::Pack(shifted, words, 640, 480, far);
  EXPECT_TRUE(plain.Verify(db_far, 4, verify).verified);
  EXPECT_TRUE(hamming.Verify(db_close, 4, verify).verified);
  EXPECT_EQ(hamming.Verify(db_close, 4, verify).num_inliers, plain.Verify(db_far, 4, verify).num_inliers);
  EXPECT_FALSE(hamming.Verify(db_far, 4, verify).verified);
  EXPECT_EQ(hamming.Verify(db_far, 4, verify).num_inliers, 0);
  // One bursty word (6 features on each side: more than max_pairs_per_word 4) gives no pair without
  // signatures; with them, its close pairs count.
  std::vector<sift::Keypoint> six(query.begin(), query.begin() + 6), six_shifted(shifted.begin(), shifted.begin() + 6);
  std::vector<uint32_t> six_words(6, 0);
  std::vector<uint64_t> six_signatures(query_signatures.begin(), query_signatures.begin() + 6),
      six_close(close.begin(), close.begin() + 6);
  const QueryGeometry burst_plain(six, six_words, region);
  const QueryGeometry burst_hamming(six, six_words, region, six_signatures, 24);
  const auto db_burst = PackedFeatures::Pack(six_shifted, six_words, 640, 480, six_close);
  EXPECT_FALSE(burst_plain.Verify(db_burst, 4, verify).verified);
  EXPECT_TRUE(burst_hamming.Verify(db_burst, 4, verify).verified);
  EXPECT_EQ(burst_hamming.Verify(db_burst, 4, verify).num_inliers, 6);
  // A db image without signatures is matched as without Hamming embedding.
  EXPECT_TRUE(hamming.Verify(PackedFeatures::Pack(shifted, words, 640, 480), 4, verify).verified);
}

TEST(HammingRerankTest, MaxMatchesKeepsTheClosestSignatures) {
  // Features 0-9 of the db image are a translated copy of the query's (Hamming distances 13-17: another
  // photo of the same thing; near-identical signatures would be pasted pixels, which a verification
  // measures as a possible overlay); features 10-29 lie elsewhere (distance 20: within the threshold, so
  // they are tentative matches).
  std::mt19937_64 rng(11);
  std::vector<sift::Keypoint> query = RandomKeypoints(rng, 30), db = RandomKeypoints(rng, 30);
  for (size_t i = 0; i < 10; ++i) {
    db[i] = query[i];
    db[i].x += 5;
  }
  std::vector<uint32_t> words(30);
  std::vector<uint64_t> query_signatures(30), db_signatures(30);
  for (uint32_t i = 0; i < 30; ++i) {
    words[i] = i;
    query_signatures[i] = rng();
    const int distance = i < 10 ? 13 + static_cast<int>(i / 2) : 20;
    db_signatures[i] = query_signatures[i] ^ ((uint64_t{1} << distance) - 1);
  }
  const std::array<float, 4> region = {0, 0, 640, 480};
  const auto packed = PackedFeatures::Pack(db, words, 640, 480, db_signatures);
  const sift::HoughVerifyOptions verify;
  const QueryGeometry all(query, words, region, query_signatures, 24);
  const QueryGeometry unlimited(query, words, region, query_signatures, 24, 0);
  const QueryGeometry closest8(query, words, region, query_signatures, 24, 8);
  const QueryGeometry closest5(query, words, region, query_signatures, 24, 5);
  EXPECT_EQ(all.Verify(packed, 4, verify).num_inliers, 10);
  EXPECT_EQ(unlimited.Verify(packed, 4, verify).num_inliers, 10);
  // The 8 closest are all copies (the far 20 are dropped first): 8 inliers, still verified.
  const sift::VerificationResult eight = closest8.Verify(packed, 4, verify);
  EXPECT_TRUE(eight.verified);
  EXPECT_EQ(eight.num_inliers, 8);
  // Fewer than min_inliers (6) matches cannot verify.
  EXPECT_FALSE(closest5.Verify(packed, 4, verify).verified);
  // Without signatures on the db side the limit does not apply (no distances to rank by).
  EXPECT_EQ(closest8.Verify(PackedFeatures::Pack(db, words, 640, 480), 4, verify).num_inliers,
            QueryGeometry(query, words, region).Verify(PackedFeatures::Pack(db, words, 640, 480), 4, verify).num_inliers);
}

// Two database images with the query's words, only one with its descriptors (hence signatures): tf-idf
// cannot tell them apart, Hamming embedding ranks the right one first; the index reopens (from its
// checkpoint and from its BLOBs) with the same signatures.
class HammingIndexTest : public ::testing::Test {
 protected:
  void SetUp() override {
    log::SetLevel(log::Level::kWarning);
    auto plain = vocab::Vocabulary::FromCentroids(testing::RandomUnitRows(kWords, kDim, 1), kDim, sift::DescriptorKind::kRootSift,
                                                  "test-extractor/1");
    ASSERT_TRUE(plain);
    auto he = plain->WithHamming(Around(plain->centroids(), 50, 9), 3, {.exact = true});
    ASSERT_TRUE(he);
    vocabulary_ = std::make_unique<vocab::Vocabulary>(*he);
  }

  // `per_word` descriptors around each centroid (sigma 0.02 per dimension: they stay in their word).
  static std::vector<float> Around(std::span<const float> centroids, size_t per_word, uint64_t seed) {
    std::mt19937_64 rng(seed);
    std::normal_distribution<float> g(0, 0.02f);
    std::vector<float> out;
    for (size_t w = 0; w < centroids.size() / kDim; ++w) {
      for (size_t i = 0; i < per_word; ++i) {
        for (int d = 0; d < kDim; ++d) out.push_back(centroids[w * kDim + d] + g(rng));
      }
    }
    return out;
  }
  sift::FeatureSet Image(std::vector<float> descriptors, uint64_t seed) const {
    std::mt19937_64 rng(seed);
    sift::FeatureSet f;
    f.image_width = 640;
    f.image_height = 480;
    f.kind = sift::DescriptorKind::kRootSift;
    f.descriptors = std::move(descriptors);
    f.keypoints = RandomKeypoints(rng, f.descriptors.size() / kDim);
    return f;
  }

  oxbow::testing::TempDir temp_;
  fs::path dir_ = temp_ / "index";
  std::unique_ptr<vocab::Vocabulary> vocabulary_;
};

TEST_F(HammingIndexTest, SignaturesDecideBetweenImagesWithTheSameWords) {
  const auto centroids = vocabulary_->centroids();
  const std::vector<float> query = Around(centroids.first(20 * kDim), 1, 100);  // words 0..19, one each
  std::vector<float> same = query;                                             // the query's descriptors
  std::mt19937_64 rng(4);
  std::normal_distribution<float> tiny(0, 0.001f);
  for (float& v : same) v += tiny(rng);
  const std::vector<float> other = Around(centroids.first(20 * kDim), 1, 200);  // same words, other descriptors
  {
    auto index = ImageIndex::Create(dir_.string(), *vocabulary_, "test-extractor/1");
    ASSERT_TRUE(index) << index.error().ToString();
    // Added first, so a tie in tf-idf keeps it first: Hamming embedding must overturn that.
    ASSERT_TRUE((*index)->Add("other", Image(other, 1), {}));
    ASSERT_TRUE((*index)->Add("same", Image(same, 2), {}));
    for (int i = 0; i < 3; ++i) {  // images without the query's words: the words get a non-zero idf
      ASSERT_TRUE((*index)->Add(test_support::NumberedId("filler", i),
                                Image(Around(centroids.subspan((30 + 10 * i) * kDim, 10 * kDim), 2, i), 3 + i), {}));
    }
  }
  for (int reopen = 0; reopen < 2; ++reopen) {
    if (reopen == 1) {  // without a checkpoint: rebuilt from the BLOBs
      for (const auto& e : fs::directory_iterator(dir_)) {
        if (e.path().extension() == ".oxck") fs::remove(e.path());
      }
    }
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    QueryOptions options;
    options.top_k = 5;
    options.rerank_depth = 0;
    options.query_expansion = false;
    options.hamming = false;
    auto tfidf = (*index)->Query(Image(query, 9), options);
    ASSERT_TRUE(tfidf);
    ASSERT_GE(tfidf->results.size(), 2u);
    EXPECT_DOUBLE_EQ(tfidf->results[0].score, tfidf->results[1].score);
    options.hamming = true;
    auto he = (*index)->Query(Image(query, 9), options);
    ASSERT_TRUE(he);
    ASSERT_GE(he->results.size(), 2u);
    EXPECT_EQ(he->results[0].id, "same");
    EXPECT_EQ(he->results[1].id, "other");
    EXPECT_GT(he->results[0].score, 0.9);  // every feature matches its twin
    EXPECT_LT(he->results[1].score, 0.3);  // independent descriptors rarely come within 24 bits
    // QuerySimilar uses the stored signatures the same way.
    auto similar = (*index)->QuerySimilar("same", options);
    ASSERT_TRUE(similar);
    EXPECT_EQ(similar->results[0].id, "same");
    EXPECT_EQ(similar->results[1].id, "other");
  }
}

// Reopened from its checkpoint, the index reads its shortlist's features from the geometry file with
// pread (Entry::SignedFeatures) and scores exactly as the index that had them in memory; a damaged
// signature in the file is caught by the image's checksum on that path too, and never scored.
TEST_F(HammingIndexTest, CheckpointedCandidatesScoreAsInMemoryAndDamageIsNeverScored) {
  const auto centroids = vocabulary_->centroids();
  const std::vector<float> query = Around(centroids.first(20 * kDim), 1, 100);
  std::vector<float> same = query;
  std::mt19937_64 rng(4);
  std::normal_distribution<float> tiny(0, 0.001f);
  for (float& v : same) v += tiny(rng);
  QueryOptions options;
  options.top_k = 8;
  options.rerank_depth = 0;
  options.query_expansion = false;
  const auto scores = [&](const ImageIndex& index) {
    auto response = index.Query(Image(query, 9), options);
    EXPECT_TRUE(response);
    std::vector<std::pair<std::string, double>> out;
    if (response) {
      for (const QueryResult& r : response->results) out.emplace_back(r.id, r.score);
    }
    return out;
  };
  std::vector<std::pair<std::string, double>> in_memory;
  {
    auto index = ImageIndex::Create(dir_.string(), *vocabulary_, "test-extractor/1");
    ASSERT_TRUE(index) << index.error().ToString();
    ASSERT_TRUE((*index)->Add("same", Image(same, 2), {}));
    for (int i = 0; i < 6; ++i) {  // the query's words with other descriptors, and other words
      ASSERT_TRUE((*index)->Add(test_support::NumberedId("other", i), Image(Around(centroids.first(20 * kDim), 1, 200 + i), 10 + i), {}));
      ASSERT_TRUE((*index)->Add(test_support::NumberedId("filler", i),
                                Image(Around(centroids.subspan((30 + 5 * i) * kDim, 5 * kDim), 2, i), 3 + i), {}));
    }
    in_memory = scores(**index);
  }
  ASSERT_GE(in_memory.size(), 7u);
  EXPECT_EQ(in_memory[0].first, "same");
  EXPECT_GT(in_memory[0].second, 0.9);
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    EXPECT_EQ(scores(**index), in_memory);
  }
  // One signature byte of "same" (the first image: number 1) changed in its geometry file.
  std::vector<fs::path> geometry;
  for (const auto& e : fs::directory_iterator(dir_)) {
    if (e.path().filename().string().starts_with("geometry-")) geometry.push_back(e.path());
  }
  ASSERT_EQ(geometry.size(), 1u);
  size_t offset = 0;
  {
    auto mapped = MappedFile::Open(geometry[0].string());
    ASSERT_TRUE(mapped);
    auto images = ReadGeometry(*mapped, "test");
    ASSERT_TRUE(images) << images.error().ToString();
    const auto it = std::find_if(images->begin(), images->end(), [](const GeometryImage& g) { return g.number == 1; });
    ASSERT_NE(it, images->end());
    ASSERT_FALSE(it->features.signature_bytes().empty());
    offset = static_cast<size_t>(it->features.signature_bytes().data() - (*mapped)->bytes().data());
  }
  {
    std::fstream file(geometry[0], std::ios::in | std::ios::out | std::ios::binary);
    file.seekg(static_cast<std::streamoff>(offset));
    char c = 0;
    file.read(&c, 1);
    c = static_cast<char>(c ^ 0x5a);
    file.seekp(static_cast<std::streamoff>(offset));
    file.write(&c, 1);
  }
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    EXPECT_EQ(scores(**index), in_memory);  // "same" read from the catalogue, not the damaged file
  }
}

// Pre-assigned words and signatures (BatchImage::signatures, the storage benchmark's path) store what
// quantising the descriptors and computing their signatures would; signatures that do not fit (another count, no assigned words, a vocabulary without parameters) are refused.
TEST_F(HammingIndexTest, AssignedSignaturesEqualComputingThem) {
  const auto centroids = vocabulary_->centroids();
  std::vector<sift::FeatureSet> images;
  std::vector<std::vector<uint32_t>> words;
  std::vector<std::vector<uint64_t>> signatures;
  for (int i = 0; i < 4; ++i) {
    images.push_back(Image(Around(centroids.subspan(static_cast<size_t>(10 * i) * kDim, 20 * kDim), 1, 40 + i), 50 + i));
    words.emplace_back(images.back().size());
    vocabulary_->Quantize(images.back().descriptors, words.back());
    signatures.emplace_back(images.back().size());
    vocabulary_->Signatures(images.back().descriptors, words.back(), signatures.back());
  }
  auto computed = ImageIndex::Create((dir_ / "computed").string(), *vocabulary_, "test-extractor/1");
  auto assigned = ImageIndex::Create((dir_ / "assigned").string(), *vocabulary_, "test-extractor/1");
  ASSERT_TRUE(computed && assigned);
  std::vector<sift::FeatureSet> bare = images;
  for (auto& f : bare) f.descriptors.clear();
  std::vector<BatchImage> a, b;
  for (size_t i = 0; i < images.size(); ++i) {
    a.push_back({test_support::NumberedId("i", i), &images[i], {}, {}, {}});
    b.push_back({test_support::NumberedId("i", i), &bare[i], {}, words[i], signatures[i]});
  }
  const std::vector<uint64_t> short_signatures(3, 0);
  b.push_back({"short", &bare[0], {}, words[0], short_signatures});
  b.push_back({"unassigned", &images[0], {}, {}, signatures[0]});
  for (const auto& r : (*computed)->AddBatch(a)) ASSERT_TRUE(r) << r.error().ToString();
  const auto results = (*assigned)->AddBatch(b);
  for (size_t i = 0; i < images.size(); ++i) ASSERT_TRUE(results[i]) << results[i].error().ToString();
  EXPECT_EQ(results[4].error().code, ErrorCode::kInvalidArgument);
  EXPECT_EQ(results[5].error().code, ErrorCode::kInvalidArgument);
  for (size_t i = 0; i < images.size(); ++i) {
    const auto x = (*computed)->QuerySimilar(test_support::NumberedId("i", i), QueryOptions{});
    const auto y = (*assigned)->QuerySimilar(test_support::NumberedId("i", i), QueryOptions{});
    ASSERT_TRUE(x && y);
    ASSERT_GE(y->results.size(), x->results.size());
    for (size_t r = 0; r < x->results.size(); ++r) {
      EXPECT_EQ(x->results[r].id, y->results[r].id);
      EXPECT_EQ(x->results[r].score, y->results[r].score);
    }
  }
  // A vocabulary without Hamming-embedding parameters refuses given signatures.
  auto plain = vocab::Vocabulary::FromCentroids(std::vector<float>(centroids.begin(), centroids.end()), kDim,
                                                sift::DescriptorKind::kRootSift, "test-extractor/1");
  ASSERT_TRUE(plain);
  auto without = ImageIndex::Create((dir_ / "plain").string(), *plain, "test-extractor/1");
  ASSERT_TRUE(without);
  const std::vector<BatchImage> c = {{"i0", &bare[0], {}, words[0], signatures[0]}};
  const auto refused = (*without)->AddBatch(c);
  ASSERT_FALSE(refused[0]);
  EXPECT_EQ(refused[0].error().code, ErrorCode::kInvalidArgument);
}

TEST_F(HammingIndexTest, QueryExpansionRanksByTheSignaturesOfTheVerifiedRegions) {
  const auto centroids = vocabulary_->centroids();
  std::mt19937_64 rng(21);
  std::normal_distribution<float> tiny(0, 0.001f);
  const auto near = [&](std::vector<float> d) {
    for (float& v : d) v += tiny(rng);
    return d;
  };
  const std::vector<float> query = Around(centroids.first(20 * kDim), 1, 300);          // words 0..19
  const std::vector<float> region = Around(centroids.subspan(20 * kDim, 20 * kDim), 1, 301);  // words 20..39
  // Both candidates share words 0..4 with the query through unrelated descriptors (tf-idf finds them,
  // neither is like the query), and words 20..39 with the verified image: "expanded" with its very
  // descriptors, "unrelated" with others.
  const std::vector<float> weak_a = Around(centroids.first(5 * kDim), 1, 302);
  const std::vector<float> weak_b = Around(centroids.first(5 * kDim), 1, 303);
  std::vector<float> expanded = weak_a, unrelated = weak_b;
  const std::vector<float> region_copy = near(region), other_region = Around(centroids.subspan(20 * kDim, 20 * kDim), 1, 304);
  expanded.insert(expanded.end(), region_copy.begin(), region_copy.end());
  unrelated.insert(unrelated.end(), other_region.begin(), other_region.end());
  // The verified image: the query's features at the query's keypoints shifted, plus words 20..39.
  sift::FeatureSet q = Image(query, 9);
  sift::FeatureSet verified = q;
  verified.descriptors = near(query);
  for (auto& k : verified.keypoints) k.x += 3;
  verified.descriptors.insert(verified.descriptors.end(), region.begin(), region.end());
  const auto extra = RandomKeypoints(rng, 20);
  verified.keypoints.insert(verified.keypoints.end(), extra.begin(), extra.end());
  auto index = ImageIndex::Create(dir_.string(), *vocabulary_, "test-extractor/1");
  ASSERT_TRUE(index) << index.error().ToString();
  ASSERT_TRUE((*index)->Add("unrelated", Image(unrelated, 1), {}));  // first: wins ties
  ASSERT_TRUE((*index)->Add("expanded", Image(expanded, 2), {}));
  ASSERT_TRUE((*index)->Add("verified", verified, {}));
  for (int i = 0; i < 3; ++i) {
    ASSERT_TRUE((*index)->Add(test_support::NumberedId("filler", i),
                              Image(Around(centroids.subspan((40 + 5 * i) * kDim, 5 * kDim), 2, i), 30 + i), {}));
  }
  QueryOptions options;
  options.top_k = 3;
  options.transitive_depth = 0;
  options.hamming = true;
  options.query_expansion = false;
  auto plain = (*index)->Query(q, options);
  ASSERT_TRUE(plain);
  ASSERT_EQ(plain->results.size(), 3u);
  EXPECT_EQ(plain->results[0].id, "verified");
  EXPECT_TRUE(plain->results[0].verified);
  EXPECT_FALSE(plain->results[1].verified);
  options.query_expansion = true;
  auto with_qe = (*index)->Query(q, options);
  ASSERT_TRUE(with_qe);
  ASSERT_EQ(with_qe->results.size(), 3u);
  EXPECT_EQ(with_qe->results[0].id, "verified");
  EXPECT_EQ(with_qe->results[1].id, "expanded");
  EXPECT_EQ(with_qe->results[2].id, "unrelated");
  EXPECT_GT(with_qe->results[1].score, with_qe->results[2].score);
}

}  // namespace
}  // namespace oxbow::index
