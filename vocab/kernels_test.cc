#include "vocab/kernels.h"

#include <gtest/gtest.h>

#include "vocab/kbest.h"

#include <cmath>
#include <cstring>
#include <random>
#include <vector>

namespace oxbow::vocab::internal {
namespace {

std::vector<float> RandomRows(size_t n, int dim, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-1.f, 1.f);
  std::vector<float> v(n * dim);
  for (auto& x : v) x = u(rng);
  return v;
}

// Panels of `w` (nw x dim) with their norms.
struct TestPanels {
  std::vector<float> data, norms;
  TestPanels(const std::vector<float>& w, size_t nw, int dim) {
    std::vector<float> row_norms(nw);
    RowSquaredNorms(w.data(), nw, dim, row_norms.data());
    data.resize(NumPanels(nw) * dim * kPanelWidth);
    norms.resize(NumPanels(nw) * kPanelWidth);
    MakePanels(w.data(), row_norms.data(), nw, dim, data.data(), norms.data());
  }
};

// The dot product's definition: one fused multiply-add per dimension, in increasing order from 0.
float SequentialScore(const float* q, const float* w, float norm, int dim) {
  float dot = 0;
  for (int d = 0; d < dim; ++d) dot = std::fma(q[d], w[d], dot);
  return norm - (dot + dot);
}

// The vector and scalar score paths must agree bit for bit with the definition, for every tile shape
// including the tails (query counts 1..13; word counts that fill 1 to 4 panels of 8 or 16, partly or
// wholly), and for dimensions that are not multiples of 8. Both vector paths where the AVX-512 one is
// chosen at run time (AllowAvx512; a native AVX-512 build has only that one).
TEST(KernelsTest, VectorAndScalarScoresAreIdentical) {
  if (!Avx2FmaAvailable()) GTEST_SKIP() << "built without AVX2+FMA: only the scalar path exists";
  struct Restore {
    ~Restore() { AllowAvx512(true); }
  } restore;
  for (const bool avx512 : {true, false}) {
    AllowAvx512(avx512);
    SCOPED_TRACE(Avx512Available() ? "AVX-512 path" : "AVX2 path");
    for (int dim : {1, 13, 128}) {
      for (size_t nq = 1; nq <= 13; ++nq) {
        for (size_t nw : {1, 2, 3, 5, 7, 8, 9, 15, 16, 17, 24, 31, 32, 33, 40, 47, 48, 49}) {
          const auto q = RandomRows(nq, dim, static_cast<uint32_t>(nq * 100 + nw));
          const auto w = RandomRows(nw, dim, static_cast<uint32_t>(nq * 1000 + nw));
          const TestPanels panels(w, nw, dim);
          std::vector<float> vec(nq * nw, -1.f), sca(nq * nw, -2.f);
          std::vector<int> calls(nq * nw, 0);
          auto all = [](size_t) { return INFINITY; };
          auto vsink = [&](size_t i, size_t j, float s) {
            ASSERT_LT(j, nw) << "a padded lane was reported";
            vec[i * nw + j] = s;
            ++calls[i * nw + j];
          };
          auto ssink = [&](size_t i, size_t j, float s) { sca[i * nw + j] = s; };
          ScorePanels(q.data(), nq, panels.data.data(), panels.norms.data(), nw, dim, all, vsink);
          ScorePanelsScalar(q.data(), nq, panels.data.data(), panels.norms.data(), nw, dim, all, ssink);
          for (size_t t = 0; t < nq * nw; ++t) {
            ASSERT_EQ(calls[t], 1) << "each pair scored once";
            ASSERT_EQ(vec[t], sca[t]) << "dim " << dim << " nq " << nq << " nw " << nw << " pair " << t;
            const size_t i = t / nw, j = t % nw;
            ASSERT_EQ(vec[t], SequentialScore(q.data() + i * dim, w.data() + j * dim, panels.norms[j], dim));
          }
        }
      }
    }
  }
}

// A pair is reported exactly when its score is <= the query's bound (the k-best filter): the bound
// set to a pair's own score keeps it, one ulp below drops it.
TEST(KernelsTest, BoundFiltersExactly) {
  const int dim = 128;
  const size_t nq = 7, nw = 19;
  const auto q = RandomRows(nq, dim, 11);
  const auto w = RandomRows(nw, dim, 12);
  const TestPanels panels(w, nw, dim);
  std::vector<float> score(nq * nw);
  auto all = [](size_t) { return INFINITY; };
  auto keep = [&](size_t i, size_t j, float s) { score[i * nw + j] = s; };
  ScorePanels(q.data(), nq, panels.data.data(), panels.norms.data(), nw, dim, all, keep);
  for (size_t target = 0; target < nw; ++target) {
    for (const bool below : {false, true}) {
      std::vector<float> bounds(nq);
      for (size_t i = 0; i < nq; ++i) {
        const float s = score[i * nw + target];
        bounds[i] = below ? std::nextafter(s, -INFINITY) : s;
      }
      auto bound = [&](size_t i) { return bounds[i]; };
      std::vector<int> reported(nq * nw, 0);
      auto count = [&](size_t i, size_t j, float) { ++reported[i * nw + j]; };
      ScorePanels(q.data(), nq, panels.data.data(), panels.norms.data(), nw, dim, bound, count);
      for (size_t i = 0; i < nq; ++i) {
        for (size_t j = 0; j < nw; ++j) {
          const bool expected = score[i * nw + j] <= bounds[i];
          ASSERT_EQ(reported[i * nw + j], expected ? 1 : 0) << "query " << i << " word " << j << " below " << below;
        }
      }
    }
  }
}

// The vector insertions into 8- and 16-slot k-best lists give InsertKBest's list after every insertion:
// streams of pairs with many equal scores (ties broken by row), into lists that start unfilled.
using InsertFn = void (*)(uint32_t*, float*, uint32_t, float);
void ExpectInsertionMatchesScalar(int k, InsertFn insert, const char* name) {
  std::mt19937 rng(3);
  for (int stream = 0; stream < 200; ++stream) {
    const int distinct = 1 + stream % 40;  // few distinct scores: many ties
    // Odd streams mix rows below and above 2^31 (rows are unsigned; the AVX2 insertion has only a signed
    // compare) and start from the largest row.
    const bool high = stream % 2 == 1;
    const uint32_t fill = high ? 0xFFFFFFFFu : 1000u;
    std::vector<uint32_t> rows_s(k, fill), rows_v(k, fill);
    std::vector<float> scores_s(k, INFINITY), scores_v(k, INFINITY);
    for (int n = 0; n < 300; ++n) {
      const auto row = static_cast<uint32_t>(rng() % 1000) + (high && rng() % 2 == 0 ? 0x80000000u : 0u);
      const float score = static_cast<float>(rng() % distinct) - 20.5f;
      InsertKBest(rows_s.data(), scores_s.data(), k, row, score);
      insert(rows_v.data(), scores_v.data(), row, score);
      ASSERT_EQ(rows_v, rows_s) << name << " stream " << stream << " insertion " << n;
      ASSERT_EQ(0, std::memcmp(scores_v.data(), scores_s.data(), sizeof(float) * k)) << name << " stream " << stream;
    }
  }
}

// WithKBestInsert gives InsertKBest's lists for k = 8 and 16, where it takes a vector insertion, and for
// other k.
void ExpectWithKBestInsertMatchesScalar() {
  std::mt19937 rng(4);
  for (const int k : {1, 3, 8, 16}) {
    std::vector<uint32_t> rows_s(k, 1000), rows_v(k, 1000);
    std::vector<float> scores_s(k, INFINITY), scores_v(k, INFINITY);
    for (int n = 0; n < 500; ++n) {
      const auto row = static_cast<uint32_t>(rng() % 1000);
      const float score = static_cast<float>(rng() % 50);
      InsertKBest(rows_s.data(), scores_s.data(), k, row, score);
      WithKBestInsert(k, [&](auto insert) { insert(rows_v.data(), scores_v.data(), row, score); });
    }
    EXPECT_EQ(rows_v, rows_s) << "k " << k;
    EXPECT_EQ(scores_v, scores_s) << "k " << k;
  }
}

TEST(KernelsTest, VectorKBestInsertionMatchesScalar) {
  int checked = 0;
#ifdef OXBOW_AVX512
  if (Avx512Available()) {
    ExpectInsertionMatchesScalar(16, InsertKBest16, "AVX-512, k 16");
    ExpectInsertionMatchesScalar(8, InsertKBest8, "AVX-512, k 8");
    checked += 2;
  }
#endif
#if defined(OXBOW_AVX2) && !defined(OXBOW_AVX512_ALWAYS)
  if (Avx2FmaAvailable()) {
    ExpectInsertionMatchesScalar(16, InsertKBest16Avx2, "AVX2, k 16");
    ExpectInsertionMatchesScalar(8, InsertKBest8Avx2, "AVX2, k 8");
    checked += 2;
  }
#endif
  // WithKBestInsert on every path this build can take here: AVX-512, then AVX2 where AllowAvx512(false)
  // turns it off, then the scalar insertion.
  ExpectWithKBestInsertMatchesScalar();
  {
    AllowAvx512(false);
    struct Restore {
      ~Restore() { AllowAvx512(true); }
    } restore;
    ExpectWithKBestInsertMatchesScalar();
  }
  if (checked == 0) GTEST_SKIP() << "no vector insertion can run in this build on this CPU: only the scalar one was checked";
}

TEST(KernelsTest, ScoreOrdersLikeSquaredDistance) {
  const int dim = 128;
  const auto q = RandomRows(1, dim, 7);
  const auto w = RandomRows(50, dim, 8);
  const TestPanels panels(w, 50, dim);
  const float qn = DotScalar(q.data(), q.data(), dim);
  int calls = 0;
  auto all = [](size_t) { return INFINITY; };
  auto sink = [&](size_t, size_t j, float s) {
    ++calls;
    double exact = 0;
    for (int d = 0; d < dim; ++d) exact += double(q[d] - w[j * dim + d]) * double(q[d] - w[j * dim + d]);
    EXPECT_NEAR(s + qn, exact, 1e-3 * exact);
    EXPECT_NEAR(SquaredL2(q.data(), w.data() + j * dim, dim), exact, 1e-5 * exact);
    EXPECT_NEAR(SquaredL2Scalar(q.data(), w.data() + j * dim, dim), exact, 1e-5 * exact);
  };
  ScorePanels(q.data(), 1, panels.data.data(), panels.norms.data(), 50, dim, all, sink);
  EXPECT_EQ(calls, 50);
}

}  // namespace
}  // namespace oxbow::vocab::internal
