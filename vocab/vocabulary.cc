#include "vocab/vocabulary.h"

namespace oxbow::vocab {

struct Vocabulary::State {
  std::vector<float> centroids;
  int dimension = 0;
  sift::DescriptorKind kind = sift::DescriptorKind::kSift;
  std::string settings;
  uint64_t fingerprint = 0;
  size_t num_lists = 0;
};

std::optional<std::string> QuantizerOptions::Check() const { return std::nullopt; }
std::optional<std::string> QuantizerBuildOptions::Check() const { return std::nullopt; }
std::optional<std::string> TrainOptions::Check() const { return std::nullopt; }
std::optional<std::string> SampleOptions::Check() const { return std::nullopt; }

Result<Vocabulary> Vocabulary::Read(const std::string&) { return Fail(ErrorCode::kInternal, "not implemented"); }
Result<Vocabulary> Vocabulary::FromCentroids(std::vector<float>, int, sift::DescriptorKind, std::string,
                                             const QuantizerBuildOptions&) {
  return Fail(ErrorCode::kInternal, "not implemented");
}
Status Vocabulary::Write(const std::string&) const { return Fail(ErrorCode::kInternal, "not implemented"); }
size_t Vocabulary::size() const { return state_->centroids.size() / state_->dimension; }
int Vocabulary::dimension() const { return state_->dimension; }
sift::DescriptorKind Vocabulary::descriptor_kind() const { return state_->kind; }
const std::string& Vocabulary::extractor_settings() const { return state_->settings; }
uint64_t Vocabulary::fingerprint() const { return state_->fingerprint; }
std::span<const float> Vocabulary::centroids() const { return state_->centroids; }
size_t Vocabulary::num_lists() const { return state_->num_lists; }
void Vocabulary::Quantize(std::span<const float>, std::span<uint32_t>, const QuantizerOptions&) const {}
void Vocabulary::QuantizeMulti(std::span<const float>, int, std::span<uint32_t>, std::span<float>,
                               const QuantizerOptions&) const {}

Result<Vocabulary> Train(std::span<const float>, int, sift::DescriptorKind, std::string, const TrainOptions&,
                         TrainReport*) {
  return Fail(ErrorCode::kInternal, "not implemented");
}

DescriptorSampler::DescriptorSampler(const SampleOptions& options, int dimension)
    : options_(options), dimension_(dimension), rng_state_(options.seed) {}
void DescriptorSampler::AddImage(std::span<const float>) {}

}  // namespace oxbow::vocab
