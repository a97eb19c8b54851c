// Filtered search at the index level (QueryOptions::filter): 300 images of which a filter keeps 3 (1%),
// all 297 others scoring higher by tf-idf and by inliers. The filter applies while scoring, so the 3
// are found even when re-ranking looks at fewer candidates than there are better disallowed images.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <memory>
#include <numeric>
#include <random>
#include <set>
#include <string>
#include <vector>

#include "index/image_index.h"
#include "tests/support/temp_dir.h"

namespace oxbow::index {
namespace {

namespace fs = std::filesystem;

constexpr int kDimension = 128;
constexpr uint32_t kVocabularyWords = 200;
constexpr uint32_t kQueryWords = 40;  // words 0..39 (with fixed positions); the rest are noise
constexpr int kImages = 300;
constexpr int kAllowed = 3;

const std::string kKeep = R"({"keep":true})";

class KeepFilter final : public ImageFilter {
 public:
  bool Matches(const ImageRecord& record) const override { return record.metadata_json == kKeep; }
};

class FilteredQueryTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::mt19937_64 rng(7);
    std::normal_distribution<float> normal(0, 1);
    centroids_.resize(static_cast<size_t>(kVocabularyWords) * kDimension);
    for (uint32_t w = 0; w < kVocabularyWords; ++w) {
      float* c = &centroids_[static_cast<size_t>(w) * kDimension];
      float norm = 0;
      for (int d = 0; d < kDimension; ++d) {
        c[d] = normal(rng);
        norm += c[d] * c[d];
      }
      for (int d = 0; d < kDimension; ++d) c[d] /= std::sqrt(norm);
    }
    auto vocabulary = vocab::Vocabulary::FromCentroids(centroids_, kDimension, sift::DescriptorKind::kRootSift, "t/1");
    ASSERT_TRUE(vocabulary) << vocabulary.error().message;
    auto index = ImageIndex::Create(dir_.string(), *vocabulary, "t/1");
    ASSERT_TRUE(index) << index.error().message;
    index_ = std::move(*index);
    std::uniform_real_distribution<float> x(10, 630), y(10, 470), scale(2, 10), angle(0, 6);
    for (uint32_t w = 0; w < kQueryWords; ++w) positions_.push_back({x(rng), y(rng), scale(rng), angle(rng), 1, 0});

    // Disallowed images hold a random 80% of the query's words at the query's positions, allowed ones
    // 50%: every disallowed image beats every allowed one. Each also has 20 noise features.
    std::uniform_int_distribution<uint32_t> noise(kQueryWords, kVocabularyWords - 1);
    for (int i = 0; i < kImages; ++i) {
      const bool allowed = i % (kImages / kAllowed) == 50;
      std::vector<uint32_t> words(kQueryWords);
      std::iota(words.begin(), words.end(), 0u);
      std::shuffle(words.begin(), words.end(), rng);
      words.resize(allowed ? kQueryWords / 2 : kQueryWords * 4 / 5);
      std::vector<sift::Keypoint> keypoints;
      keypoints.reserve(words.size() + 20);
      for (uint32_t w : words) keypoints.push_back(positions_[w]);
      for (int n = 0; n < 20; ++n) {
        words.push_back(noise(rng));
        keypoints.push_back({x(rng), y(rng), scale(rng), angle(rng), 1, 0});
      }
      ImageInfo info;
      info.metadata_json = allowed ? kKeep : R"({"keep":false})";
      const std::string id = (allowed ? "allowed-" : "other-") + std::to_string(i);
      if (allowed) allowed_ids_.insert(id);
      ASSERT_TRUE(index_->Add(id, Features(words, keypoints), info));
    }
    ASSERT_EQ(allowed_ids_.size(), static_cast<size_t>(kAllowed));
  }
  void TearDown() override { index_.reset(); }  // closed before its folder goes

  sift::FeatureSet Features(const std::vector<uint32_t>& words, const std::vector<sift::Keypoint>& keypoints) const {
    sift::FeatureSet f;
    f.image_width = 640;
    f.image_height = 480;
    f.kind = sift::DescriptorKind::kRootSift;
    f.keypoints = keypoints;
    for (uint32_t w : words) {
      const auto* c = &centroids_[static_cast<size_t>(w) * kDimension];
      f.descriptors.insert(f.descriptors.end(), c, c + kDimension);
    }
    return f;
  }

  sift::FeatureSet Query() const {
    std::vector<uint32_t> words(kQueryWords);
    std::iota(words.begin(), words.end(), 0u);
    return Features(words, positions_);
  }

  static std::set<std::string> Ids(const QueryResponse& response) {
    std::set<std::string> ids;
    for (const QueryResult& r : response.results) ids.insert(r.id);
    return ids;
  }

  oxbow::testing::TempDir temp_;
  fs::path dir_ = temp_ / "index";
  std::vector<float> centroids_;
  std::vector<sift::Keypoint> positions_;
  std::unique_ptr<ImageIndex> index_;
  std::set<std::string> allowed_ids_;
};

QueryOptions Options(int top_k, int rerank_depth, bool expansion, int transitive_depth) {
  QueryOptions o;
  o.top_k = top_k;
  o.rerank_depth = rerank_depth;
  o.query_expansion = expansion;
  o.transitive_depth = transitive_depth;
  return o;
}

TEST_F(FilteredQueryTest, WithoutFilterTheAllowedImagesAreOutranked) {
  const auto response = index_->Query(Query(), Options(20, 100, true, 200));
  ASSERT_TRUE(response) << response.error().message;
  ASSERT_EQ(response->results.size(), 20u);
  for (const QueryResult& r : response->results) EXPECT_EQ(allowed_ids_.count(r.id), 0u) << r.id;
}

TEST_F(FilteredQueryTest, FilterKeepsTheBestAllowedImagesAtEveryStage) {
  // tf-idf only; re-ranking shallower than the 297 better images; the full pipeline.
  for (const QueryOptions& base : {Options(10, 0, false, 0), Options(10, 5, false, 0), Options(10, 100, true, 200)}) {
    QueryOptions options = base;
    options.filter = std::make_shared<KeepFilter>();
    const auto response = index_->Query(Query(), options);
    ASSERT_TRUE(response) << response.error().message;
    EXPECT_EQ(Ids(*response), allowed_ids_) << "rerank " << base.rerank_depth;
    EXPECT_EQ(response->candidates, static_cast<uint64_t>(kAllowed));
    for (const QueryResult& r : response->results) {
      EXPECT_EQ(r.record.metadata_json, kKeep);
      EXPECT_EQ(r.verified, base.rerank_depth > 0) << r.id;
    }
  }
}

TEST_F(FilteredQueryTest, SimilarToADisallowedImageReturnsOnlyAllowedOnes) {
  QueryOptions options = Options(10, 100, true, 200);
  options.filter = std::make_shared<KeepFilter>();
  const auto response = index_->QuerySimilar("other-0", options);
  ASSERT_TRUE(response) << response.error().message;
  EXPECT_EQ(Ids(*response), allowed_ids_);
}

class NothingFilter final : public ImageFilter {
 public:
  bool Matches(const ImageRecord&) const override { return false; }
};

TEST_F(FilteredQueryTest, FilterMatchingNothingGivesNoResults) {
  QueryOptions options = Options(10, 100, true, 200);
  options.filter = std::make_shared<NothingFilter>();
  const auto response = index_->Query(Query(), options);
  ASSERT_TRUE(response) << response.error().message;
  EXPECT_TRUE(response->results.empty());
  EXPECT_EQ(response->candidates, 0u);
}

}  // namespace
}  // namespace oxbow::index
