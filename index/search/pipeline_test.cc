// The search pipeline's stages over a scripted Source: what each stage does with the verifications it
// is given, without an index or images.
#include "index/search/pipeline.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <map>
#include <string>
#include <utility>
#include <vector>

namespace oxbow::index::search {
namespace {

// A source of a few images whose verifications are scripted: outcome[{geometry, image}], where the
// geometry is named by its first word (the query's features have word 1000 + i, an image's stored
// features word 2000 + 10 * image + i). Every image scores in image order; unscripted pairs do not
// verify.
class ScriptedSource final : public Source {
 public:
  struct Outcome {
    bool verified = false;
    bool firm = false;
    bool overlay = false;
    int inliers = 0;
  };

  explicit ScriptedSource(std::vector<std::string> ids) : ids_(std::move(ids)) {}
  std::map<std::pair<uint32_t, uint32_t>, Outcome> outcome;
  std::vector<std::pair<uint32_t, uint32_t>> verified_pairs;  // (geometry's first word, image) tried

  static constexpr int kSize = 100;

  Result<std::optional<ImageRef>> Find(const std::string& id) override {
    for (uint32_t i = 0; i < ids_.size(); ++i) {
      if (ids_[i] == id) return ImageRef{0, i};
    }
    return std::optional<ImageRef>{};
  }
  Result<ScoreOutput> Score(const ScoreInput& /*input*/, size_t max_results, const QueryOptions& /*options*/) override {
    ScoreOutput out;
    for (uint32_t i = 0; i < ids_.size() && out.best.size() < max_results; ++i) {
      out.best.push_back({ImageRef{0, i}, ids_[i], 1.0f - 0.01f * static_cast<float>(i)});
    }
    out.candidates = ids_.size();
    return out;
  }
  void Prefetch(std::span<const ScoredRef> /*refs*/) override {}
  Result<std::vector<double>> HammingScores(std::span<const uint32_t> /*words*/, std::span<const uint64_t> /*signatures*/,
                                            std::span<const ImageRef> refs, const QueryOptions& /*options*/) override {
    std::vector<double> scores;
    for (const ImageRef& r : refs) scores.push_back(1.0 - 0.01 * r.number);
    return scores;
  }
  Result<std::vector<Verified>> Verify(std::span<const GeometryQuery> geometries, std::span<const VerifyTask> tasks,
                                       const QueryOptions& /*options*/) override {
    std::vector<Verified> out(tasks.size());
    for (size_t t = 0; t < tasks.size(); ++t) {
      for (const uint32_t g : tasks[t].geometries) {
        const uint32_t name = geometries[g].words.empty() ? 0 : geometries[g].words[0];
        verified_pairs.emplace_back(name, tasks[t].ref.number);
        const auto it = outcome.find({name, tasks[t].ref.number});
        const Outcome o = it == outcome.end() ? Outcome{} : it->second;
        out[t].geometry = g;
        out[t].overlay = o.overlay;
        out[t].result = {};
        out[t].result.verified = o.verified;
        out[t].result.firm = o.firm;
        out[t].result.num_inliers = o.inliers;
        if (o.verified) out[t].result.db_region = {0, 0, kSize, kSize};
        if (o.verified) break;
      }
    }
    return out;
  }
  Result<std::vector<RegionFeatures>> Features(std::span<const ImageRef> refs,
                                               std::span<const std::array<float, 4>> /*regions*/,
                                               const FeaturesRequest& request) override {
    std::vector<RegionFeatures> out(refs.size());
    for (size_t i = 0; i < refs.size(); ++i) {
      for (uint32_t k = 0; k < 4; ++k) {
        out[i].keypoints.push_back({10.0f * static_cast<float>(k), 20, 2, 0, 1, 0});
        out[i].words.push_back(2000 + 10 * refs[i].number + k);
        if (request.signatures) out[i].signatures.push_back(k);
      }
      if (request.all_words) out[i].all_words = out[i].words;
    }
    return out;
  }
  Result<std::vector<std::vector<QueryTerm>>> RegionTerms(std::span<const ImageRef> refs,
                                                          std::span<const std::array<float, 4>> /*regions*/) override {
    return std::vector<std::vector<QueryTerm>>(refs.size());
  }
  Status RankAmong(std::span<const ImageRef> refs) override {
    ranked_ = refs.size();
    return Ok();
  }
  Result<std::vector<std::vector<float>>> ScoreAmong(std::span<const std::vector<uint32_t>> queries) override {
    // Every anchor's region scores every image of the ranking alike: each is among its neighbours.
    return std::vector<std::vector<float>>(queries.size(), std::vector<float>(ranked_, 0.5f));
  }
  Result<std::vector<ImageRecord>> Records(std::span<const ImageRef> refs) override {
    std::vector<ImageRecord> out(refs.size());
    for (size_t i = 0; i < refs.size(); ++i) out[i].id = ids_[refs[i].number];
    return out;
  }

