// End to end on real photos (OpenCV's sample images, always installed with opencv-doc): extract SIFT,
// train a small vocabulary with vocab::Train, index a handful of photos, query with another view of
// some of them. Then the same through the `oxbow` CLI (index build / query), including resuming and a
// bad image in the folder.
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <string>

#include "index/image_index.h"
#include "sift/sift.h"
#include "tests/support/e2e.h"
#include "tests/support/temp_dir.h"
#include "vocab/vocabulary.h"

namespace oxbow {
namespace {

namespace fs = std::filesystem;
const fs::path kSamples = "/usr/share/doc/opencv-doc/examples/data";
constexpr int kMaxSide = 640;

// Indexed photos, and queries with the image each must retrieve first.
const std::vector<std::string> kDatabase = {"box_in_scene.png", "graf3.png", "aero3.jpg", "leuvenB.jpg",
                                            "baboon.jpg", "building.jpg", "fruits.jpg", "home.jpg",
                                            "messi5.jpg", "Blender_Suzanne2.jpg"};
const std::map<std::string, std::string> kQueries = {
    {"box.png", "box_in_scene"}, {"graf1.png", "graf3"}, {"aero1.jpg", "aero3"}, {"leuvenA.jpg", "leuvenB"}};

using testing::RunCommand;

class EndToEnd : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    for (const auto& name : kDatabase) {
      if (!fs::exists(kSamples / name)) return;
    }
    temp_ = new oxbow::testing::TempDir("oxbow-index-end-to-end");
    work_ = new fs::path(temp_->path());
    sift::SiftOptions options;
    options.descriptor = sift::DescriptorKind::kRootSift;
    options.max_features = 1500;
    extractor_ = new sift::SiftExtractor(*sift::SiftExtractor::Create(options));
    features_ = new std::map<std::string, sift::FeatureSet>();
    sift::DecodeOptions decode;
    decode.max_image_side_px = kMaxSide;
    std::vector<float> training;
    for (const auto& name : kDatabase) {
      auto f = extractor_->ExtractFromFile((kSamples / name).string(), decode);
      ASSERT_TRUE(f) << name << ": " << f.error().ToString();
      training.insert(training.end(), f->descriptors.begin(), f->descriptors.end());
      (*features_)[name] = std::move(*f);
    }
    for (const auto& [name, expected] : kQueries) {
      auto f = extractor_->ExtractFromFile((kSamples / name).string(), decode);
      ASSERT_TRUE(f) << name;
      (*features_)[name] = std::move(*f);
    }
    vocab::TrainOptions train;
    train.num_words = 2000;
    train.max_iterations = 10;
    auto v = vocab::Train(training, sift::kDescriptorDim, sift::DescriptorKind::kRootSift, options.Describe(), train);
    ASSERT_TRUE(v) << v.error().ToString();
    vocabulary_ = new vocab::Vocabulary(std::move(*v));
  }
  static void TearDownTestSuite() {
    delete work_;
    delete temp_;  // removes the folder
    delete extractor_;
    delete features_;
    delete vocabulary_;
  }
  void SetUp() override {
    if (!vocabulary_) GTEST_SKIP() << "OpenCV sample images not found in " << kSamples;
  }

  static std::string Stem(const std::string& name) { return fs::path(name).stem().string(); }

  static inline oxbow::testing::TempDir* temp_ = nullptr;
  static inline fs::path* work_ = nullptr;
  static inline sift::SiftExtractor* extractor_ = nullptr;
  static inline std::map<std::string, sift::FeatureSet>* features_ = nullptr;
  static inline vocab::Vocabulary* vocabulary_ = nullptr;
};

