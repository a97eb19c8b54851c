// Seeded two-stage descriptor sampling (see DescriptorSampler in vocabulary.h).
#include <algorithm>
#include <numeric>

#include "vocab/search.h"
#include "vocab/vocabulary.h"

namespace oxbow::vocab {

std::optional<std::string> SampleOptions::Check() const {
  if (max_per_image < 1) return "SampleOptions.max_per_image must be >= 1";
  if (max_total < 1) return "SampleOptions.max_total must be >= 1";
  return std::nullopt;
}

DescriptorSampler::DescriptorSampler(const SampleOptions& options, int dimension)
    : options_(options), dimension_(dimension), rng_state_(options.seed) {
  auto problem = options.Check();
  OXBOW_CHECK(!problem, "invalid SampleOptions");
  OXBOW_CHECK(dimension > 0, "dimension must be positive");
}

void DescriptorSampler::AddImage(std::span<const float> descriptors) {
  OXBOW_CHECK(descriptors.size() % dimension_ == 0, "descriptor buffer is not a multiple of the dimension");
  const size_t rows = descriptors.size() / dimension_;
  ++images_;
  internal::SplitMix64 rng(rng_state_);
  // Stage 1: a uniform subset of at most max_per_image rows (partial Fisher-Yates), kept in row order.
  std::vector<uint32_t> pick(rows);
  std::iota(pick.begin(), pick.end(), 0u);
  const size_t keep = std::min(rows, options_.max_per_image);
  if (keep < rows) {
    for (size_t i = 0; i < keep; ++i) std::swap(pick[i], pick[i + rng.Below(rows - i)]);
    pick.resize(keep);
    std::sort(pick.begin(), pick.end());
  }
  // Stage 2: reservoir sampling (algorithm R) of at most max_total rows over all images.
  const size_t dim = static_cast<size_t>(dimension_);
  for (uint32_t r : pick) {
    ++seen_;
    const float* row = descriptors.data() + r * dim;
    if (rows_ < options_.max_total) {
      data_.insert(data_.end(), row, row + dim);
      ++rows_;
    } else {
      const uint64_t slot = rng.Below(seen_);
      if (slot < options_.max_total) std::copy_n(row, dim, data_.data() + slot * dim);
    }
  }
  rng_state_ = rng.state;
}

}  // namespace oxbow::vocab
