// The storage benchmark's path at a small N (eval/README.md, "Benchmarks"): `index_benchmark
// storage` builds its folder through ImageIndex::AddBatch with words already assigned, in small batches,
// with checkpoints, then adds and removes images while searching. The same synthetic collection,
// exported as feature files, is indexed by `oxbow index build --features`. Both folders must give the
// same answers (ids, order, scores, verification) to the same queries, and so must the benchmark's
// folder when reopened from its checkpoint, and again after one more add and remove.
#include <gtest/gtest.h>

#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "index/image_index.h"
#include "sift/features_io.h"
#include "tests/e2e_testing.h"

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
#ifndef OXBOW_INDEX_BENCHMARK
    GTEST_SKIP() << "built without the benchmarks (OXBOW_BUILD_BENCHMARKS=OFF): no index_benchmark to run";
#endif
    dir_ = fs::temp_directory_path() / ("oxbow-storage-path-" + std::to_string(getpid()));
    fs::remove_all(dir_);
    fs::create_directories(dir_ / "photos" / "images");
    // A few real photos: their features are the pool the synthetic images draw from.
    for (const char* name : {"box.png", "box_in_scene.png", "graf1.png", "graf3.png", "building.jpg"}) {
      fs::copy_file(fs::path("/usr/share/doc/opencv-doc/examples/data") / name, dir_ / "photos" / "images" / name);
    }
  }
  void TearDown() override {
    if (!dir_.empty()) fs::remove_all(dir_);
  }
  fs::path dir_;
};

TEST_F(StoragePath, BenchmarkFolderAnswersAsIndexBuildFromTheSameFeatures) {
#ifdef OXBOW_INDEX_BENCHMARK
  const std::string oxbow = OXBOW_BINARY;
  const fs::path vocab = dir_ / "words.oxvoc", bench = dir_ / "bench", built = dir_ / "built", exported = dir_ / "features";
  MustRun(oxbow + " vocab train --images " + (dir_ / "photos" / "images").string() + " --words 300 --out " + vocab.string());
  // Batches of 64 and the benchmark's own adds and removes while searching: several segments, a
  // checkpoint at close, removed images in the log.
  const std::string report = MustRun(std::string(OXBOW_INDEX_BENCHMARK) + " storage --images " + std::to_string(kImages) +
                                 " --features 150 --batch 64 --queries 4 --threads 2 --out " + bench.string() +
                                 " --data " + (dir_ / "photos").string() + " --cache " + (dir_ / "cache").string() +
                                 " --vocab " + vocab.string() + " --export-features " + exported.string());
  EXPECT_NE(report.find("full default search"), std::string::npos) << report;
  MustRun(oxbow + " index build --features " + exported.string() + " --vocab " + vocab.string() + " --out " + built.string());

  std::vector<sift::FeatureSet> queries;
  for (const int k : {0, 17, 123, 299}) {
    auto file = sift::ReadFeatureFile((exported / ("s" + std::to_string(k) + ".oxfeat")).string());
    ASSERT_TRUE(file) << file.error().ToString();
    queries.push_back(std::move(file->features));
  }

  index::IndexOptions options;
  options.num_threads = 2;
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
    auto opened = index::ImageIndex::Open(bench.string(), options);  // from the checkpoint written at close
    ASSERT_TRUE(opened) << opened.error().ToString();
    EXPECT_EQ((*opened)->Stats().num_images, static_cast<uint64_t>(kImages));
    for (size_t i = 0; i < queries.size(); ++i) EXPECT_EQ(Ask(**opened, queries[i]), expected[i]) << "query " << i;
    ASSERT_TRUE((*opened)->Add("extra", queries[1], {}));
    ASSERT_TRUE((*opened)->Remove("extra"));
  }
  auto reopened = index::ImageIndex::Open(bench.string(), options);
  ASSERT_TRUE(reopened) << reopened.error().ToString();
  for (size_t i = 0; i < queries.size(); ++i) EXPECT_EQ(Ask(**reopened, queries[i]), expected[i]) << "query " << i;
#endif
}

}  // namespace
}  // namespace oxbow
