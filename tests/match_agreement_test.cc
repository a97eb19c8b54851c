// `oxbow match` (the CLI binary, OXBOW_BINARY) and POST /v1/match (a running `oxbow serve`) run one
// pipeline (api/pair_match.h): for the same images and options they must give the same JSON: the same
// fields, the same verified rule (min_inliers for every model), the same region definition (the whole
// image a mapped into b, as search results define it) and null transform/region when not verified.
#include <gtest/gtest.h>
#include <httplib.h>

#include <algorithm>
#include <array>
#include <filesystem>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "sift/sift.h"
#include "tests/support/e2e.h"
#include "tests/support/samples.h"
#include "tests/support/temp_dir.h"

namespace oxbow {
namespace {

using testing::ReadBytes;
using testing::SamplePath;
using nlohmann::json;
using Options = std::map<std::string, std::string>;  // e.g. {"model", "homography"}

// The extraction both sides use: the server's comes from the vocabulary's label, the CLI's from its
// flags (the defaults: RootSIFT and SiftOptions' other settings on both sides).
sift::SiftOptions SharedExtraction() {
  sift::SiftOptions options;
  options.descriptor = sift::DescriptorKind::kRootSift;
  return options;
}

class MatchAgreementTest : public ::testing::Test {
 public:
  static void SetUpTestSuite() {
    for (const char* name : {"box.png", "box_in_scene.png", "graf1.png"}) {
      if (!std::filesystem::exists(SamplePath(name))) return;
    }
    dir_ = new oxbow::testing::TempDir("oxbow-match-agreement");
    const std::string vocabulary_path = dir_->path() + "/vocab.oxvoc";
    // Matching never quantises: random words suffice, only the extractor label matters.
    auto vocabulary = oxbow::testing::RandomVocabulary(SharedExtraction().Describe());
    ASSERT_TRUE(vocabulary) << vocabulary.error().ToString();
    ASSERT_TRUE(vocabulary->Write(vocabulary_path));
    server_ = new oxbow::testing::ServerProcess(
        {"serve", "--index", dir_->path() + "/index", "--vocab", vocabulary_path, "--port", "0"},
        dir_->path() + "/server.log");
    ASSERT_GT(server_->port(), 0) << server_->Log();
    ASSERT_TRUE(server_->WaitReady()) << server_->Log();
  }
  static void TearDownTestSuite() {
    delete server_;
    server_ = nullptr;
    delete dir_;
    dir_ = nullptr;
  }
  void SetUp() override {
    if (dir_ == nullptr) GTEST_SKIP() << "opencv-doc sample photos not installed (scripts/install-deps.sh)";
    ASSERT_NE(server_, nullptr);
  }

  // `oxbow match` on two sample photos; `options` become --name value flags (min_inliers -> --min-inliers).
  static json Cli(const std::string& a, const std::string& b, const Options& options, const std::string& extra = "") {
    std::string command = std::string(OXBOW_BINARY) + " match " + SamplePath(a) + " " + SamplePath(b);
    for (const auto& [name, value] : options) {
      std::string flag = name;
      std::replace(flag.begin(), flag.end(), '_', '-');
      command.append(" --").append(flag).append(" ").append(value);
    }
    int exit_code = -1;
    const std::string out = oxbow::testing::RunCommand(command + " " + extra + " 2>&1", &exit_code);
    EXPECT_EQ(exit_code, 0) << command << "\n" << out;
    auto parsed = json::parse(out, nullptr, false);
    EXPECT_FALSE(parsed.is_discarded()) << out;
    return parsed;
  }

  // POST /v1/match with the same photos; `options` become form fields.
  static json Http(const std::string& a, const std::string& b, const Options& options) {
    const auto bytes_a = ReadBytes(SamplePath(a));
    const auto bytes_b = ReadBytes(SamplePath(b));
    httplib::MultipartFormDataItems form = {{"a", std::string(bytes_a.begin(), bytes_a.end()), a, ""},
                                            {"b", std::string(bytes_b.begin(), bytes_b.end()), b, ""}};
    for (const auto& [name, value] : options) form.push_back({name, value, "", ""});
    auto client = server_->Client();
    auto res = client.Post("/v1/match", form);
    EXPECT_TRUE(res);
    if (!res) return json();
    EXPECT_EQ(res->status, 200) << res->body;
    auto parsed = json::parse(res->body, nullptr, false);
    EXPECT_FALSE(parsed.is_discarded()) << res->body;
    return parsed;
  }

