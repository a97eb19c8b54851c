// The service over a real index: a small vocabulary trained here on opencv-doc photos, then adds,
// searches, replace semantics, errors and limits, without HTTP.
#include <gtest/gtest.h>

#include <filesystem>
#include <utility>

#include "api/json.h"
#include "api/service.h"
#include "tests/support/feature_eval.h"
#include "tests/support/samples.h"
#include "tests/support/temp_dir.h"

namespace oxbow::api {
namespace {

using testing::ReadBytes;
using testing::SamplePath;

class ServiceTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    if (!std::filesystem::exists(SamplePath("box_in_scene.png"))) return;
    dir_ = new oxbow::testing::TempDir("oxbow-service-test");
    vocab_path_ = dir_->path() + "/vocab.oxvoc";
    auto vocabulary = testing::BuildTestVocabulary({"box_in_scene.png", "graf1.png", "leuvenA.jpg", "graf3.png"}, 512, vocab_path_);
    ASSERT_TRUE(vocabulary) << vocabulary.error().ToString();
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  void SetUp() override {
    if (dir_ == nullptr) GTEST_SKIP() << "opencv-doc sample photos not installed (scripts/install-deps.sh)";
  }
  std::unique_ptr<Service> OpenFresh(const ServiceOptions& options = {}) {
    const std::string index_dir = dir_->path() + "/index-" + std::to_string(counter_++);
    auto service = Service::Open(index_dir, vocab_path_, options);
    EXPECT_TRUE(service) << service.error().ToString();
    return service ? std::move(*service) : nullptr;
  }
  Result<AddImageResponse> Add(Service& service, const std::string& id, const std::string& file, bool replace = false) {
    const auto bytes = ReadBytes(SamplePath(file));
    AddImageRequest request;
    request.id = id;
    request.image = bytes;
    request.metadata_json = R"({"file":")" + file + "\"}";
    request.replace = replace;
    return service.AddImage(request);
  }

  static inline oxbow::testing::TempDir* dir_ = nullptr;
  static inline std::string vocab_path_;
  static inline int counter_ = 0;
};

TEST_F(ServiceTest, OpenWithoutIndexOrVocabularyIsNotFound) {
  auto service = Service::Open(dir_->path() + "/missing", std::nullopt, {});
  ASSERT_FALSE(service);
  EXPECT_EQ(service.error().code, ErrorCode::kNotFound);
  EXPECT_NE(service.error().message.find("--vocab"), std::string::npos);
}

TEST_F(ServiceTest, AddSearchReplaceDelete) {
  auto service = OpenFresh();
  ASSERT_TRUE(service);
  auto added = Add(*service, "scene", "box_in_scene.png");
  ASSERT_TRUE(added) << added.error().ToString();
  EXPECT_EQ(added->record.width, 512);
  EXPECT_GT(added->record.num_features, 100u);
  EXPECT_FALSE(added->replaced);
  ASSERT_TRUE(Add(*service, "graf", "graf1.png"));
  ASSERT_TRUE(Add(*service, "leuven", "leuvenA.jpg"));

  auto again = Add(*service, "scene", "graf1.png");
  ASSERT_FALSE(again);
  EXPECT_EQ(again.error().code, ErrorCode::kAlreadyExists);

  const auto box = ReadBytes(SamplePath("box.png"));
  index::QueryOptions query;
  query.top_k = 3;
  auto found = service->Search(box, query);
  ASSERT_TRUE(found) << found.error().ToString();
  ASSERT_FALSE(found->index.results.empty());
  EXPECT_EQ(found->index.results[0].id, "scene");
  EXPECT_TRUE(found->index.results[0].verified);
  EXPECT_GE(found->index.results[0].inliers, 6);
  EXPECT_EQ(found->query_width, 324);
  EXPECT_GT(found->decode_extract_ms, 0);
  const auto json = SearchResponseToJson(*found);
  EXPECT_EQ(json["results"][0]["metadata"]["file"], "box_in_scene.png");

  auto similar = service->SearchSimilar("graf", query);
  ASSERT_TRUE(similar) << similar.error().ToString();
  ASSERT_FALSE(similar->index.results.empty());
  EXPECT_EQ(similar->index.results[0].id, "graf");
  EXPECT_FALSE(service->SearchSimilar("nope", query));

  auto replaced = Add(*service, "scene", "graf3.png", /*replace=*/true);
  ASSERT_TRUE(replaced) << replaced.error().ToString();
  EXPECT_TRUE(replaced->replaced);
  EXPECT_EQ(replaced->record.width, 800);
  EXPECT_EQ(service->GetImage("scene")->width, 800);

  auto list = service->ListImages(0, 2);
  ASSERT_TRUE(list);
  EXPECT_EQ(list->total, 3u);
  ASSERT_EQ(list->images.size(), 2u);
  EXPECT_EQ(list->images[0].id, "graf");

  ASSERT_TRUE(service->DeleteImage("graf"));
  EXPECT_EQ(service->DeleteImage("graf").error().code, ErrorCode::kNotFound);
  EXPECT_EQ(service->GetImage("graf").error().code, ErrorCode::kNotFound);
  EXPECT_EQ(service->Stats().index.num_images, 2u);
  EXPECT_GT(service->Stats().rss_bytes, 0u);
}

