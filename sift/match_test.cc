// Tests of descriptor matching: exactness against a naive reference, kernel agreement, ratio test,
// mutual and one-to-one properties, kd-forest recall and determinism, and bad input.
#include "sift/match.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <set>

#include "sift/match_internal.h"

namespace oxbow::sift {
namespace {

// A unit-norm non-negative descriptor (SIFT-like) from a seeded generator.
void RandomDescriptor(std::mt19937& rng, float* out) {
  std::exponential_distribution<float> value(4.0f);
  double norm = 0;
  for (int k = 0; k < kDescriptorDim; ++k) {
    out[k] = value(rng);
    norm += double(out[k]) * out[k];
  }
  for (int k = 0; k < kDescriptorDim; ++k) out[k] = static_cast<float>(out[k] / std::sqrt(norm));
}

FeatureSet RandomSet(size_t n, uint32_t seed, DescriptorKind kind = DescriptorKind::kSift) {
  std::mt19937 rng(seed);
  FeatureSet set;
  set.kind = kind;
  set.keypoints.resize(n);
  set.descriptors.resize(n * kDescriptorDim);
  for (size_t i = 0; i < n; ++i) RandomDescriptor(rng, set.descriptors.data() + i * kDescriptorDim);
  return set;
}

// Query features: noisy copies of db[perm[i]] for i < num_copies, then unrelated random descriptors.
FeatureSet NoisyCopies(const FeatureSet& db, const std::vector<uint32_t>& perm, size_t num_copies, size_t num_random,
                       float noise, uint32_t seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> gauss(0.0f, noise);
  FeatureSet q;
  q.kind = db.kind;
  q.keypoints.resize(num_copies + num_random);
  q.descriptors.resize(q.keypoints.size() * kDescriptorDim);
  for (size_t i = 0; i < num_copies; ++i) {
    float* out = q.descriptors.data() + i * kDescriptorDim;
    const float* in = db.descriptors.data() + size_t{perm[i]} * kDescriptorDim;
    double norm = 0;
    for (int k = 0; k < kDescriptorDim; ++k) {
      out[k] = std::max(0.0f, in[k] + gauss(rng));
      norm += double(out[k]) * out[k];
    }
    for (int k = 0; k < kDescriptorDim; ++k) out[k] = static_cast<float>(out[k] / std::sqrt(norm));
  }
  for (size_t i = num_copies; i < q.keypoints.size(); ++i) RandomDescriptor(rng, q.descriptors.data() + i * kDescriptorDim);
  return q;
}

double Distance(const FeatureSet& a, size_t i, const FeatureSet& b, size_t j) {
  double sum = 0;
  for (int k = 0; k < kDescriptorDim; ++k) {
    const double d = double(a.descriptors[i * kDescriptorDim + k]) - b.descriptors[j * kDescriptorDim + k];
    sum += d * d;
  }
  return std::sqrt(sum);
}

// Naive double-precision reference: nearest and second nearest distance of query i.
struct Reference {
  size_t nearest;
  double d1, d2;
};
Reference NaiveNearest(const FeatureSet& q, size_t i, const FeatureSet& db) {
  Reference r{0, std::numeric_limits<double>::infinity(), std::numeric_limits<double>::infinity()};
  for (size_t j = 0; j < db.size(); ++j) {
    const double d = Distance(q, i, db, j);
    if (d < r.d1) {
      r.d2 = r.d1;
      r.d1 = d;
      r.nearest = j;
    } else if (d < r.d2) {
      r.d2 = d;
    }
  }
  return r;
}

std::vector<uint32_t> Permutation(size_t n, uint32_t seed) {
  std::vector<uint32_t> perm(n);
  for (size_t i = 0; i < n; ++i) perm[i] = static_cast<uint32_t>(i);
  std::mt19937 rng(seed);
  std::shuffle(perm.begin(), perm.end(), rng);
  return perm;
}

TEST(MatchDescriptors, BruteForceAgreesWithNaiveReference) {
  const FeatureSet db = RandomSet(300, 1);
  const FeatureSet q = NoisyCopies(db, Permutation(300, 2), 150, 100, 0.03f, 3);
  MatchOptions options;
  options.ratio = 1.0f;  // every query gets its nearest neighbour
  options.one_to_one = false;
  auto matches = MatchDescriptors(q, db, options);
  ASSERT_TRUE(matches.has_value()) << matches.error().ToString();
  ASSERT_EQ(matches->size(), q.size());
  int same = 0;
  for (const Match& m : *matches) {
    const Reference ref = NaiveNearest(q, m.query_index, db);
    EXPECT_NEAR(m.distance, Distance(q, m.query_index, db, m.db_index), 1e-4);
    // A different index is only acceptable for a (near) tie.
    if (m.db_index == ref.nearest) {
      ++same;
    } else {
      EXPECT_NEAR(m.distance, ref.d1, 1e-4) << "query " << m.query_index;
    }
  }
  EXPECT_GE(same, static_cast<int>(q.size()) - 2);
}

TEST(MatchDescriptors, RatioTestKeepsExactlyTheDistinctiveMatches) {
  const FeatureSet db = RandomSet(400, 4);
  const std::vector<uint32_t> perm = Permutation(400, 5);
  const FeatureSet q = NoisyCopies(db, perm, 200, 200, 0.03f, 6);
  MatchOptions options;
  options.one_to_one = false;
  auto matches = MatchDescriptors(q, db, options);
  ASSERT_TRUE(matches.has_value());
  std::set<uint32_t> matched;
  for (const Match& m : *matches) matched.insert(m.query_index);
  for (size_t i = 0; i < q.size(); ++i) {
    const Reference ref = NaiveNearest(q, i, db);
    if (std::abs(ref.d1 - 0.8 * ref.d2) < 1e-4) continue;  // too close to the threshold to call
    EXPECT_EQ(matched.count(static_cast<uint32_t>(i)) == 1, ref.d1 < 0.8 * ref.d2) << "query " << i;
  }
  // The noisy copies are distinctive, the random queries are not.
  int correct = 0;
  for (const Match& m : *matches) correct += m.query_index < 200 && m.db_index == perm[m.query_index];
  EXPECT_GE(correct, 190);
  EXPECT_LE(matches->size(), 210u);
}

TEST(MatchDescriptors, ScalarAndVectorKernelsGiveIdenticalResults) {
  const FeatureSet db = RandomSet(517, 7);  // not a multiple of the 16-wide block
  const FeatureSet q = NoisyCopies(db, Permutation(517, 8), 203, 58, 0.1f, 9);  // nor of 4 or 64
  for (bool mutual : {false, true}) {
    MatchOptions options;
    options.ratio = 1.0f;
    options.mutual = mutual;
    options.one_to_one = false;
    auto a = internal::MatchDescriptorsWithKernel(q, db, options, internal::DotKernel::kAuto);
    auto b = internal::MatchDescriptorsWithKernel(q, db, options, internal::DotKernel::kScalar);
    ASSERT_TRUE(a.has_value() && b.has_value());
    ASSERT_EQ(a->size(), b->size());
    for (size_t i = 0; i < a->size(); ++i) {
      EXPECT_EQ((*a)[i], (*b)[i]) << "match " << i << " (bit-identical distances expected)";
    }
  }
  if (!internal::HaveAvx2Kernel()) GTEST_SKIP() << "built without AVX2+FMA: both runs used the scalar kernel";
}

TEST(MatchDescriptors, ResultDoesNotDependOnThreadCount) {
  const FeatureSet db = RandomSet(700, 10);
  const FeatureSet q = NoisyCopies(db, Permutation(700, 11), 400, 300, 0.08f, 12);
  for (auto method : {MatchOptions::Method::kBruteForce, MatchOptions::Method::kKdForest}) {
    MatchOptions options;
    options.method = method;
    options.mutual = true;
    options.num_threads = 1;
    auto one = MatchDescriptors(q, db, options);
    options.num_threads = 3;
    auto three = MatchDescriptors(q, db, options);
    auto again = MatchDescriptors(q, db, options);
    ASSERT_TRUE(one.has_value() && three.has_value() && again.has_value());
    EXPECT_FALSE(one->empty());
    EXPECT_EQ(*one, *three);
    EXPECT_EQ(*three, *again);
  }
}

TEST(MatchDescriptors, KdForestAgreesWithBruteForce) {
  for (DescriptorKind kind : {DescriptorKind::kSift, DescriptorKind::kRootSift}) {
    const FeatureSet db = RandomSet(2000, 13, kind);
    const FeatureSet q = NoisyCopies(db, Permutation(2000, 14), 1000, 500, 0.05f, 15);
    MatchOptions exact;
    auto a = MatchDescriptors(q, db, exact);
    MatchOptions approx;
    approx.method = MatchOptions::Method::kKdForest;
    approx.kd_checks = 128;
    auto b = MatchDescriptors(q, db, approx);
    ASSERT_TRUE(a.has_value() && b.has_value());
    ASSERT_GT(a->size(), 500u);
    std::set<std::pair<uint32_t, uint32_t>> exact_pairs;
    for (const Match& m : *a) exact_pairs.insert({m.query_index, m.db_index});
    size_t shared = 0;
    for (const Match& m : *b) shared += exact_pairs.count({m.query_index, m.db_index});
    EXPECT_GE(shared, a->size() * 9 / 10) << DescriptorKindName(kind);
    // Approximate search can only miss neighbours, so it cannot produce many matches the exact one lacks.
    EXPECT_LE(b->size() - shared, a->size() / 20) << DescriptorKindName(kind);
  }
}

TEST(MatchDescriptors, MutualMatchesAreNearestNeighboursBothWays) {
  const FeatureSet db = RandomSet(250, 16);
  const FeatureSet q = NoisyCopies(db, Permutation(250, 17), 120, 130, 0.12f, 18);
  MatchOptions options;
  options.mutual = true;
  options.ratio = 1.0f;
  options.one_to_one = false;
  auto matches = MatchDescriptors(q, db, options);
  ASSERT_TRUE(matches.has_value());
  ASSERT_FALSE(matches->empty());
  for (const Match& m : *matches) {
    EXPECT_EQ(NaiveNearest(q, m.query_index, db).nearest, m.db_index);
    EXPECT_EQ(NaiveNearest(db, m.db_index, q).nearest, m.query_index);
  }
  // And every mutual pair of the reference is found.
  size_t expected = 0;
  for (size_t i = 0; i < q.size(); ++i) {
    const size_t j = NaiveNearest(q, i, db).nearest;
    expected += NaiveNearest(db, j, q).nearest == i;
  }
  EXPECT_EQ(matches->size(), expected);
}

TEST(MatchDescriptors, OneToOneLeavesNoDbFeatureTwice) {
  // Many queries are noisy copies of the same few db descriptors: without one-to-one they collide.
  const FeatureSet db = RandomSet(20, 19);
  std::vector<uint32_t> perm(200);
  for (size_t i = 0; i < perm.size(); ++i) perm[i] = static_cast<uint32_t>(i % 10);
  const FeatureSet q = NoisyCopies(db, perm, 200, 0, 0.02f, 20);
  MatchOptions options;
  options.one_to_one = false;
  auto many = MatchDescriptors(q, db, options);
  options.one_to_one = true;
  auto unique = MatchDescriptors(q, db, options);
  ASSERT_TRUE(many.has_value() && unique.has_value());
  std::set<uint32_t> db_seen;
  for (const Match& m : *many) db_seen.insert(m.db_index);
  EXPECT_GT(many->size(), db_seen.size());  // collisions happened
  std::set<uint32_t> db_unique;
  for (const Match& m : *unique) EXPECT_TRUE(db_unique.insert(m.db_index).second) << "db " << m.db_index << " twice";
  EXPECT_EQ(unique->size(), db_seen.size());  // the best of each collision group survives
  for (const Match& kept : *unique) {
    for (const Match& m : *many) {
      if (m.db_index == kept.db_index) {
        EXPECT_LE(kept.distance, m.distance);
      }
    }
  }
}

TEST(EnforceOneToOne, KeepsBestPerFeatureWithDeterministicTies) {
  const std::vector<Match> matches = {
      {0, 5, 0.3f}, {1, 5, 0.2f}, {2, 5, 0.2f},  // db 5: tie between queries 1 and 2 -> query 1
      {1, 6, 0.1f},                               // query 1's best is db 6 (greedy: it goes first)
      {3, 7, 0.4f}, {3, 8, 0.4f},                 // query 3: tie between db 7 and 8 -> db 7
  };
  const std::vector<Match> kept = EnforceOneToOne(matches);
  const std::vector<Match> expected = {{1, 6, 0.1f}, {2, 5, 0.2f}, {3, 7, 0.4f}};
  EXPECT_EQ(kept, expected);
  std::vector<Match> reversed(matches.rbegin(), matches.rend());
  EXPECT_EQ(EnforceOneToOne(reversed), expected);  // input order does not matter
  EXPECT_TRUE(EnforceOneToOne({}).empty());
}

TEST(MatchDescriptors, SmallAndEmptySets) {
  const FeatureSet empty;
  const FeatureSet one = RandomSet(1, 21);
  const FeatureSet some = RandomSet(5, 22);
  for (auto method : {MatchOptions::Method::kBruteForce, MatchOptions::Method::kKdForest}) {
    MatchOptions options;
    options.method = method;
    auto a = MatchDescriptors(empty, some, options);
    auto b = MatchDescriptors(some, empty, options);
    auto c = MatchDescriptors(some, one, options);  // a ratio test needs two db features
    ASSERT_TRUE(a.has_value() && b.has_value() && c.has_value());
    EXPECT_TRUE(a->empty());
    EXPECT_TRUE(b->empty());
    EXPECT_TRUE(c->empty());
    options.ratio = 1.0f;
    options.one_to_one = false;
    auto d = MatchDescriptors(some, one, options);
    ASSERT_TRUE(d.has_value());
    EXPECT_EQ(d->size(), 5u);
  }
}

TEST(MatchDescriptors, RejectsBadInput) {
  const FeatureSet good = RandomSet(10, 23);
  FeatureSet short_descriptors = good;
  short_descriptors.descriptors.pop_back();
  FeatureSet nan = good;
  nan.descriptors[17] = std::numeric_limits<float>::quiet_NaN();
  FeatureSet root = RandomSet(10, 24, DescriptorKind::kRootSift);
  EXPECT_EQ(MatchDescriptors(short_descriptors, good).error().code, ErrorCode::kInvalidArgument);
  EXPECT_EQ(MatchDescriptors(good, nan).error().code, ErrorCode::kInvalidArgument);
  EXPECT_EQ(MatchDescriptors(good, root).error().code, ErrorCode::kInvalidArgument);
  for (auto bad : {MatchOptions{.ratio = 0.0f}, MatchOptions{.ratio = 1.5f}, MatchOptions{.kd_trees = 0},
                   MatchOptions{.kd_checks = 0}, MatchOptions{.num_threads = -1}}) {
    EXPECT_TRUE(bad.Check().has_value());
    auto result = MatchDescriptors(good, good, bad);
    ASSERT_FALSE(result.has_value());
    EXPECT_EQ(result.error().code, ErrorCode::kInvalidArgument);
  }
  EXPECT_FALSE(MatchOptions{}.Check().has_value());
}

}  // namespace
}  // namespace oxbow::sift
