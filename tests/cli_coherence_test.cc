// The `oxbow` commands behave as one product: a vocabulary trained from SIFT feature files is accepted by
// index build and serve; every command extracts a large photo the way the server does (same default image
// size limit, same descriptor); every command lists a nested folder the same way; 0 means "no limit" for
// --max-image-side everywhere.
#include <gtest/gtest.h>

// Before <httplib.h>: it includes <resolv.h>, whose `_res` macro breaks Eigen's headers.
#include "index/image_index.h"
#include "server/cli/cli.h"
#include "sift/sift.h"

#include <httplib.h>
#include <nlohmann/json.hpp>

#include <filesystem>
#include <fstream>
#include <memory>
#include <regex>
#include <string>
#include <tuple>
#include <vector>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "tests/support/e2e.h"
#include "tests/support/samples.h"
#include "tests/support/temp_dir.h"

namespace oxbow {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;
using testing::RunCommand;

const fs::path kSamples = "/usr/share/doc/opencv-doc/examples/data";

std::string Oxbow(const std::string& args) { return std::string(OXBOW_BINARY) + " " + args + " 2>&1"; }

class CliCoherence : public ::testing::Test {
 protected:
  void SetUp() override {
    if (!fs::exists(kSamples / "graf1.png") || !fs::exists(kSamples / "box.png"))
      GTEST_SKIP() << "opencv-doc sample photos not installed (scripts/install-deps.sh)";
    dir_ = std::make_unique<oxbow::testing::TempDir>("oxbow-cli-coherence");
    // A photo larger than the default --max-image-side (1600 px): graf1 (800x640) enlarged 2.5x.
    big_ = dir_->path() + "/photos/nested/big.png";
    fs::create_directories(fs::path(big_).parent_path());
    cv::Mat graf = cv::imread((kSamples / "graf1.png").string(), cv::IMREAD_GRAYSCALE);
    cv::Mat enlarged;
    cv::resize(graf, enlarged, {}, 2.5, 2.5, cv::INTER_CUBIC);
    ASSERT_TRUE(cv::imwrite(big_, enlarged));
    fs::copy_file(kSamples / "box.png", dir_->path() + "/photos/nested/box.png");
  }
  std::string Path(const std::string& name) const { return dir_->path() + "/" + name; }

