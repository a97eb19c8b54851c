// Pieces of k-means training (train.cc) shared with the distributed trainer (distributed_train.cc), so
// that both run the same seeding, assignment and acceptance code. Not part of the public API.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "vocab/search.h"
#include "vocab/vocabulary.h"

namespace oxbow::vocab::internal {

// k-means++ (D^2 sampling) over the rows of `sample` (m x dim, row-major) in their order; k x dim centroids.
std::vector<float> KMeansPlusPlus(const std::vector<float>& sample, int dim, size_t k, SplitMix64& rng, int threads);

// The assignment method `options` asks for, kAuto resolved by the vocabulary size.
AssignmentMethod ResolveAssignment(const TrainOptions& options);

// Nearest centroid of each of the n rows of `x` by `method` (never kAuto) into `out` (n entries). A row's
// result depends on the row, the centroids and `iteration_seed` only, not on n or the thread count
// (except kKdForest, see train.cc).
void Assign(AssignmentMethod method, const std::vector<float>& centroids, size_t k, const float* x, size_t n, int dim,
            const TrainOptions& options, uint64_t iteration_seed, int threads, std::vector<uint32_t>& out);

// Takes the proposed words into `assign` with their exact squared distances into `dist`; with an
// approximate method (after the first iteration) a row keeps its previous word when that is not farther.
// Returns how many rows changed word (every row in the first iteration).
uint64_t AcceptAssignments(bool approximate, bool first_iteration, const std::vector<float>& centroids, const float* x,
                           size_t n, int dim, int threads, const std::vector<uint32_t>& proposal,
                           std::vector<uint32_t>& assign, std::vector<float>& dist);

}  // namespace oxbow::vocab::internal