TEST_F(EndToEnd, RightImageRanksFirstAfterReRanking) {
  auto idx = index::ImageIndex::Create((*work_ / "lib_index").string(), *vocabulary_, extractor_->options().Describe());
  ASSERT_TRUE(idx) << idx.error().ToString();
  for (const auto& name : kDatabase) ASSERT_TRUE((*idx)->Add(Stem(name), features_->at(name), {}));
  int first = 0;
  for (const auto& [query, expected] : kQueries) {
    index::QueryOptions options;
    options.top_k = 5;
    options.rerank_depth = 10;
    const auto r = (*idx)->Query(features_->at(query), options);
    ASSERT_TRUE(r) << r.error().ToString();
    ASSERT_FALSE(r->results.empty());
    std::printf("%-12s -> %-14s verified=%d inliers=%d score=%.3f (2nd: %s inliers=%d)\n", query.c_str(),
                r->results[0].id.c_str(), r->results[0].verified, r->results[0].inliers, r->results[0].score,
                r->results.size() > 1 ? r->results[1].id.c_str() : "-", r->results.size() > 1 ? r->results[1].inliers : 0);
    if (r->results[0].id == expected && r->results[0].verified) ++first;
    if (query == "box.png" || query == "graf1.png") {
      EXPECT_EQ(r->results[0].id, expected) << query;
      EXPECT_TRUE(r->results[0].verified) << query;
      EXPECT_GE(r->results[0].inliers, 10) << query;
      // The matched region lies inside the db image.
      const auto& box = r->results[0].db_region;
      EXPECT_LT(box[0], box[2]);
      EXPECT_LE(box[2], static_cast<float>(r->results[0].record.width) + 1);
    }
  }
  EXPECT_GE(first, 3) << "of " << kQueries.size() << " queries ranked their image first, verified";

  // box.png restricted to a region (its left half) still finds the box scene.
  index::QueryOptions region;
  region.top_k = 3;
  region.rerank_depth = 10;
  const auto& box = features_->at("box.png");
  region.region = std::array<float, 4>{0, 0, box.image_width / 2.0f, static_cast<float>(box.image_height)};
  const auto r = (*idx)->Query(box, region);
  ASSERT_TRUE(r);
  EXPECT_LT(r->query_features, box.size());
  ASSERT_FALSE(r->results.empty());
  EXPECT_EQ(r->results[0].id, "box_in_scene");
}

