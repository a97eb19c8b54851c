#include "vocab/kernels.h"

#include <gtest/gtest.h>

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

// The vector and scalar score paths must agree bit for bit (same formula), for every tile shape
// including the tails (query counts 1..9, word counts 1..8).
TEST(KernelsTest, VectorAndScalarScoresAreIdentical) {
  for (int dim : {8, 16, 128}) {
    if (!VectorPathAvailable(dim)) GTEST_SKIP() << "built without AVX2+FMA: only the scalar path exists";
    for (size_t nq = 1; nq <= 9; ++nq) {
      for (size_t nw = 1; nw <= 8; ++nw) {
        const auto q = RandomRows(nq, dim, static_cast<uint32_t>(nq * 100 + nw));
        const auto w = RandomRows(nw, dim, static_cast<uint32_t>(nq * 1000 + nw));
        std::vector<float> norms(nw);
        RowSquaredNorms(w.data(), nw, dim, norms.data());
        std::vector<const float*> ptrs(nq);
        for (size_t i = 0; i < nq; ++i) ptrs[i] = q.data() + i * dim;
        std::vector<float> vec(nq * nw, -1.f), sca(nq * nw, -2.f);
        std::vector<int> calls(nq * nw, 0);
        auto vsink = [&](size_t i, size_t j, float s) { vec[i * nw + j] = s; ++calls[i * nw + j]; };
        auto ssink = [&](size_t i, size_t j, float s) { sca[i * nw + j] = s; };
        ScoreBlock(ptrs.data(), nq, w.data(), norms.data(), nw, dim, vsink);
        ScoreBlockScalar(ptrs.data(), nq, w.data(), norms.data(), nw, dim, ssink);
        for (size_t t = 0; t < nq * nw; ++t) {
          ASSERT_EQ(calls[t], 1) << "each pair scored once";
          ASSERT_EQ(vec[t], sca[t]) << "dim " << dim << " nq " << nq << " nw " << nw << " pair " << t;
        }
      }
    }
  }
}

TEST(KernelsTest, ScoreOrdersLikeSquaredDistance) {
  const int dim = 128;
  const auto q = RandomRows(1, dim, 7);
  const auto w = RandomRows(50, dim, 8);
  std::vector<float> norms(50);
  RowSquaredNorms(w.data(), 50, dim, norms.data());
  const float qn = DotScalar(q.data(), q.data(), dim);
  const float* ptr = q.data();
  auto sink = [&](size_t, size_t j, float s) {
    double exact = 0;
    for (int d = 0; d < dim; ++d) exact += double(q[d] - w[j * dim + d]) * double(q[d] - w[j * dim + d]);
    EXPECT_NEAR(s + qn, exact, 1e-3 * exact);
    EXPECT_NEAR(SquaredL2(q.data(), w.data() + j * dim, dim), exact, 1e-5 * exact);
    EXPECT_NEAR(SquaredL2Scalar(q.data(), w.data() + j * dim, dim), exact, 1e-5 * exact);
  };
  ScoreBlock(&ptr, 1, w.data(), norms.data(), 50, dim, sink);
}

TEST(KernelsTest, OddDimensionUsesScalarPath) {
  const int dim = 13;
  const auto q = RandomRows(3, dim, 1);
  const auto w = RandomRows(5, dim, 2);
  std::vector<float> norms(5);
  RowSquaredNorms(w.data(), 5, dim, norms.data());
  std::vector<const float*> ptrs = {q.data(), q.data() + dim, q.data() + 2 * dim};
  int calls = 0;
  auto sink = [&](size_t i, size_t j, float s) {
    ++calls;
    EXPECT_FLOAT_EQ(s, norms[j] - 2 * DotScalar(ptrs[i], w.data() + j * dim, dim));
  };
  ScoreBlock(ptrs.data(), 3, w.data(), norms.data(), 5, dim, sink);
  EXPECT_EQ(calls, 15);
}

}  // namespace
}  // namespace oxbow::vocab::internal
