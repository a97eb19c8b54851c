// Internal entry points of the SIFT extractor, for tests that compare the vectorised and scalar paths.
// Not part of the public API.
#pragma once

#include "sift/image.h"
#include "sift/sift.h"
#include "sift/types.h"

namespace oxbow::sift::internal {

// SiftExtractor::Extract with the AVX2 paths switched on or off (`allow_simd` = false forces the scalar
// formulas everywhere). Both give bit-identical output. `options` must pass Check().
FeatureSet ExtractImpl(const GrayImage& image, const SiftOptions& options, bool allow_simd);

}  // namespace oxbow::sift::internal