TEST_F(ServiceTest, BadImagesAreErrorValues) {
  ServiceOptions options;
  options.max_pixels = 100'000;  // box_in_scene (512 x 384 = 196608) is over it, box (324 x 223) under
  auto service = OpenFresh(options);
  ASSERT_TRUE(service);
  const std::vector<uint8_t> garbage = {'n', 'o', 't', ' ', 'a', 'n', ' ', 'i', 'm', 'a', 'g', 'e'};
  auto bad = service->Search(garbage, {});
  ASSERT_FALSE(bad);
  EXPECT_EQ(bad.error().code, ErrorCode::kInvalidImage);

  auto big = Add(*service, "big", "box_in_scene.png");
  ASSERT_FALSE(big);
  EXPECT_EQ(big.error().code, ErrorCode::kImageTooLarge);
  EXPECT_FALSE(service->index().Contains("big"));

  auto truncated = ReadBytes(SamplePath("box.png"));
  truncated.resize(truncated.size() / 2);
  AddImageRequest request;
  request.id = "half";
  request.image = truncated;
  auto half = service->AddImage(request);
  ASSERT_FALSE(half);
  EXPECT_EQ(half.error().code, ErrorCode::kInvalidImage);
}

TEST_F(ServiceTest, MatchFindsTheBoxInTheScene) {
  auto service = OpenFresh();
  ASSERT_TRUE(service);
  const auto box = ReadBytes(SamplePath("box.png"));
  const auto scene = ReadBytes(SamplePath("box_in_scene.png"));
  const auto graf = ReadBytes(SamplePath("graf1.png"));
  PairMatchOptions options;
  auto match = service->Match(box, scene, options);
  ASSERT_TRUE(match) << match.error().ToString();
  EXPECT_TRUE(match->match.verified);
  EXPECT_GE(match->match.inliers.size(), 10u);
  EXPECT_EQ(match->match.width_b, 512);
  // The box occupies the lower-left part of the scene: the matched region lies inside the scene.
  ASSERT_TRUE(match->match.region);
  EXPECT_GT((*match->match.region)[2], (*match->match.region)[0]);
  EXPECT_LE((*match->match.region)[2], 512.f);

  auto unrelated = service->Match(box, graf, options);
  ASSERT_TRUE(unrelated) << unrelated.error().ToString();
  EXPECT_FALSE(unrelated->match.verified) << unrelated->match.inliers.size() << " inliers between the box and graf1";
  EXPECT_LT(unrelated->match.inliers.size(), match->match.inliers.size());

  options.model = sift::GeometricModel::kHomography;
  auto homography = service->Match(box, scene, options);
  ASSERT_TRUE(homography) << homography.error().ToString();
  EXPECT_TRUE(homography->match.verified);

  const std::vector<uint8_t> empty;
  auto bad = service->Match(box, empty, options);
  ASSERT_FALSE(bad);
  EXPECT_NE(bad.error().message.find("image b"), std::string::npos);
}

// POST /v1/match's homography on graf1 -> graf3 against the true one (H1to3p.xml): the mean distance
// between where the two send graf1's corners (the HPatches corner error) stays within the bound of
// pair_match_accuracy_benchmark (OpenCV's 1.01 px + 0.5). The index's extractor settings unchanged
// (no refinement in scale) give 3.44 px here; the pair-matching extractor (PairMatchExtractorOptions)
// gives 1.04.
TEST_F(ServiceTest, MatchHomographyOfGrafIsNearTheTrueOne) {
  // A server whose vocabulary was made with the default extractor settings, as `oxbow vocab train`'s.
  const std::string vocab = dir_->path() + "/default-extractor.oxvoc";
  ASSERT_TRUE(oxbow::testing::BuildTestVocabulary({"box.png"}, 32, vocab, sift::SiftOptions{}));
  auto opened = Service::Open(dir_->path() + "/default-extractor", vocab, ServiceOptions{});
  ASSERT_TRUE(opened) << opened.error().ToString();
  const std::unique_ptr<Service> service = std::move(*opened);
  auto truth = sift::ReadHomography(SamplePath("H1to3p.xml"));
  ASSERT_TRUE(truth) << truth.error().ToString();
  auto match = service->Match(ReadBytes(SamplePath("graf1.png")), ReadBytes(SamplePath("graf3.png")), PairMatchOptions{});
  ASSERT_TRUE(match) << match.error().ToString();
  ASSERT_TRUE(match->match.verified);
  ASSERT_TRUE(match->match.transform);
  sift::Homography found;
  for (int i = 0; i < 9; ++i) found[static_cast<size_t>(i)] = (*match->match.transform)(i / 3, i % 3);
  EXPECT_LT(sift::CornerErrorOf(found, *truth, match->match.width_a, match->match.height_a).mean_px, 1.51)
      << "mean corner error, px";
}

TEST_F(ServiceTest, ReopensWithItsOwnVocabularyAndRefusesAnother) {
  const std::string index_dir = dir_->path() + "/reopen";
  {
    auto service = Service::Open(index_dir, vocab_path_, {});
    ASSERT_TRUE(service) << service.error().ToString();
    ASSERT_TRUE(Add(**service, "scene", "box_in_scene.png"));
  }
  auto reopened = Service::Open(index_dir, std::nullopt, {});
  ASSERT_TRUE(reopened) << reopened.error().ToString();
  EXPECT_TRUE((*reopened)->index().Contains("scene"));
  reopened->reset();

  const std::string other_path = dir_->path() + "/other.oxvoc";
  ASSERT_TRUE(testing::BuildTestVocabulary({"graf1.png"}, 16, other_path));
  auto mismatched = Service::Open(index_dir, other_path, {});
  ASSERT_FALSE(mismatched);
  EXPECT_EQ(mismatched.error().code, ErrorCode::kIncompatible);
}

}  // namespace
}  // namespace oxbow::api
