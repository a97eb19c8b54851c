#include "api/duplicates.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <map>
#include <string>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "api/service.h"
#include "sift/sift.h"
#include "tests/support/samples.h"
#include "tests/support/temp_dir.h"
#include "vocab/vocabulary.h"

namespace oxbow::api {
namespace {

using testing::SamplePath;

std::vector<uint8_t> Png(const cv::Mat& image) {
  std::vector<uchar> png;
  EXPECT_TRUE(cv::imencode(".png", image, png));
  return {png.begin(), png.end()};
}

// Adds every image to the service's index as a PNG under its id.
void AddImages(Service& service, const std::map<std::string, cv::Mat>& images) {
  for (const auto& [id, image] : images) {
    const auto bytes = Png(image);
    AddImageRequest request;
    request.id = id;
    request.image = bytes;
    auto added = service.AddImage(request);
    ASSERT_TRUE(added) << id << ": " << added.error().ToString();
  }
}

// The sample photo `photo` shown in a frame (graf1.png, a photo viewer's window): resized into the
// frame's central half.
cv::Mat Framed(const char* photo) {
  cv::Mat out = cv::imread(SamplePath("graf1.png"), cv::IMREAD_COLOR), inner;
  const cv::Rect window(out.cols / 4, out.rows / 4, out.cols / 2, out.rows / 2);
  cv::resize(cv::imread(SamplePath(photo), cv::IMREAD_COLOR), inner, window.size(), 0, 0, cv::INTER_AREA);
  inner.copyTo(out(window));
  return out;
}

// The report's pairs by (a, b).
std::map<std::pair<std::string, std::string>, DuplicatePair> PairsOf(const DuplicateReport& report) {
  std::map<std::pair<std::string, std::string>, DuplicatePair> pairs;
  for (const auto& p : report.pairs) pairs[{p.a, p.b}] = p;
  return pairs;
}

float Distance(const float* a, const float* b) {
  float sum = 0;
  for (int i = 0; i < sift::kDescriptorDim; ++i) sum += (a[i] - b[i]) * (a[i] - b[i]);
  return std::sqrt(sum);
}

// A keypoint of the mirrored image at the mirrored place and scale has the mirrored descriptor.
TEST(MirrorDescriptorTest, MatchesTheDescriptorOfTheMirroredImage) {
  if (!std::filesystem::exists(SamplePath("graf1.png"))) GTEST_SKIP() << "opencv-doc sample photos not installed";
  const cv::Mat image = cv::imread(SamplePath("graf1.png"), cv::IMREAD_COLOR);
  cv::Mat flipped;
  cv::flip(image, flipped, 1);
  auto extractor = sift::SiftExtractor::Create(testing::TestSiftOptions());
  ASSERT_TRUE(extractor);
  auto a = extractor->ExtractFromBytes(Png(image));
  auto b = extractor->ExtractFromBytes(Png(flipped));
  ASSERT_TRUE(a && b);
  const int width = image.cols;
  int pairs = 0, closer = 0;
  std::vector<float> mirrored(sift::kDescriptorDim);
  for (size_t i = 0; i < a->keypoints.size(); ++i) {
    const auto& p = a->keypoints[i];
    for (size_t j = 0; j < b->keypoints.size(); ++j) {
      const auto& q = b->keypoints[j];
      if (std::abs(q.x - (width - 1 - p.x)) > 0.5f || std::abs(q.y - p.y) > 0.5f || std::abs(q.scale / p.scale - 1) > 0.05f) {
        continue;
      }
      const float* da = a->descriptors.data() + i * sift::kDescriptorDim;
      const float* db = b->descriptors.data() + j * sift::kDescriptorDim;
      MirrorDescriptor(da, mirrored.data());
      ++pairs;
      if (Distance(mirrored.data(), db) < 0.5f * Distance(da, db)) ++closer;
      break;
    }
  }
  ASSERT_GT(pairs, 100);
  EXPECT_GT(closer, pairs * 8 / 10) << closer << " of " << pairs;
  // A permutation: mirroring twice gives the descriptor back.
  std::vector<float> twice(sift::kDescriptorDim);
  MirrorDescriptor(mirrored.data(), twice.data());
  std::vector<float> again(sift::kDescriptorDim);
  MirrorDescriptor(twice.data(), again.data());
  EXPECT_EQ(again, mirrored);
}

class DuplicatesTest : public ::testing::Test {
 protected:
  void SetUp() override {
    if (!std::filesystem::exists(SamplePath("graf1.png"))) GTEST_SKIP() << "opencv-doc sample photos not installed";
  }
};

// Copies, a crop, a resize, a rotation and a mirror image of one photo are found with their kind; two
// unrelated photos carrying the same logo are not a pair.
TEST_F(DuplicatesTest, FindsCopiesWithTheirKindAndIgnoresASharedLogo) {
  oxbow::testing::TempDir dir("oxbow-duplicates-test");
  const std::string vocab_path = dir.path() + "/vocab.oxvoc";
  ASSERT_TRUE(testing::BuildTestVocabulary({"graf1.png", "box_in_scene.png", "leuvenA.jpg", "fruits.jpg"}, 500, vocab_path));
  auto service = Service::Open(dir.path() + "/index", vocab_path, ServiceOptions{});
  ASSERT_TRUE(service) << service.error().ToString();

  const cv::Mat graf = cv::imread(SamplePath("graf1.png"), cv::IMREAD_COLOR);
  cv::Mat mirror, crop, resized, rotated;
  cv::flip(graf, mirror, 1);
  crop = graf(cv::Rect(graf.cols / 5, graf.rows / 5, graf.cols * 3 / 5, graf.rows * 3 / 5)).clone();
  cv::resize(graf, resized, {}, 0.75, 0.75, cv::INTER_AREA);
  cv::warpAffine(graf, rotated, cv::getRotationMatrix2D({graf.cols / 2.0f, graf.rows / 2.0f}, 10, 1.0), graf.size());
  // The same logo (a patch of another photo) in a corner of two unrelated photos.
  const cv::Mat logo_source = cv::imread(SamplePath("fruits.jpg"), cv::IMREAD_COLOR);
  const cv::Mat logo = logo_source(cv::Rect(100, 100, 180, 180)).clone();
  cv::Mat box = cv::imread(SamplePath("box_in_scene.png"), cv::IMREAD_COLOR);
  cv::Mat leuven = cv::imread(SamplePath("leuvenA.jpg"), cv::IMREAD_COLOR);
  logo.copyTo(box(cv::Rect(0, 0, logo.cols, logo.rows)));
  logo.copyTo(leuven(cv::Rect(leuven.cols - logo.cols, leuven.rows - logo.rows, logo.cols, logo.rows)));

  const std::map<std::string, cv::Mat> images = {{"graf", graf},       {"graf-copy", graf},  {"graf-mirror", mirror},
                                                 {"graf-crop", crop},  {"graf-small", resized},
                                                 {"graf-rotated", rotated}, {"box-logo", box}, {"leuven-logo", leuven}};
  ASSERT_NO_FATAL_FAILURE(AddImages(**service, images));

  DuplicateOptions options;
  options.threads = 2;
  uint64_t last_done = 0;
  auto report = FindDuplicates((*service)->index(), options, [&](uint64_t done, uint64_t total) {
    EXPECT_EQ(total, images.size());
    last_done = std::max(last_done, done);
  });
  ASSERT_TRUE(report) << report.error().ToString();
  EXPECT_EQ(report->images, images.size());
  EXPECT_EQ(last_done, images.size());
  auto pairs = PairsOf(*report);
  auto kind_of = [&](const std::string& a, const std::string& b) -> std::string {
    auto it = pairs.find({std::min(a, b), std::max(a, b)});
    return it == pairs.end() ? "none" : DuplicateKindName(it->second.kind);
  };
  EXPECT_EQ(kind_of("graf", "graf-copy"), "exact");
  EXPECT_EQ(kind_of("graf", "graf-crop"), "near_copy");
  EXPECT_EQ(kind_of("graf", "graf-small"), "near_copy");
  EXPECT_EQ(kind_of("graf", "graf-rotated"), "near_copy");
  EXPECT_EQ(kind_of("graf", "graf-mirror"), "near_copy");
  const DuplicatePair& mirror_pair = pairs[std::make_pair(std::string("graf"), std::string("graf-mirror"))];
  EXPECT_TRUE(mirror_pair.mirrored);
  EXPECT_LT(mirror_pair.b_from_a.Determinant(), 0);
  EXPECT_EQ(kind_of("box-logo", "leuven-logo"), "none");
  // The logo pair was verified by the searches and dropped by the measure.
  EXPECT_GE(report->overlay_pairs, 1u);
  // The crop lies inside graf: its map sends graf's crop corner near (0, 0) of the crop.
  const DuplicatePair& crop_pair = pairs[std::make_pair(std::string("graf"), std::string("graf-crop"))];
  EXPECT_FALSE(crop_pair.mirrored);
  const Eigen::Vector2d corner = crop_pair.b_from_a.Apply({graf.cols / 5.0, graf.rows / 5.0});
  EXPECT_NEAR(corner.x(), 0, 6);
  EXPECT_NEAR(corner.y(), 0, 6);
  EXPECT_GT(crop_pair.coverage_b, 0.8);
  // One group holds graf and its copies; the logo photos are in none.
  ASSERT_EQ(report->groups.size(), 1u);
  EXPECT_EQ(report->groups[0].size(), 6u);

  // JSON and CSV carry every pair.
  const auto json = DuplicateReportToJson(*report, options);
  EXPECT_EQ(json["pairs"].size(), report->pairs.size());
  const std::string csv = DuplicateReportToCsv(*report);
  EXPECT_EQ(static_cast<size_t>(std::count(csv.begin(), csv.end(), '\n')), report->pairs.size() + 1);

  // Cancelled: an error, no report.
  auto cancelled = FindDuplicates((*service)->index(), options, {}, [] { return true; });
  ASSERT_FALSE(cancelled);
  EXPECT_EQ(cancelled.error().code, ErrorCode::kResourceExhausted);
}

// The test vocabulary of tests/support/samples.h, with Hamming-embedding parameters when `hamming`.
void WriteVocabulary(const std::vector<std::string>& images, bool hamming, const std::string& path) {
  auto extractor = sift::SiftExtractor::Create(testing::TestSiftOptions());
  ASSERT_TRUE(extractor);
  std::vector<float> descriptors;
  for (const auto& name : images) {
    auto features = extractor->ExtractFromFile(SamplePath(name));
    ASSERT_TRUE(features) << name;
    descriptors.insert(descriptors.end(), features->descriptors.begin(), features->descriptors.end());
  }
  vocab::TrainOptions train;
  train.num_words = 500;
  train.max_iterations = 10;
  auto vocabulary = vocab::Train(descriptors, sift::kDescriptorDim, sift::DescriptorKind::kRootSift,
                                 testing::TestSiftOptions().Describe(), train);
  ASSERT_TRUE(vocabulary) << vocabulary.error().ToString();
  if (hamming) {
    auto with = vocabulary->WithHamming(descriptors, 7, vocab::QuantizerOptions{.exact = true});
    ASSERT_TRUE(with) << with.error().ToString();
    vocabulary = std::move(with);
  }
  ASSERT_TRUE(vocabulary->Write(path));
}

// Another photo of an object (the box alone, and in a cluttered scene) matches little of the scene, like
// a shared logo; its content is distinct (the signatures of its inliers differ), the logo's is not. With
// `min_coverage` raised so that every kept pair goes through that test, the box pair is kept as the same
// scene and the logo pair dropped (by the searches' verification already); without signatures (a
// vocabulary without Hamming embedding) neither can be told apart and both are dropped.
TEST_F(DuplicatesTest, KeepsAnotherPhotoOfAnObjectAndDropsASharedLogoByTheirContent) {
  const cv::Mat logo = cv::imread(SamplePath("fruits.jpg"), cv::IMREAD_COLOR)(cv::Rect(100, 100, 180, 180)).clone();
  cv::Mat home = cv::imread(SamplePath("home.jpg"), cv::IMREAD_COLOR);
  cv::Mat leuven = cv::imread(SamplePath("leuvenA.jpg"), cv::IMREAD_COLOR);
  logo.copyTo(home(cv::Rect(0, 0, logo.cols, logo.rows)));
  logo.copyTo(leuven(cv::Rect(leuven.cols - logo.cols, leuven.rows - logo.rows, logo.cols, logo.rows)));
  const std::map<std::string, cv::Mat> images = {{"box", cv::imread(SamplePath("box.png"), cv::IMREAD_COLOR)},
                                                 {"box-scene", cv::imread(SamplePath("box_in_scene.png"), cv::IMREAD_COLOR)},
                                                 {"home-logo", home},
                                                 {"leuven-logo", leuven}};
  for (const bool hamming : {true, false}) {
    SCOPED_TRACE(hamming ? "with signatures" : "without signatures");
    oxbow::testing::TempDir dir("oxbow-duplicates-content");
    const std::string vocab_path = dir.path() + "/vocab.oxvoc";
    WriteVocabulary({"graf1.png", "box_in_scene.png", "leuvenA.jpg", "fruits.jpg"}, hamming, vocab_path);
    auto service = Service::Open(dir.path() + "/index", vocab_path, ServiceOptions{});
    ASSERT_TRUE(service) << service.error().ToString();
    ASSERT_NO_FATAL_FAILURE(AddImages(**service, images));
    DuplicateOptions options;
    options.threads = 2;
    options.mirrored = false;
    options.min_coverage = 0.9;
    auto report = FindDuplicates((*service)->index(), options);
    ASSERT_TRUE(report) << report.error().ToString();
    auto pairs = PairsOf(*report);
    EXPECT_FALSE(pairs.contains({"home-logo", "leuven-logo"}));
    if (hamming) {
      // The searches' verification already tells the logo from content: only the box pair is verified,
      // and the measure keeps it.
      EXPECT_EQ(report->candidate_pairs, 1u);
      ASSERT_TRUE(pairs.contains({"box", "box-scene"}));
      const DuplicatePair& box = pairs[{"box", "box-scene"}];
      EXPECT_EQ(box.kind, DuplicateKind::kSameScene);
      EXPECT_LT(std::max(box.coverage_a, box.coverage_b), options.min_coverage);
      EXPECT_EQ(report->pairs.size(), 1u);
      EXPECT_EQ(report->overlay_pairs, 0u);
    } else {
      // Both pairs are verified by the searches; the measure drops both.
      EXPECT_EQ(report->candidate_pairs, 2u);
      EXPECT_TRUE(report->pairs.empty());
      EXPECT_EQ(report->overlay_pairs, 2u);
    }
  }
}

// A search's verified results show the query's content, not an overlay it shares: with signatures, a
// photo shown in a frame (a viewer's window) does not verify another photo in the same frame (the match
// is the frame's identical pixels around different content), while a brighter copy of the framed photo
// verifies. Without signatures the pasted pixels cannot be told from content, and the other framed photo
// verifies.
TEST_F(DuplicatesTest, SearchDoesNotVerifyAPhotoThatSharesOnlyAFrame) {
  const cv::Mat box = Framed("box_in_scene.png");
  cv::Mat box_brighter;
  box.convertTo(box_brighter, -1, 1.0, 25);
  for (const bool hamming : {true, false}) {
    SCOPED_TRACE(hamming ? "with signatures" : "without signatures");
    oxbow::testing::TempDir dir("oxbow-search-overlay");
    const std::string vocab_path = dir.path() + "/vocab.oxvoc";
    WriteVocabulary({"graf1.png", "box_in_scene.png", "leuvenA.jpg", "fruits.jpg"}, hamming, vocab_path);
    auto service = Service::Open(dir.path() + "/index", vocab_path, ServiceOptions{});
    ASSERT_TRUE(service) << service.error().ToString();
    ASSERT_NO_FATAL_FAILURE(AddImages(**service, {{"framed-fruits", Framed("fruits.jpg")}, {"framed-box-brighter", box_brighter}}));
    index::QueryOptions options;
    options.hamming = hamming;
    auto found = (*service)->Search(Png(box), options);
    ASSERT_TRUE(found) << found.error().ToString();
    std::map<std::string, bool> verified;
    for (const auto& r : found->index.results) verified[r.id] = r.verified;
    EXPECT_TRUE(verified["framed-box-brighter"]);
    EXPECT_EQ(verified["framed-fruits"], !hamming);
  }
}

// Two different photos shown in one frame (a viewer's window, a border): the frame matches itself with
// identical pixels over most of both images, around a centre where each shows its own photo. The pair is
// verified by the searches and dropped by the measure; a copy of one framed photo is still a near copy.
// (The test vocabulary has no signatures: the twins, identical features at the same places, decide.)
TEST_F(DuplicatesTest, DropsTwoPhotosInTheSameFrame) {
  oxbow::testing::TempDir dir("oxbow-duplicates-frame");
  const std::string vocab_path = dir.path() + "/vocab.oxvoc";
  ASSERT_TRUE(testing::BuildTestVocabulary({"graf1.png", "box_in_scene.png", "leuvenA.jpg", "fruits.jpg"}, 500, vocab_path));
  auto service = Service::Open(dir.path() + "/index", vocab_path, ServiceOptions{});
  ASSERT_TRUE(service) << service.error().ToString();
  const cv::Mat box = Framed("box_in_scene.png"), fruits = Framed("fruits.jpg");
  cv::Mat box_brighter;
  box.convertTo(box_brighter, -1, 1.0, 25);
  const std::map<std::string, cv::Mat> images = {{"framed-box", box}, {"framed-fruits", fruits}, {"framed-box-brighter", box_brighter}};
  ASSERT_NO_FATAL_FAILURE(AddImages(**service, images));
  DuplicateOptions options;
  options.threads = 2;
  options.mirrored = false;
  auto report = FindDuplicates((*service)->index(), options);
  ASSERT_TRUE(report) << report.error().ToString();
  auto pairs = PairsOf(*report);
  EXPECT_EQ(report->candidate_pairs, 3u);  // every pair verified: the frame matches
  EXPECT_FALSE(pairs.contains({"framed-box", "framed-fruits"}));
  EXPECT_FALSE(pairs.contains({"framed-box-brighter", "framed-fruits"}));
  ASSERT_TRUE(pairs.contains({"framed-box", "framed-box-brighter"}));
  EXPECT_EQ((pairs[{"framed-box", "framed-box-brighter"}].kind), DuplicateKind::kNearCopy);
  EXPECT_EQ(report->overlay_pairs, 2u);
}

}  // namespace
}  // namespace oxbow::api
