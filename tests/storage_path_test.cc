// The storage benchmark's path at a small N (eval/README.md, "Benchmarks"; eval/synthetic_collection.h):
// synthetic images added through ImageIndex::AddBatch with words already assigned, in small batches, then
// a checkpoint at close, then adds and removes while searching. The same synthetic collection, exported
// as feature files, is indexed by `oxbow index build --features`. Both folders must give the same answers
// (ids, order, scores, verification) to the same queries, and so must the ingested folder when reopened
// from its checkpoint, and again after one more add and remove.
#include <gtest/gtest.h>

#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "eval/synthetic_collection.h"
#include "index/image_index.h"
#include "sift/features_io.h"
#include "sift/sift.h"
#include "tests/support/e2e.h"
#include "tests/support/temp_dir.h"

namespace oxbow {
namespace {

namespace fs = std::filesystem;
using testing::RunCommand;

constexpr int kImages = 300;

std::string MustRun(const std::string& command) {
  int code = -1;
  std::string out = RunCommand(command + " 2>&1", &code);
  EXPECT_EQ(code, 0) << command << "\n" << out;
  return out;
}

// What a query answers, everything a client sees of the ranking.
struct Answer {
  std::string id;
  double score;
  bool verified;
  int inliers;
  bool operator==(const Answer&) const = default;
};

void PrintTo(const Answer& a, std::ostream* os) {
  *os << a.id << " score " << a.score << (a.verified ? " verified " : " not verified ") << a.inliers;
}

std::vector<Answer> Ask(const index::ImageIndex& idx, const sift::FeatureSet& query) {
  auto r = idx.Query(query, index::QueryOptions{});
  EXPECT_TRUE(r) << r.error().ToString();
  std::vector<Answer> out;
  if (!r) return out;
  for (const auto& x : r->results) out.push_back({x.id, x.score, x.verified, x.inliers});
  return out;
}

class StoragePath : public ::testing::Test {
 protected:
  void SetUp() override {
    fs::create_directories(dir_ / "photos");
    // A few real photos: their features are the pool the synthetic images draw from.
    for (const char* name : {"box.png", "box_in_scene.png", "building.jpg", "graf1.png", "graf3.png"}) {
      fs::copy_file(fs::path("/usr/share/doc/opencv-doc/examples/data") / name, dir_ / "photos" / name);
    }
  }
  oxbow::testing::TempDir temp_;  // removed with its contents after the test
  fs::path dir_{temp_.path()};
};

TEST_F(StoragePath, IngestedFolderAnswersAsIndexBuildFromTheSameFeatures) {
  const std::string oxbow = OXBOW_BINARY;
  const fs::path vocab_file = dir_ / "words.oxvoc", ingested = dir_ / "ingested", built = dir_ / "built",
                 exported = dir_ / "features";
  MustRun(oxbow + " vocab train --images " + (dir_ / "photos").string() + " --words 300 --out " + vocab_file.string());
  auto vocabulary = vocab::Vocabulary::Read(vocab_file.string());
  ASSERT_TRUE(vocabulary) << vocabulary.error().ToString();

  // The real photos' RootSIFT features (long side <= 1024 px), as the storage benchmark extracts them.
  sift::SiftOptions sift_options;
  sift_options.descriptor = sift::DescriptorKind::kRootSift;
  sift_options.num_threads = 1;
  auto extractor = sift::SiftExtractor::Create(sift_options);
  ASSERT_TRUE(extractor) << extractor.error().ToString();
  sift::DecodeOptions decode;
  decode.max_image_side_px = 1024;
  std::vector<sift::FeatureSet> photos;
  for (const auto& entry : fs::directory_iterator(dir_ / "photos")) {
    auto f = extractor->ExtractFromFile(entry.path().string(), decode);
    ASSERT_TRUE(f) << f.error().ToString();
    photos.push_back(std::move(*f));
  }

  index::IndexOptions options;
  options.num_threads = 2;
  vocab::QuantizerOptions quantizer = options.quantizer;
  quantizer.num_threads = 2;
  const eval::SyntheticCollection collection(photos, *vocabulary, quantizer,
                                             {.features_per_image = 150, .descriptors = true});
  ASSERT_TRUE(collection.has_signatures());  // `oxbow vocab train` adds Hamming-embedding parameters
  {
    auto created = index::ImageIndex::Create(ingested.string(), *vocabulary, sift_options.Describe(), options);
    ASSERT_TRUE(created) << created.error().ToString();
    // Batches of 64: several segments; a checkpoint at close.
    const auto report = eval::IngestSynthetic(
        **created, collection,
        {.count = kImages, .batch = 64, .num_threads = 2, .export_dir = exported, .extractor = sift_options});
    ASSERT_TRUE(report) << report.error().ToString();
  }
  {
    // Adds and removes while searching: removed images in the log.
    auto opened = index::ImageIndex::Open(ingested.string(), options);
    ASSERT_TRUE(opened) << opened.error().ToString();
    std::vector<const sift::FeatureSet*> searches;
    searches.reserve(photos.size());
    for (const auto& p : photos) searches.push_back(&p);
    const auto writes = eval::AddAndRemoveWhileSearching(**opened, collection, kImages, 8, searches);
    ASSERT_TRUE(writes) << writes.error().ToString();
    EXPECT_EQ(writes->add_ms.size(), 8u);
    EXPECT_EQ(writes->remove_ms.size(), 8u);
  }
  MustRun(oxbow + " index build --features " + exported.string() + " --vocab " + vocab_file.string() + " --out " +
          built.string());

  std::vector<sift::FeatureSet> queries;
  for (const int k : {0, 17, 123, 299}) {
    auto file = sift::ReadFeatureFile((exported / (eval::SyntheticCollection::Id(k) + ".oxfeat")).string());
    ASSERT_TRUE(file) << file.error().ToString();
    queries.push_back(std::move(file->features));
  }

  std::vector<std::vector<Answer>> expected;
  {
    auto reference = index::ImageIndex::Open(built.string(), options);
    ASSERT_TRUE(reference) << reference.error().ToString();
    EXPECT_EQ((*reference)->Stats().num_images, static_cast<uint64_t>(kImages));
    for (const auto& q : queries) expected.push_back(Ask(**reference, q));
  }
  // The query is one of the images, so the collection must rank it first.
  for (size_t i = 0; i < queries.size(); ++i) ASSERT_FALSE(expected[i].empty());
  EXPECT_EQ(expected[0][0].id, "s0");
  EXPECT_EQ(expected[3][0].id, "s299");

  {
    auto opened = index::ImageIndex::Open(ingested.string(), options);  // from the checkpoint written at close
    ASSERT_TRUE(opened) << opened.error().ToString();
    EXPECT_EQ((*opened)->Stats().num_images, static_cast<uint64_t>(kImages));
    for (size_t i = 0; i < queries.size(); ++i) EXPECT_EQ(Ask(**opened, queries[i]), expected[i]) << "query " << i;
    ASSERT_TRUE((*opened)->Add("extra", queries[1], {}));
    ASSERT_TRUE((*opened)->Remove("extra"));
  }
  auto reopened = index::ImageIndex::Open(ingested.string(), options);
  ASSERT_TRUE(reopened) << reopened.error().ToString();
  for (size_t i = 0; i < queries.size(); ++i) EXPECT_EQ(Ask(**reopened, queries[i]), expected[i]) << "query " << i;
}

}  // namespace
}  // namespace oxbow