TEST_F(EndToEnd, CommandLineBuildResumeAndQuery) {
  const fs::path images = *work_ / "images";
  fs::create_directories(images);
  for (const auto& name : kDatabase) fs::create_symlink(kSamples / name, images / name);
  { std::ofstream(images / "broken.jpg") << "not a jpeg at all"; }
  const fs::path vocab_file = *work_ / "vocab.oxvoc";
  ASSERT_TRUE(vocabulary_->Write(vocab_file.string()));
  const fs::path out = *work_ / "cli_index";
  const std::string bin = OXBOW_BINARY;
  const std::string build = bin + " -q index build --vocab " + vocab_file.string() + " --images " + images.string() +
                            " --out " + out.string() + " --max-image-side " + std::to_string(kMaxSide);
  int code = -1;
  auto summary = nlohmann::json::parse(RunCommand(build, &code));
  ASSERT_EQ(code, 0);
  EXPECT_EQ(summary["added"], kDatabase.size());
  EXPECT_EQ(summary["failed"], 1);  // broken.jpg reported and skipped
  EXPECT_EQ(summary["images"], kDatabase.size());
  EXPECT_GT(summary["bytes_per_feature"].get<double>(), 9.0);

  // Re-running resumes: everything already indexed is skipped.
  summary = nlohmann::json::parse(RunCommand(build, &code));
  ASSERT_EQ(code, 0);
  EXPECT_EQ(summary["added"], 0);
  EXPECT_EQ(summary["already_indexed"], kDatabase.size());

  // Inputs none of which can be indexed: an error (exit 3), not an empty index reported as built.
  const fs::path broken_only = *work_ / "broken_only";
  fs::create_directories(broken_only);
  fs::copy_file(images / "broken.jpg", broken_only / "broken.jpg");
  const std::string build_broken = bin + " -q index build --vocab " + vocab_file.string() + " --images " +
                                   broken_only.string() + " --out " + (*work_ / "broken_index").string();
  RunCommand(build_broken, &code);
  EXPECT_EQ(code, 3);
  // A mistyped --images leaves no index behind; a folder of other files is not written into.
  RunCommand(bin + " -q index build --vocab " + vocab_file.string() + " --images " + (*work_ / "no-such").string() +
                 " --out " + (*work_ / "typo_index").string(),
             &code);
  EXPECT_EQ(code, 4);
  EXPECT_FALSE(fs::exists(*work_ / "typo_index"));
  RunCommand(bin + " -q index build --vocab " + vocab_file.string() + " --images " + images.string() + " --out " +
                 broken_only.string(),
             &code);
  EXPECT_EQ(code, 5);
  EXPECT_FALSE(fs::exists(broken_only / "catalogue.sqlite"));

  const std::string query = bin + " -q query --index " + out.string() + " --max-image-side " + std::to_string(kMaxSide) +
                            " --top-k 3 " + (kSamples / "box.png").string();
  const auto result = nlohmann::json::parse(RunCommand(query, &code));
  ASSERT_EQ(code, 0);
  ASSERT_FALSE(result["results"].empty());
  EXPECT_EQ(result["results"][0]["id"], "box_in_scene");
  EXPECT_TRUE(result["results"][0]["verified"].get<bool>());
  for (const char* stage : {"decode", "extract", "quantize", "score", "verify"}) {
    EXPECT_TRUE(result["timings_ms"].contains(stage)) << stage;
  }

  // remove + info
  RunCommand(bin + " -q index remove --index " + out.string() + " home", &code);
  EXPECT_EQ(code, 0);
  const auto info = nlohmann::json::parse(RunCommand(bin + " -q index info --index " + out.string(), &code));
  ASSERT_EQ(code, 0);
  EXPECT_EQ(info["images"], kDatabase.size() - 1);
  // An empty folder makes an empty index.
  fs::create_directories(*work_ / "empty");
  summary = nlohmann::json::parse(RunCommand(bin + " -q index build --vocab " + vocab_file.string() + " --images " +
                                                 (*work_ / "empty").string() + " --out " + (*work_ / "empty_index").string(),
                                             &code));
  ASSERT_EQ(code, 0);
  EXPECT_EQ(summary["images"], 0);
  // Resuming with another vocabulary is refused with a message.
  const auto c = vocabulary_->centroids();
  auto other = vocab::Vocabulary::FromCentroids(std::vector<float>(c.begin(), c.begin() + 500 * 128), 128,
                                                sift::DescriptorKind::kRootSift, vocabulary_->extractor_settings());
  ASSERT_TRUE(other);
  ASSERT_TRUE(other->Write((*work_ / "other.oxvoc").string()));
  const std::string refused = RunCommand(bin + " -q index build --vocab " + (*work_ / "other.oxvoc").string() +
                                             " --images " + images.string() + " --out " + out.string() + " 2>&1",
                                         &code);
  EXPECT_NE(code, 0);
  EXPECT_NE(refused.find("another vocabulary"), std::string::npos) << refused;
}

