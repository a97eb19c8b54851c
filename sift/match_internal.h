// Internals of match.cc exposed for tests and benchmarks only; not part of the public API.
#pragma once

#include <vector>

#include "sift/base/error.h"
#include "sift/match.h"
#include "sift/types.h"

namespace oxbow::sift::internal {

// Which dot-product kernel the exact matcher uses. kAuto is AVX2+FMA when compiled with __AVX2__ and
// __FMA__, else the scalar kernel. Both accumulate every dot product with fused multiply-adds in the same
// order (dimension 0 to 127), so they give bit-identical results; match_test checks this.
enum class DotKernel { kAuto, kScalar };

// True when kAuto means the AVX2 kernel in this build.
bool HaveAvx2Kernel();

// MatchDescriptors with a chosen kernel (only used for kBruteForce).
Result<std::vector<Match>> MatchDescriptorsWithKernel(const FeatureSet& query, const FeatureSet& db,
                                                      const MatchOptions& options, DotKernel kernel);

}  // namespace oxbow::sift::internal
