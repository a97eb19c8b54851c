// Test support of oxbow_index's tests (index/*_test.cc, index/storage/*_test.cc): an index over a
// vocabulary of kWords random words with features made from its centroids (IndexFixture), and the
// checkpoint helpers (CheckpointFixture: deterministic images, a child process killed at a checkpoint
// stage, comparison with a fresh index). Header-only; included by test files only.
#pragma once

#include "index/image_index.h"

#include <gtest/gtest.h>
#include <sqlite3.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <concepts>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <map>
#include <numeric>
#include <optional>
#include <numbers>
#include <random>
#include <set>
#include <thread>

#include <csignal>
#include <functional>
#include <future>
#include <string_view>
#include <sched.h>
#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include "index/storage/catalogue.h"
#include "index/storage/checkpoint.h"
#include "index/storage/feature_store.h"
#include "index/search/pipeline.h"
#include "index/search/source.h"
#include "tests/support/temp_dir.h"

namespace oxbow::index::test_support {

namespace fs = std::filesystem;
inline constexpr int kWords = 256;

// Image `id`'s stored keypoints and words, as a search reads them (kNotFound).
inline Result<search::RegionFeatures> FeaturesOf(const ImageIndex& index, const std::string& id) {
  const std::unique_ptr<search::Source> source = index.OpenSearch();
  auto ref = source->Find(id);
  if (!ref) return std::unexpected(ref.error());
  if (!*ref) return Fail(ErrorCode::kNotFound, "no image with id '" + id + "'");
  constexpr float kAll = std::numeric_limits<float>::infinity();
  const std::array<float, 4> everywhere = {-kAll, -kAll, kAll, kAll};
  auto features = source->Features(std::span(&**ref, 1), std::span(&everywhere, 1), {});
  if (!features) return std::unexpected(features.error());
  return std::move(features->front());
}

// `prefix` then `number` ("i7"): the ids of the tests' images. Appended rather than `"i" +
// std::to_string(n)`, on which GCC 12 reports a false -Wrestrict overlap once inlined.
inline std::string NumberedId(std::string_view prefix, std::integral auto number) {
  return std::string(prefix).append(std::to_string(number));
}

// A vocabulary of `words` random unit centroids (128 dimensions, RootSIFT) drawn from `seed`.
inline vocab::Vocabulary RandomVocabulary(uint64_t seed, int words, const std::string& settings) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<float> g(0, 1);
  std::vector<float> c(static_cast<size_t>(words) * 128);
  for (int w = 0; w < words; ++w) {
    double n = 0;
    for (int d = 0; d < 128; ++d) {
      c[w * 128 + d] = g(rng);
      n += c[w * 128 + d] * c[w * 128 + d];
    }
    for (int d = 0; d < 128; ++d) c[w * 128 + d] /= static_cast<float>(std::sqrt(n));
  }
  auto v = vocab::Vocabulary::FromCentroids(std::move(c), 128, sift::DescriptorKind::kRootSift, settings);
  EXPECT_TRUE(v.has_value()) << (v ? "" : v.error().ToString());
  return *v;
}

// A vocabulary of kWords random unit centroids; features are made by perturbing a centroid slightly so
// the quantiser is known to return that word.
class IndexFixture : public ::testing::Test {
 protected:
  static vocab::Vocabulary MakeVocabulary(uint64_t seed, const std::string& settings = "test-extractor/1") {
    return RandomVocabulary(seed, kWords, settings);
  }

  // Features with the given words at the given keypoints.
  sift::FeatureSet Features(const std::vector<uint32_t>& words, const std::vector<sift::Keypoint>& keypoints,
                            int width = 640, int height = 480) const {
    sift::FeatureSet f;
    f.image_width = width;
    f.image_height = height;
    f.kind = sift::DescriptorKind::kRootSift;
    f.keypoints = keypoints;
    const auto centroids = vocabulary_.centroids();
    for (uint32_t w : words) {
      f.descriptors.insert(f.descriptors.end(), centroids.begin() + w * 128, centroids.begin() + (w + 1) * 128);
    }
    return f;
  }

  // An image of n random features (word, position, scale, orientation).
  sift::FeatureSet RandomImage(std::mt19937_64& rng, int n, int width = 640, int height = 480) const {
    std::uniform_int_distribution<uint32_t> word(0, kWords - 1);
    std::uniform_real_distribution<float> x(0, static_cast<float>(width - 1)), y(0, static_cast<float>(height - 1));
    std::uniform_real_distribution<float> s(1.5f, 12.0f), o(0, 6.28f);
    std::vector<uint32_t> words;
    std::vector<sift::Keypoint> kps;
    for (int i = 0; i < n; ++i) {
      words.push_back(word(rng));
      kps.push_back({x(rng), y(rng), s(rng), o(rng), 1.0f, 0});
    }
    return Features(words, kps, width, height);
  }