  static inline oxbow::testing::TempDir* dir_ = nullptr;
  static inline oxbow::testing::ServerProcess* server_ = nullptr;
};

std::vector<std::string> Keys(const json& object) {
  std::vector<std::string> keys;
  for (const auto& item : object.items()) keys.push_back(item.key());
  return keys;
}

// A 3x3 matrix, an [x1,y1,x2,y2] box or null, equal within 1e-6.
void ExpectNumbersNear(const json& cli, const json& http, const std::string& what) {
  ASSERT_EQ(cli.is_null(), http.is_null()) << what << ": cli " << cli << " http " << http;
  if (cli.is_null()) return;
  const json flat_cli = cli.flatten(), flat_http = http.flatten();
  ASSERT_EQ(Keys(flat_cli), Keys(flat_http)) << what << ": cli " << cli << " http " << http;
  for (const auto& item : flat_cli.items()) {
    EXPECT_NEAR(item.value().get<double>(), flat_http[item.key()].get<double>(), 1e-6) << what << item.key();
  }
}

const std::vector<std::string> kFields = {"a", "b", "inliers", "model", "region", "tentative_matches",
                                          "timings_ms", "transform", "verified"};

// Runs the pair both ways and checks that both answers have the one shape and agree field by field;
// *http is the server's answer.
void ExpectAgreement(const std::string& a, const std::string& b, const Options& options, json* http) {
  const json cli = MatchAgreementTest::Cli(a, b, options);
  *http = MatchAgreementTest::Http(a, b, options);
  SCOPED_TRACE(a + " vs " + b + " " + json(options).dump());
  ASSERT_EQ(Keys(*http), kFields) << *http;
  ASSERT_EQ(Keys(cli), kFields) << cli;
  // Without identical features the rest cannot agree: name the cause instead.
  ASSERT_EQ(cli["a"]["keypoints"], (*http)["a"]["keypoints"]) << "the CLI and the server extracted differently";
  ASSERT_EQ(cli["b"]["keypoints"], (*http)["b"]["keypoints"]) << "the CLI and the server extracted differently";

  json cli_images = {{"a", cli["a"]}, {"b", cli["b"]}};  // the CLI adds only the file paths
  cli_images["a"].erase("path");
  cli_images["b"].erase("path");
  EXPECT_EQ(cli_images["a"], (*http)["a"]);
  EXPECT_EQ(cli_images["b"], (*http)["b"]);
  EXPECT_EQ(Keys(cli["timings_ms"]), Keys((*http)["timings_ms"]));
  for (const char* field : {"model", "verified", "inliers", "tentative_matches"}) {
    EXPECT_EQ(cli[field], (*http)[field]) << field;
  }
  ExpectNumbersNear(cli["transform"], (*http)["transform"], "transform");
  ExpectNumbersNear(cli["region"], (*http)["region"], "region");
}

// The region definition: the corners of the whole image a mapped by the transform into b, their
// bounding box clipped to b.
void ExpectRegionIsImageAMapped(const json& match) {
  ASSERT_TRUE(match["verified"].get<bool>()) << match;
  const auto& t = match["transform"];
  const double wa = match["a"]["width"], ha = match["a"]["height"];
  const double wb = match["b"]["width"], hb = match["b"]["height"];
  std::array<double, 4> box = {1e300, 1e300, -1e300, -1e300};
  for (const auto& [x, y] : {std::pair{0.0, 0.0}, {wa, 0.0}, {0.0, ha}, {wa, ha}}) {
    const double z = t[2][0].get<double>() * x + t[2][1].get<double>() * y + t[2][2].get<double>();
    const double u = (t[0][0].get<double>() * x + t[0][1].get<double>() * y + t[0][2].get<double>()) / z;
    const double v = (t[1][0].get<double>() * x + t[1][1].get<double>() * y + t[1][2].get<double>()) / z;
    box = {std::min(box[0], u), std::min(box[1], v), std::max(box[2], u), std::max(box[3], v)};
  }
  const std::array<double, 4> expected = {std::clamp(box[0], 0.0, wb), std::clamp(box[1], 0.0, hb),
                                          std::clamp(box[2], 0.0, wb), std::clamp(box[3], 0.0, hb)};
  for (size_t i = 0; i < 4; ++i) EXPECT_NEAR(match["region"][i].get<double>(), expected[i], 1e-3) << match["region"];
}

TEST_F(MatchAgreementTest, BoxInSceneAgreesForEveryModel) {
  for (const Options& options : {Options{}, Options{{"model", "homography"}}, Options{{"model", "affine"}}}) {
    json match;
    ASSERT_NO_FATAL_FAILURE(ExpectAgreement("box.png", "box_in_scene.png", options, &match));
    EXPECT_TRUE(match["verified"].get<bool>()) << match;
    EXPECT_GE(match["inliers"].get<int>(), 20) << match;
    ExpectRegionIsImageAMapped(match);
  }
}

TEST_F(MatchAgreementTest, UnrelatedPairIsUnverifiedWithNullTransformAndRegion) {
  // box.png vs graf1.png: a homography fits a handful of chance matches exactly, under min_inliers.
  for (const Options& options : {Options{}, Options{{"model", "homography"}}}) {
    json match;
    ASSERT_NO_FATAL_FAILURE(ExpectAgreement("box.png", "graf1.png", options, &match));
    EXPECT_FALSE(match["verified"].get<bool>()) << match;
    EXPECT_TRUE(match["transform"].is_null()) << match;
    EXPECT_TRUE(match["region"].is_null()) << match;
  }
}

TEST_F(MatchAgreementTest, MinInliersDecidesVerifiedForEveryModel) {
  for (const std::string model : {"hough-affine", "homography"}) {
    json plain, exact, over;
    ASSERT_NO_FATAL_FAILURE(ExpectAgreement("box.png", "box_in_scene.png", {{"model", model}}, &plain));
    ASSERT_TRUE(plain["verified"].get<bool>()) << plain;
    const int inliers = plain["inliers"];
    ASSERT_NO_FATAL_FAILURE(ExpectAgreement("box.png", "box_in_scene.png",
                                            {{"model", model}, {"min_inliers", std::to_string(inliers)}}, &exact));
    EXPECT_TRUE(exact["verified"].get<bool>()) << exact;
    ASSERT_NO_FATAL_FAILURE(ExpectAgreement("box.png", "box_in_scene.png",
                                            {{"model", model}, {"min_inliers", std::to_string(inliers + 1)}}, &over));
    EXPECT_FALSE(over["verified"].get<bool>()) << over;
    EXPECT_EQ(over["inliers"], inliers) << "the rejected fit's inliers are still reported";
    EXPECT_TRUE(over["transform"].is_null()) << over;
    EXPECT_TRUE(over["region"].is_null()) << over;
  }
}

TEST_F(MatchAgreementTest, CliDrawsTheMatch) {
  const std::string path = dir_->path() + "/drawing.png";
  const json match = Cli("box.png", "box_in_scene.png", {}, "--draw " + path);
  EXPECT_EQ(match.value("drawing", ""), path) << match;
  const cv::Mat drawing = cv::imread(path);
  ASSERT_FALSE(drawing.empty());
  EXPECT_EQ(drawing.cols, 324 + 512);  // box.png and box_in_scene.png side by side
}

// The descriptor window flags reach the extractor: the same keypoints, other descriptors, so another set of
// tentative matches, and the box is still found.
TEST_F(MatchAgreementTest, CliDescriptorWindow) {
  const json lowe = Cli("box.png", "box_in_scene.png", {});
  const json wide =
      Cli("box.png", "box_in_scene.png", {{"descriptor_magnification", "4"}, {"descriptor_row_step", "2"}});
  EXPECT_EQ(wide["a"]["keypoints"], lowe["a"]["keypoints"]) << wide;
  EXPECT_EQ(wide["b"]["keypoints"], lowe["b"]["keypoints"]) << wide;
  EXPECT_NE(wide["tentative_matches"], lowe["tentative_matches"]) << wide << "\n" << lowe;
  EXPECT_TRUE(wide["verified"].get<bool>()) << wide;
}

}  // namespace
}  // namespace oxbow