// `index build --features` (feature files from `oxbow extract`, extracted elsewhere) gives the same
// index as extracting here: same records, same rankings and scores.
TEST_F(EndToEnd, BuildFromFeatureFilesEqualsBuildFromImages) {
  const fs::path images = *work_ / "images_for_features";
  fs::create_directories(images);
  std::string image_args;
  for (const auto& name : kDatabase) {
    fs::create_symlink(kSamples / name, images / name);
    image_args += " " + (images / name).string();
  }
  const fs::path vocab_file = *work_ / "vocab_for_features.oxvoc";
  ASSERT_TRUE(vocabulary_->Write(vocab_file.string()));
  const std::string bin = OXBOW_BINARY;
  const std::string side = " --max-image-side " + std::to_string(kMaxSide);
  int code = -1;
  RunCommand(bin + " -q extract --max-features 1500 --out " + (*work_ / "feats").string() + side + image_args, &code);
  ASSERT_EQ(code, 0);
  const auto from_features = nlohmann::json::parse(RunCommand(
      bin + " -q index build --vocab " + vocab_file.string() + " --features " + (*work_ / "feats").string() +
          " --out " + (*work_ / "from_features").string(), &code));
  ASSERT_EQ(code, 0);
  EXPECT_EQ(from_features["added"], kDatabase.size());
  const auto from_images = nlohmann::json::parse(RunCommand(
      bin + " -q index build --vocab " + vocab_file.string() + " --images " + images.string() + side + " --out " +
          (*work_ / "from_images").string(), &code));
  ASSERT_EQ(code, 0);
  EXPECT_EQ(from_features["features"], from_images["features"]);
  for (const auto& [query, expected] : kQueries) {
    const std::string args = " --top-k 10" + side + " " + (kSamples / query).string();
    const auto run_query = [&](const fs::path& index) {
      std::string command = bin;
      command.append(" -q query --index ").append(index.string()).append(args);
      return nlohmann::json::parse(RunCommand(command, &code));
    };
    const auto a = run_query(*work_ / "from_features");
    ASSERT_EQ(code, 0);
    const auto b = run_query(*work_ / "from_images");
    ASSERT_EQ(code, 0);
    ASSERT_EQ(a["results"].size(), b["results"].size()) << query;
    EXPECT_EQ(a["results"][0]["id"], expected);
    for (size_t i = 0; i < a["results"].size(); ++i) {
      EXPECT_EQ(a["results"][i]["id"], b["results"][i]["id"]) << query << " rank " << i;
      EXPECT_EQ(a["results"][i]["score"], b["results"][i]["score"]) << query << " rank " << i;
      EXPECT_EQ(a["results"][i]["inliers"], b["results"][i]["inliers"]) << query << " rank " << i;
    }
  }
  // Feature files from another extractor are refused per image, with the reason.
  RunCommand(bin + " -q extract --max-features 700 --out " + (*work_ / "other_feats").string() + side + " " +
                 (images / kDatabase[0]).string(), &code);
  ASSERT_EQ(code, 0);
  const std::string refused = RunCommand(bin + " index build --vocab " + vocab_file.string() + " --features " +
                                             (*work_ / "other_feats").string() + " --out " +
                                             (*work_ / "from_other").string() + " 2>&1", &code);
  EXPECT_NE(refused.find("extract with the index's settings"), std::string::npos) << refused;
  EXPECT_NE(refused.find("\"failed\": 1"), std::string::npos) << refused;
  // Two images whose ids (file names without extension) are one: the second is counted as failed.
  fs::create_directories(*work_ / "clash" / "x");
  fs::create_directories(*work_ / "clash" / "y");
  fs::copy_file(images / kDatabase[0], *work_ / "clash" / "x" / kDatabase[0]);
  fs::copy_file(images / kDatabase[0], *work_ / "clash" / "y" / kDatabase[0]);
  const std::string clash = RunCommand(bin + " index build --vocab " + vocab_file.string() + side + " --images " +
                                           (*work_ / "clash").string() + " --out " + (*work_ / "clash_index").string() +
                                           " 2>&1", &code);
  EXPECT_EQ(code, 0) << clash;
  EXPECT_NE(clash.find("\"added\": 1"), std::string::npos) << clash;
  EXPECT_NE(clash.find("\"failed\": 1"), std::string::npos) << clash;
  EXPECT_NE(clash.find("not indexed: " + (*work_ / "clash" / "y" / kDatabase[0]).string()), std::string::npos) << clash;
  // A folder without feature files, a folder or an image as --list: refused before an index is made.
  fs::create_directories(*work_ / "no_feats");
  const std::vector<std::pair<std::string, std::string>> wrong = {
      {"--features " + (*work_ / "no_feats").string(), "no .oxfeat files under"},
      {"--list " + images.string(), "is a folder: give a text file of image paths"},
      {"--list " + (images / kDatabase[0]).string(), "is not a text file of image paths"}};
  for (const auto& [source, expected] : wrong) {
    std::string command = bin + " index build --vocab " + vocab_file.string();
    command.append(" ").append(source).append(" --out ").append((*work_ / "wrong_source").string()).append(" 2>&1");
    const std::string out = RunCommand(command, &code);
    EXPECT_NE(code, 0) << source;
    EXPECT_NE(out.find(expected), std::string::npos) << source << "\n" << out;
    EXPECT_FALSE(fs::exists(*work_ / "wrong_source")) << source;
  }
}

}  // namespace
}  // namespace oxbow