  // `count` images of n random features each (RandomImage).
  std::vector<sift::FeatureSet> RandomImages(std::mt19937_64& rng, int count, int n) const {
    std::vector<sift::FeatureSet> out;
    out.reserve(static_cast<size_t>(count));
    for (int i = 0; i < count; ++i) out.push_back(RandomImage(rng, n));
    return out;
  }

  std::unique_ptr<ImageIndex> CreateIndex(const IndexOptions& options = {}) {
    auto index = ImageIndex::Create(dir_.string(), vocabulary_, "test-extractor/1", options);
    EXPECT_TRUE(index.has_value()) << (index ? "" : index.error().ToString());
    return std::move(*index);
  }

  // An index of images "a" and "b" (80 random features each) and 10 noise images; *query gets 30 of
  // a's features on the left half (x < 300, DoG responses +-a_response) then 70 of b's on the right
  // half (+-b_response).
  std::unique_ptr<ImageIndex> TwoObjectIndex(sift::FeatureSet* query, float a_response, float b_response) {
    auto index = CreateIndex();
    std::mt19937_64 rng(4);
    const auto a = RandomImage(rng, 80), b = RandomImage(rng, 80);
    EXPECT_TRUE(index->Add("a", a, {}));
    EXPECT_TRUE(index->Add("b", b, {}));
    for (int i = 0; i < 10; ++i) EXPECT_TRUE(index->Add(NumberedId("noise", i), RandomImage(rng, 80), {}));
    *query = Features({}, {}, 640, 480);
    auto append = [&](const sift::FeatureSet& src, size_t count, float x0, float response) {
      for (size_t i = 0; i < count; ++i) {
        sift::Keypoint k = src.keypoints[i];
        k.x = x0 + std::fmod(k.x, 290.0f);
        k.response = (i % 2 == 0 ? 1.0f : -1.0f) * response;  // the magnitude counts
        query->keypoints.push_back(k);
        const auto d = src.Descriptor(i);
        query->descriptors.insert(query->descriptors.end(), d.begin(), d.end());
      }
    };
    append(a, 30, 0, a_response);
    append(b, 70, 330, b_response);
    return index;
  }

  oxbow::testing::TempDir temp_;      // the test's folder (removed after it)
  fs::path dir_ = temp_ / "index";    // the index folder, made by CreateIndex
  vocab::Vocabulary vocabulary_ = MakeVocabulary(1);
};

inline QueryOptions Opts(int top_k, int rerank_depth, bool query_expansion = false,
                  std::optional<std::array<float, 4>> region = std::nullopt) {
  QueryOptions o;
  o.top_k = top_k;
  o.rerank_depth = rerank_depth;
  o.query_expansion = query_expansion;
  o.region = region;
  return o;
}

inline ImageInfo Info(std::string source_path = "", std::string metadata_json = "", std::string settings = "") {
  ImageInfo info;
  info.source_path = std::move(source_path);
  info.metadata_json = std::move(metadata_json);
  info.extractor_settings = std::move(settings);
  return info;
}

inline std::map<std::string, double> ScoresById(const QueryResponse& r) {
  std::map<std::string, double> out;
  for (const auto& x : r.results) out[x.id] = x.score;
  return out;
}

inline void ExecSql(const fs::path& db_path, const std::string& sql) {
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open(db_path.c_str(), &db), SQLITE_OK);
  char* error = nullptr;
  EXPECT_EQ(sqlite3_exec(db, sql.c_str(), nullptr, nullptr, &error), SQLITE_OK) << (error ? error : "");
  sqlite3_free(error);
  sqlite3_close(db);
}

inline std::string FileBytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

// ==== Checkpoints (checkpoint.h) =====================================================================

// Checkpoint files in the index folder, sorted.
inline std::vector<std::string> CheckpointFiles(const fs::path& dir) {
  std::vector<std::string> out;
  for (const auto& item : fs::directory_iterator(dir)) {
    const std::string name = item.path().filename().string();
    if (name.find(".oxck") != std::string::npos) out.push_back(name);
  }
  std::sort(out.begin(), out.end());
  return out;
}

// CheckpointFiles without the postings' segment files (their number depends on merges), for tests of
// the geometry files and the manifest.
inline std::vector<std::string> HeadAndGeometryFiles(const fs::path& dir) {
  std::vector<std::string> out = CheckpointFiles(dir);
  std::erase_if(out, [](const std::string& name) { return name.starts_with("segment-"); });
  return out;
}

