// Random unit vectors for tests of vocabularies and Hamming embedding: directions drawn uniformly on the
// sphere (normalised Gaussian rows), reproducible from a seed. Header-only, the standard library only.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <random>
#include <vector>

namespace oxbow::testing {

// `rows` unit vectors of `dim` floats, row after row.
inline std::vector<float> RandomUnitRows(size_t rows, int dim, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<float> g(0, 1);
  const auto d = static_cast<size_t>(dim);
  std::vector<float> out(rows * d);
  for (size_t r = 0; r < rows; ++r) {
    double norm2 = 0;
    for (size_t k = 0; k < d; ++k) norm2 += std::pow(out[r * d + k] = g(rng), 2);
    for (size_t k = 0; k < d; ++k) out[r * d + k] /= static_cast<float>(std::sqrt(norm2));
  }
  return out;
}

}  // namespace oxbow::testing