  std::unique_ptr<oxbow::testing::TempDir> dir_;
  std::string big_;
};

// Keypoint count printed by `oxbow extract` ("...: WxH, N keypoints, ...").
int ExtractedKeypoints(const std::string& output) {
  std::smatch m;
  const std::regex line(R"(, (\d+) keypoints,)");
  return std::regex_search(output, m, line) ? std::stoi(m[1]) : -1;
}

TEST_F(CliCoherence, VocabularyFromSiftFeatureFilesIsUsableByIndexBuildAndServe) {
  int rc = 0;
  std::string out = RunCommand(Oxbow("extract --descriptor SIFT --max-image-side 800 --out " + Path("feats") + " " +
                                     (kSamples / "graf1.png").string() + " " + (kSamples / "box.png").string()),
                               &rc);
  ASSERT_EQ(rc, 0) << out;
  out = RunCommand(Oxbow("features info " + Path("feats/box.png.oxfeat")), &rc);
  ASSERT_NE(out.find(", sift descriptors"), std::string::npos) << out;
  // A damaged feature file among them is skipped with a warning, as an unreadable image is.
  std::ofstream(Path("feats/damaged.png.oxfeat"), std::ios::binary) << "not a feature file";
  // The documented path: SIFT files, a RootSIFT vocabulary (the default descriptor converts them).
  out = RunCommand(Oxbow("vocab train --features " + Path("feats") + " --words 64 --out " + Path("v.oxvoc")), &rc);
  ASSERT_EQ(rc, 0) << out;
  EXPECT_NE(out.find("skipping " + Path("feats/damaged.png.oxfeat")), std::string::npos) << out;
  EXPECT_NE(out.find("(1 unreadable)"), std::string::npos) << out;
  out = RunCommand(Oxbow("vocab info " + Path("v.oxvoc")), &rc);
  ASSERT_EQ(rc, 0) << out;
  EXPECT_NE(out.find("descriptor   rootsift"), std::string::npos) << out;
  // Before: ";vocab_root_sift=1" in the settings made these exit 6 ("not understood by this build").
  out = RunCommand(Oxbow("index build --vocab " + Path("v.oxvoc") + " --images " + Path("photos") + " --out " +
                         Path("index")),
                   &rc);
  ASSERT_EQ(rc, 0) << out;
  out = RunCommand(Oxbow("query --index " + Path("index") + " " + (kSamples / "box.png").string()), &rc);
  ASSERT_EQ(rc, 0) << out;
  testing::ServerProcess server({"serve", "--index", Path("index"), "--port", "0"}, Path("serve.log"));
  ASSERT_GT(server.port(), 0) << server.Log();
  EXPECT_TRUE(server.WaitReady()) << server.Log();
}

TEST_F(CliCoherence, EveryCommandExtractsALargePhotoAsTheServerDoes) {
  int rc = 0;
  // The library's defaults: RootSIFT, downscaled to the default longest side.
  const sift::SiftExtractor extractor = *sift::SiftExtractor::Create(sift::SiftOptions{});
  const auto library = extractor.ExtractFromFile(big_);
  ASSERT_TRUE(library) << library.error().ToString();
  ASSERT_EQ(library->kind, sift::DescriptorKind::kRootSift);

  std::string out = RunCommand(Oxbow("extract --out " + Path("feats") + " " + big_), &rc);
  ASSERT_EQ(rc, 0) << out;
  EXPECT_EQ(ExtractedKeypoints(out), static_cast<int>(library->size())) << out;
  out = RunCommand(Oxbow("features info " + Path("feats/big.png.oxfeat")), &rc);
  EXPECT_NE(out.find("rootsift descriptors"), std::string::npos) << out;
  // 0 = no limit, accepted by every command.
  out = RunCommand(Oxbow("extract --max-image-side 0 --out " + Path("full") + " " + big_), &rc);
  ASSERT_EQ(rc, 0) << out;
  EXPECT_GT(ExtractedKeypoints(out), static_cast<int>(library->size())) << "the full-size photo has more keypoints";

  // vocab train lists the nested folder (it did not recurse: "no images to train on").
  out = RunCommand(Oxbow("vocab train --images " + Path("photos") + " --words 64 --out " + Path("v.oxvoc")), &rc);
  ASSERT_EQ(rc, 0) << out;
  out = RunCommand(Oxbow("index build --vocab " + Path("v.oxvoc") + " --images " + Path("photos") + " --out " +
                         Path("index")),
                   &rc);
  ASSERT_EQ(rc, 0) << out;
  const json summary = json::parse(out.substr(out.find('{')));
  EXPECT_EQ(summary["added"], 2) << out;
  out = RunCommand(Oxbow("query --index " + Path("index") + " --no-qe " + big_), &rc);
  ASSERT_EQ(rc, 0) << out;
  const json query = json::parse(out.substr(out.find('{')));
  EXPECT_EQ(query["query"]["features"], library->size());

  // The server, with its defaults, extracts the same photo to the same features.
  testing::ServerProcess server({"serve", "--index", Path("index"), "--port", "0"}, Path("serve.log"));
  ASSERT_GT(server.port(), 0) << server.Log();
  ASSERT_TRUE(server.WaitReady()) << server.Log();
  const std::string bytes = testing::FileBytes(big_);
  httplib::Client client("127.0.0.1", server.port());
  client.set_read_timeout(120);
  auto searched = client.Post("/v1/search", bytes, "image/png");
  ASSERT_TRUE(searched);
  ASSERT_EQ(searched->status, 200) << searched->body;
  const json response = json::parse(searched->body);
  EXPECT_EQ(response["query"]["features"], library->size());
  // The same search defaults as the library (QueryOptions): re-ranking depth and query expansion.
  EXPECT_EQ(response["params"]["rerank"], index::QueryOptions{}.rerank_depth);
  EXPECT_EQ(response["params"]["qe"], index::QueryOptions{}.query_expansion);
  EXPECT_TRUE(index::QueryOptions{}.query_expansion);
}

// Mistakes are refused before any work, with what is wrong in the flag's own terms.
TEST(CliErrors, MistakesAreRefusedBeforeAnyWorkNamingWhatIsWrong) {
  const oxbow::testing::TempDir dir("oxbow-cli-errors");
  const std::string& d = dir.path();
  const std::vector<std::tuple<std::string, int, std::string>> cases = {
      {"frobnicate", 106, "'frobnicate' is not a command of oxbow; the commands are: "},
      {"index bild --out x", 106, "'bild' is not a command of oxbow index"},
      {"vocab train --images " + d + " --words 0 --out " + d + "/v.oxvoc", 105, "must be greater than 0, not 0"},
      {"vocab train --images " + d + " --words 10 --out " + d + "/no-such/v.oxvoc", 105,
       "the folder '" + d + "/no-such' of '" + d + "/no-such/v.oxvoc' does not exist"},
      {"vocab train --images " + d + " --words 10 --out " + d, 105, "is a folder: give a file name"},
      {"eval --images " + d + " --qe maybe", 105, "maybe not in {off,on}"},
      {"eval --images " + d + " --protocol foo", 105, "foo not in {oxford,restricted,revisited,groups}"},
      {"eval --images " + d + " --hamming-sigma 0", 105, "must be in (0, 64], not 0"},
      {"eval --images " + d + " --work " + d + "/photo.jpg", 105, "is a file: give a folder"},
      // Flags name themselves, and conflicting or meaningless values are refused.
      {"extract " + d + "/photo.jpg --contrast-threshold 2", 105, "--contrast-threshold: must be in [0, 1], not 2"},
      {"vocab train --images " + d + " --words 10 --seed -1 --out " + d + "/v.oxvoc", 105, "--seed: must be at least 0"},
      {"vocab train --images " + d + " --words 10 --descriptor sift --root-sift --out " + d + "/v.oxvoc", 108,
       "--descriptor excludes --root-sift"},
      {"extract " + d + "/photo.jpg --descriptor-sampling grid --descriptor-row-step 2", 2,
       "descriptor_row_step applies to the pixel sampling only"},
      {"extract " + d + "/photo.jpg --descriptor-sampling dense", 105, "--descriptor-sampling: dense not in {grid,pixels}"},
      {"serve --index " + d + "/no-index --shutdown-grace-s nan", 105, "'nan' is not a number"},
      {"index add --index " + d + "/no-index --id '' " + d + "/photo.jpg", 105, "--id: an id is not empty"},
      {"match " + d + "/photo.jpg " + d + "/x/photo.jpg --kd-trees 3", 2, "--kd-trees and --kd-checks tune --method kdtree"},
      {"index check --index " + d + "/no-index", 4, "no index at " + d + "/no-index"},
      {"index check --index " + d + "/no-index -q", 4, "no index at " + d + "/no-index"},  // global flags anywhere
      // A missing flag is named, not read as a mistyped command (the sources are an option group).
      {"vocab train --images " + d + " --words 10", 106, "--out is required"},
      {"vocab hamming --vocab " + d + "/v.oxvoc --images " + d, 106, "--out is required"},
      // Outputs never replace an input, a file of another kind, or another image's output.
      {"vocab train --images " + d + " --words 10 --out " + d + "/photo.jpg", 105,
       "'" + d + "/photo.jpg' exists and is not a vocabulary file"},
      {"index duplicates --index " + d + "/no-index --out " + d + "/photo.jpg", 105,
       "'" + d + "/photo.jpg' exists and is not a duplicates report"},
      {"extract " + d + "/photo.jpg --out " + d + "/features --draw " + d + "/photo.jpg", 2,
       "the drawing '" + d + "/photo.jpg' is one of the input files"},
      {"extract " + d + "/photo.jpg --out " + d + "/features --draw " + d + "/drawing", 105,
       "name the drawing's format by its extension"},
      {"match " + d + "/photo.jpg " + d + "/x/photo.jpg --draw " + d + "/x/photo.jpg", 2,
       "--draw '" + d + "/x/photo.jpg' is one of the input files"},
      {"extract " + d + "/photo.jpg " + d + "/x/photo.jpg --out " + d + "/features", 2,
       "'" + d + "/photo.jpg' and '" + d + "/x/photo.jpg' would both write the feature file"},
  };
  // Checked before decoding: the bytes need not be a photo.
  const std::string photo = "not decoded: the outputs are refused first";
  fs::create_directories(d + "/x");
  for (const std::string& path : {d + "/photo.jpg", d + "/x/photo.jpg"}) std::ofstream(path, std::ios::binary) << photo;
  for (const auto& [args, expected_rc, expected_text] : cases) {
    int rc = -1;
    const std::string out = RunCommand(Oxbow(args), &rc);
    EXPECT_EQ(rc, expected_rc) << args << "\n" << out;
    EXPECT_NE(out.find(expected_text), std::string::npos) << args << "\n" << out;
  }
  EXPECT_FALSE(fs::exists(d + "/no-index"));
  EXPECT_FALSE(fs::exists(d + "/v.oxvoc"));
  EXPECT_FALSE(fs::exists(d + "/features"));
  for (const std::string& path : {d + "/photo.jpg", d + "/x/photo.jpg"}) {
    EXPECT_EQ(testing::FileBytes(path), photo) << path;
  }
}

// Ctrl-C in `extract` and `index build`: the first signal is recorded for the command to stop between
// images; the second takes the default action (the handler resets itself); the command's end restores
// what was there before.
TEST(CliInterrupt, TheFirstSignalIsRecordedTheSecondIsTheDefault) {
  struct sigaction before {};
  ASSERT_EQ(sigaction(SIGINT, nullptr, &before), 0);
  {
    const oxbow::cli::InterruptibleCommand command;
    EXPECT_FALSE(oxbow::cli::InterruptibleCommand::Interrupted());
    ASSERT_EQ(raise(SIGINT), 0);
    EXPECT_TRUE(oxbow::cli::InterruptibleCommand::Interrupted());
    struct sigaction now {};
    ASSERT_EQ(sigaction(SIGINT, nullptr, &now), 0);
    EXPECT_EQ(now.sa_handler, SIG_DFL);
  }
  struct sigaction after {};
  ASSERT_EQ(sigaction(SIGINT, nullptr, &after), 0);
  EXPECT_EQ(after.sa_handler, before.sa_handler);
}

}  // namespace
}  // namespace oxbow