// The segment files among CheckpointFiles.
inline std::vector<std::string> SegmentFiles(const fs::path& dir) {
  std::vector<std::string> out = CheckpointFiles(dir);
  std::erase_if(out, [](const std::string& name) { return !name.starts_with("segment-"); });
  return out;
}

// The kill tests fork a child that opens the index, which starts threads: ThreadSanitizer cannot run a
// child starting threads after fork() in a multi-threaded process (it dies at once), so under it they
// are skipped, saying so; the normal and ASan builds run them.
#if defined(__SANITIZE_THREAD__)
#define SKIP_KILL_TEST_UNDER_TSAN() \
  GTEST_SKIP() << "fork() of a multi-threaded process: not supported by ThreadSanitizer (run in the normal and ASan builds)"
#else
#define SKIP_KILL_TEST_UNDER_TSAN() static_cast<void>(0)
#endif

class CheckpointFixture : public IndexFixture {
 protected:
  // Images i0..i(n-1), deterministic.
  sift::FeatureSet Image(int i) const {
    std::mt19937_64 rng(1000 + static_cast<uint64_t>(i));
    return RandomImage(rng, 30 + i % 50);
  }
  // In a child process: opens the index, runs `body`, then dies by SIGKILL (no close, no checkpoint),
  // at the end of body or at checkpoint stage `kill_at`.
  void InChildThenKill(const std::function<void(ImageIndex&)>& body, const std::string& kill_at = "",
                       const IndexOptions& options = {}) {
    const pid_t pid = fork();
    ASSERT_GE(pid, 0);
    if (pid == 0) {
      if (!kill_at.empty()) {
        SetCheckpointStageHookForTesting([kill_at](std::string_view stage) {
          if (stage == kill_at) ::raise(SIGKILL);
        });
      }
      auto index = ImageIndex::Open(dir_.string(), options);
      if (!index) ::_exit(2);
      body(**index);
      if (::testing::Test::HasFailure()) ::_exit(3);  // the parent's check of the exit status fails
      if (!kill_at.empty()) index->reset();  // close: writes the checkpoint, killed at `kill_at`
      ::raise(SIGKILL);
    }
    int status = 0;
    ASSERT_EQ(::waitpid(pid, &status, 0), pid);
    ASSERT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == SIGKILL) << "child status " << status;
  }
  // The scores of `index` equal those of a fresh index holding images `live` (exact statistics).
  void ExpectEqualsFresh(ImageIndex& index, const std::vector<int>& live) {
    const fs::path fresh_dir = temp_ / "fresh";
    {
      auto fresh = ImageIndex::Create(fresh_dir.string(), vocabulary_, "test-extractor/1");
      ASSERT_TRUE(fresh);
      for (const int i : live) ASSERT_TRUE((*fresh)->Add(NumberedId("i", i), Image(i), {}));
      EXPECT_EQ(index.Stats().num_images, live.size());
      std::mt19937_64 rng(77);
      for (int q = 0; q < 5; ++q) {
        const auto query = RandomImage(rng, 60);
        const auto a = index.Query(query, Opts(1000, 10));
        const auto b = (*fresh)->Query(query, Opts(1000, 10));
        ASSERT_TRUE(a && b);
        ASSERT_EQ(a->results.size(), b->results.size());
        for (size_t k = 0; k < a->results.size(); ++k) {
          EXPECT_EQ(a->results[k].id, b->results[k].id);
          EXPECT_NEAR(a->results[k].score, b->results[k].score, 1e-6);
          EXPECT_EQ(a->results[k].inliers, b->results[k].inliers);
        }
      }
    }
    fs::remove_all(fresh_dir);
  }
  // Until the returned promise is set (or for 60 s), the checkpointer of the next index opened waits
  // before it verifies the geometry files; reset the hook (SetCheckpointStageHookForTesting) after.
  static std::promise<void> HoldBackGeometryVerification() {
    std::promise<void> release;
    std::shared_future<void> released = release.get_future().share();
    SetCheckpointStageHookForTesting([released](std::string_view stage) {
      if (stage == "verifying-geometry") released.wait_for(std::chrono::seconds(60));
    });
    return release;
  }
  std::vector<int> Range(int begin, int end) {
    std::vector<int> out;
    for (int i = begin; i < end; ++i) out.push_back(i);
    return out;
  }
};

// Inverts every byte of the second half of a geometry file's feature data (its image table intact).
inline void DamageGeometryData(const fs::path& path) {
  std::fstream f(path, std::ios::in | std::ios::out | std::ios::binary);
  std::vector<char> bytes((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  ASSERT_GT(bytes.size(), 4000u);
  for (size_t i = bytes.size() / 2; i < bytes.size(); ++i) bytes[i] = static_cast<char>(~bytes[i]);
  f.seekp(0);
  f.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}

}  // namespace oxbow::index::test_support
