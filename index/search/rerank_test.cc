#include "index/search/rerank.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include "index/storage/feature_store.h"
#include "sift/match.h"

namespace oxbow::index {
namespace {

struct Image {
  std::vector<sift::Keypoint> keypoints;
  std::vector<uint32_t> words;
};

// n random features over a small vocabulary (so words repeat: bursts of every size occur).
Image RandomImage(std::mt19937_64& rng, int n, uint32_t vocabulary, float width, float height) {
  std::uniform_int_distribution<uint32_t> word(0, vocabulary - 1);
  std::uniform_real_distribution<float> x(0, width - 1), y(0, height - 1), s(1.5f, 12.0f), o(0, 6.28f);
  Image img;
  for (int i = 0; i < n; ++i) {
    img.words.push_back(word(rng));
    img.keypoints.push_back({x(rng), y(rng), s(rng), o(rng), 1.0f, 0});
  }
  return img;
}

// The reference the optimised Verify must equal: every pair of a shared word with at most `limit`
// features on each side, distance = the product of the two counts, sift::EnforceOneToOne, and the
// verifier on all the db image's (dequantised) keypoints.
sift::VerificationResult Reference(const Image& query, const PackedFeatures& db, int limit,
                                   const std::array<float, 4>& region, const sift::HoughVerifyOptions& options) {
  std::vector<sift::Match> pairs;
  for (size_t q = 0; q < query.words.size(); ++q) {
    const uint32_t w = query.words[q];
    size_t cq = 0, cd = 0;
    for (uint32_t x : query.words) cq += x == w ? 1 : 0;
    for (size_t d = 0; d < db.size(); ++d) cd += db.word(d) == w ? 1 : 0;
    if (cq > static_cast<size_t>(limit) || cd > static_cast<size_t>(limit)) continue;
    for (size_t d = 0; d < db.size(); ++d) {
      if (db.word(d) == w) pairs.push_back({static_cast<uint32_t>(q), static_cast<uint32_t>(d), static_cast<float>(cq * cd)});
    }
  }
  const std::vector<sift::Match> unique = sift::EnforceOneToOne(pairs);
  return sift::VerifyHoughAffine(query.keypoints, db.Keypoints(), unique, region, {db.width(), db.height()}, options);
}

TEST(QueryGeometry, VerifyEqualsAllPairsOneToOneAndTheVerifier) {
  std::mt19937_64 rng(5);
  int verified = 0, unverified = 0;
  for (int trial = 0; trial < 40; ++trial) {
    const uint32_t vocabulary = trial % 2 == 0 ? 60 : 400;
    Image db = RandomImage(rng, 300, vocabulary, 640, 480);
    Image query = RandomImage(rng, 150, vocabulary, 800, 600);
    if (trial % 4 < 2) {
      // Half the trials: a rotated, scaled copy of 120 db features inside the query (verifiable).
      const double angle = 0.3 + 0.05 * trial, scale = 1.1, tx = 150, ty = 40;
      for (size_t i = 0; i < 120; ++i) {
        sift::Keypoint k = db.keypoints[i];
        const float x = k.x, y = k.y;
        k.x = static_cast<float>(scale * (std::cos(angle) * x - std::sin(angle) * y) + tx);
        k.y = static_cast<float>(scale * (std::sin(angle) * x + std::cos(angle) * y) + ty);
        k.scale *= static_cast<float>(scale);
        k.orientation = static_cast<float>(std::fmod(k.orientation + angle, 2 * M_PI));
        query.keypoints.push_back(k);
        query.words.push_back(db.words[i]);
      }
    }
    const PackedFeatures packed = PackedFeatures::Pack(db.keypoints, db.words, 640, 480);
    const std::array<float, 4> region = {0, 0, 800, 600};
    const QueryGeometry geometry(query.keypoints, query.words, region);
    for (int limit : {1, 2, 4, 16}) {
      const sift::HoughVerifyOptions options;
      const sift::VerificationResult expected = Reference(query, packed, limit, region, options);
      const sift::VerificationResult got = geometry.Verify(packed, limit, options);
      ASSERT_EQ(got.verified, expected.verified) << "trial " << trial << " limit " << limit;
      if (!expected.verified) {
        // Same verdict is all that counts; Verify may skip the verifier when too few pairs remain.
        ++unverified;
        continue;
      }
      ASSERT_EQ(got.num_inliers, expected.num_inliers) << "trial " << trial << " limit " << limit;
      EXPECT_EQ(got.inliers, expected.inliers);
      EXPECT_EQ(got.db_region, expected.db_region);
      for (size_t k = 0; k < 6; ++k) EXPECT_EQ(got.db_from_query.m[k], expected.db_from_query.m[k]);
      verified += got.verified ? 1 : 0;
    }
  }
  // Both verdicts were exercised.
  EXPECT_GT(verified, 20);
  EXPECT_GT(unverified, 20);
}

TEST(QueryGeometry, FewerMatchesThanMinInliersIsNotVerified) {
  // Five features shared with the db image under one similarity: a six-inlier rule cannot pass, five can.
  std::vector<sift::Keypoint> db_keypoints, query_keypoints;
  std::vector<uint32_t> words;
  for (uint32_t i = 0; i < 5; ++i) {
    const sift::Keypoint k{40.0f + 70.0f * static_cast<float>(i), 30.0f + 45.0f * static_cast<float>(i % 3), 3.0f, 0.5f, 1.0f, 0};
    db_keypoints.push_back(k);
    query_keypoints.push_back({k.x + 20, k.y + 10, k.scale, k.orientation, 1.0f, 0});
    words.push_back(i * 7);
  }
  const PackedFeatures db = PackedFeatures::Pack(db_keypoints, words, 640, 480);
  const QueryGeometry geometry(query_keypoints, words, {0, 0, 640, 480});
  sift::HoughVerifyOptions options;
  options.min_inliers = 6;
  EXPECT_FALSE(geometry.Verify(db, 4, options).verified);
  options.min_inliers = 5;
  const sift::VerificationResult five = geometry.Verify(db, 4, options);
  EXPECT_TRUE(five.verified);
  EXPECT_EQ(five.num_inliers, 5);
}

// A word matched to the same word in another caption: a row of letters' features, plus one chance
// inlier far across the image that the same similarity happens to map. The verifier finds the row plus
// that point firm (the far point sets their principal axis, so the row's thickness is never measured
// across it); the search's Verify keeps it verified but not firm, so it anchors no chain. With a second
// inlier far off the row, the inliers span an area whichever one is left out, and the match stays firm.
TEST(QueryGeometry, ARowOfMatchesPlusOneFarInlierIsNotFirm) {
  auto match = [](const std::vector<std::array<float, 2>>& places) {
    std::vector<sift::Keypoint> query, db;
    std::vector<uint32_t> words;
    query.reserve(places.size());
    db.reserve(places.size());
    words.reserve(places.size());
    for (size_t i = 0; i < places.size(); ++i) {
      const auto [x, y] = places[i];
      query.push_back({x, y, 2.0f, 0.3f, 1.0f, 0});
      db.push_back({1.5f * x + 160, 1.5f * y + 50, 3.0f, 0.3f, 1.0f, 0});
      words.push_back(static_cast<uint32_t>(i) * 11 + 3);
    }
    const PackedFeatures packed = PackedFeatures::Pack(db, words, 1280, 1280);
    const std::array<float, 4> region = {0, 0, 1024, 768};
    const sift::HoughVerifyOptions options;
    std::vector<sift::Match> matches;
    matches.reserve(places.size());
    for (uint32_t i = 0; i < places.size(); ++i) matches.push_back({i, i, 1.0f});
    const sift::VerificationResult verifier =
        sift::VerifyHoughAffine(query, packed.Keypoints(), matches, region, {1280, 1280}, options);
    const sift::VerificationResult search = QueryGeometry(query, words, region).Verify(packed, 4, options);
    return std::pair{verifier, search};
  };
  std::vector<std::array<float, 2>> row;
  row.reserve(11);
  for (int i = 0; i < 11; ++i) row.push_back({98.0f + 20.0f * static_cast<float>(i), 11.0f + 3.0f * static_cast<float>(i % 4)});
  std::vector<std::array<float, 2>> stray = row;
  stray.push_back({347, 700});
  const auto [verifier, search] = match(stray);
  ASSERT_TRUE(verifier.verified);
  ASSERT_EQ(verifier.num_inliers, 12);
  EXPECT_TRUE(verifier.firm);  // the case this guards: the verifier's own test passes it
  EXPECT_TRUE(search.verified);
  EXPECT_EQ(search.num_inliers, 12);
  EXPECT_FALSE(search.firm);

  std::vector<std::array<float, 2>> area = row;
  area.push_back({347, 700});
  area.push_back({600, 400});
  const auto [area_verifier, area_search] = match(area);
  ASSERT_TRUE(area_verifier.firm);
  EXPECT_TRUE(area_search.firm);
}

}  // namespace
}  // namespace oxbow::index