 private:
  std::vector<std::string> ids_;
  size_t ranked_ = 0;
};

QueryFeatures Query() {
  QueryFeatures q;
  for (uint32_t k = 0; k < 4; ++k) {
    q.keypoints.push_back({10.0f * static_cast<float>(k), 20, 2, 0, 1, 0});
    q.words.push_back(1000 + k);
    q.signatures.push_back(k);
  }
  q.width = q.height = ScriptedSource::kSize;
  return q;
}

QueryOptions Options() {
  QueryOptions options;
  options.top_k = 10;
  options.query_expansion = false;
  return options;
}

// "copy" is the query's own photo (verified firmly: an anchor); "logo" shares only a pasted logo with the
// query (its verified match, 70 inliers, is rejected as an overlay) and "far" shares nothing the query's
// verification finds. Against copy's region both verify: far is another view of the query's content and
// is verified through copy, while logo, whose only match with the query was an overlay, is not: a chain
// does not make the content beside a shared overlay match the query. A match rejected as an overlay on a
// few inliers (an uncertain judgment) or not verified at all does not keep an image from a chain.
TEST(PipelineTest, TransitiveVerificationDoesNotVerifyWhatTheQueryMatchedOnlyThroughAnOverlay) {
  constexpr uint32_t kQuery = 1000, kCopyRegion = 2000;
  enum : uint32_t { kCopy, kLogo, kFar, kOther };
  struct Case {
    const char* what;
    bool overlay;
    int inliers;  // of logo's match with the query
    bool blocked;
  };
  for (const Case& c : {Case{"an overlay on 70 inliers", true, 70, true}, Case{"an overlay on 30 inliers", true, 30, true},
                        Case{"an overlay on 29 inliers", true, 29, false}, Case{"too weak to verify", false, 3, false}}) {
    SCOPED_TRACE(std::string("logo's match with the query: ") + c.what);
    ScriptedSource source({"copy", "logo", "far", "other"});
    source.outcome[{kQuery, kCopy}] = {.verified = true, .firm = true, .inliers = 300};
    source.outcome[{kQuery, kLogo}] = {.overlay = c.overlay, .inliers = c.inliers};
    source.outcome[{kQuery, kFar}] = {.inliers = 3};
    source.outcome[{kCopyRegion, kLogo}] = {.verified = true, .firm = true, .inliers = 72};
    source.outcome[{kCopyRegion, kFar}] = {.verified = true, .firm = true, .inliers = 40};
    auto response = search::Run(source, Query(), Options(), {});
    ASSERT_TRUE(response) << response.error().ToString();
    std::map<std::string, QueryResult> by_id;
    for (const QueryResult& r : response->results) by_id[r.id] = r;
    ASSERT_EQ(by_id.size(), 4u);
    EXPECT_TRUE(by_id["copy"].verified);
    EXPECT_EQ(by_id["copy"].via, "");
    EXPECT_TRUE(by_id["far"].verified);
    EXPECT_EQ(by_id["far"].via, "copy");
    EXPECT_EQ(by_id["far"].inliers, 40);
    EXPECT_FALSE(by_id["other"].verified);
    // Unless blocked, logo is verified through copy as far is.
    EXPECT_EQ(by_id["logo"].verified, !c.blocked);
    EXPECT_EQ(by_id["logo"].via, c.blocked ? "" : "copy");
    EXPECT_EQ(by_id["logo"].inliers, c.blocked ? c.inliers : 72);
    // A blocked image is not even tried against an anchor.
    const bool tried = std::find(source.verified_pairs.begin(), source.verified_pairs.end(),
                                 std::pair{kCopyRegion, static_cast<uint32_t>(kLogo)}) != source.verified_pairs.end();
    EXPECT_EQ(tried, !c.blocked);
    EXPECT_EQ(response->results[0].id, "copy");
  }
}

}  // namespace
}  // namespace oxbow::index::search
