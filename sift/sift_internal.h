// Internal entry points of the SIFT extractor, for tests that compare the vectorised and scalar paths.
// Not part of the public API.
#pragma once

#include "sift/image.h"
#include "sift/sift.h"
#include "sift/types.h"

namespace oxbow::sift::internal {

// SiftExtractor::Extract with the AVX2 paths switched on or off (`allow_simd` = false forces the scalar
// formulas everywhere). Both give bit-identical output. `options` must pass Check(). When `stop` (may be
// empty) turns true the extraction returns early with what it has: the caller discards that (stop is
// monotonic, so asking it again tells).
FeatureSet ExtractImpl(const GrayImage& image, const SiftOptions& options, bool allow_simd, const StopRequested& stop = {});

}  // namespace oxbow::sift::internal
