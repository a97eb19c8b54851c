// Geometry parts (storage/geometry_parts.h): damaged or truncated geometry found on use and never
// served, images moved to the files their checkpoint wrote, files and descriptors bounded under churn.
#include "index/storage/test_support.h"

#include <gtest/gtest.h>

namespace oxbow::index {
namespace {

using namespace test_support;  // NOLINT(google-build-using-namespace): the tests' shared fixtures

class GeometryPartsTest : public CheckpointFixture {
 protected:
  // Body of DamagedGeometryDataIsFoundOnFirstUseAndNeverServed for geometry files of `version`.
  void ExpectDamagedGeometryDataNeverServed(uint32_t version);
};
// Every stored keypoint and word of images i0..i(n-1).
std::vector<std::pair<std::vector<float>, std::vector<uint32_t>>> AllFeatures(const ImageIndex& index, int n) {
  std::vector<std::pair<std::vector<float>, std::vector<uint32_t>>> out;
  for (int i = 0; i < n; ++i) {
    auto features = FeaturesOf(index, NumberedId("i", i));
    EXPECT_TRUE(features) << features.error().ToString();
    if (!features) return out;
    std::vector<float> keypoints;
    for (const sift::Keypoint& k : features->keypoints) keypoints.insert(keypoints.end(), {k.x, k.y, k.scale, k.orientation});
    out.emplace_back(std::move(keypoints), features->words);
  }
  return out;
}

// Open checks a geometry file's size and image table only; its data is checked on use (each image's
// checksum, or the whole file for the versions without per-image sums that older builds wrote). Damaged
// feature data is never served: whichever comes first (a query's use, or the background verification
// after open), the images come from the catalogue, and the next checkpoint rewrites them.
TEST_F(GeometryPartsTest, DamagedGeometryDataIsFoundOnFirstUseAndNeverServed) {
  for (const uint32_t version : {3u, 1u}) {
    SCOPED_TRACE("geometry format version " + std::to_string(version));
    fs::remove_all(dir_);
    ExpectDamagedGeometryDataNeverServed(version);
  }
}

void GeometryPartsTest::ExpectDamagedGeometryDataNeverServed(uint32_t version) {
  std::vector<std::pair<std::vector<float>, std::vector<uint32_t>>> before;
  {
    SetGeometryFormatVersionForTesting(version);
    auto index = CreateIndex();
    for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
    before = AllFeatures(*index, 20);
  }
  SetGeometryFormatVersionForTesting(3);
  ASSERT_EQ(HeadAndGeometryFiles(dir_), (std::vector<std::string>{"geometry-1-0.oxck", "postings-1.oxck"}));
  const std::vector<std::string> segments = SegmentFiles(dir_);
  DamageGeometryData(dir_ / "geometry-1-0.oxck");
  {
    // The background verification waits until the images were used: their use finds the damage.
    std::promise<void> used = HoldBackGeometryVerification();
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString() << " (open must not read the geometry data)";
    EXPECT_EQ(AllFeatures(**index, 20), before);
    ExpectEqualsFresh(**index, Range(0, 20));
    used.set_value();
    index->reset();
    SetCheckpointStageHookForTesting(nullptr);
  }
  // The damaged file was replaced by a new one holding its images (the postings were sound: their
  // segment files are kept).
  EXPECT_EQ(HeadAndGeometryFiles(dir_), (std::vector<std::string>{"geometry-2-0.oxck", "postings-2.oxck"}));
  EXPECT_EQ(SegmentFiles(dir_), segments);
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    EXPECT_EQ(AllFeatures(**index, 20), before);
    ExpectEqualsFresh(**index, Range(0, 20));
  }
  EXPECT_EQ(HeadAndGeometryFiles(dir_), (std::vector<std::string>{"geometry-2-0.oxck", "postings-2.oxck"}));
  EXPECT_EQ(SegmentFiles(dir_), segments);
}

// After a background checkpoint, the images it wrote view its geometry files instead of the copies
// Add kept in memory (an index that ingested 1M images would hold 17 GB of them): their
// memory leaves IndexStats::geometry_bytes, and features and searches stay the same. Damage to such a
// file is found on use and never served, and the next checkpoint rewrites it, as for a file an open loaded.
TEST_F(GeometryPartsTest, ImagesViewTheGeometryFilesTheirCheckpointWrote) {
  IndexOptions options;
  options.checkpoint_changes = 20;
  std::promise<void> go;
  std::shared_future<void> may_commit = go.get_future().share();
  std::atomic<int> viewed{0};
  SetCheckpointStageHookForTesting([&, may_commit](std::string_view stage) {
    if (stage == "files-written") may_commit.wait_for(std::chrono::seconds(60));
    if (stage == "geometry-viewed") ++viewed;
  });
  {
    auto index = CreateIndex(options);
    std::vector<sift::FeatureSet> images;
    images.reserve(20);
    for (int i = 0; i < 20; ++i) images.push_back(Image(i));
    std::vector<BatchImage> batch;
    batch.reserve(20);
    for (int i = 0; i < 20; ++i) batch.push_back({NumberedId("i", i), &images[i], {}, {}, {}});
    for (const auto& r : index->AddBatch(batch)) ASSERT_TRUE(r) << r.error().ToString();
    // The checkpoint's files are written, not committed: the images are still in memory.
    const auto before = AllFeatures(*index, 20);
    size_t features = 0;
    for (const auto& image : images) features += image.keypoints.size();
    EXPECT_GE(index->Stats().geometry_bytes, features * kPackedFeatureBytes);
    go.set_value();
    for (int t = 0; t < 600 && viewed == 0; ++t) std::this_thread::sleep_for(std::chrono::milliseconds(100));
    ASSERT_EQ(viewed.load(), 1) << "no checkpoint within 60 s";
    EXPECT_EQ(index->Stats().geometry_bytes, 20 * sizeof(PackedFeatures));
    EXPECT_EQ(AllFeatures(*index, 20), before);
    ExpectEqualsFresh(*index, Range(0, 20));
    // Damaged under the running index: each image's check finds it, the catalogue serves them.
    ASSERT_EQ(HeadAndGeometryFiles(dir_), (std::vector<std::string>{"geometry-1-0.oxck", "postings-1.oxck"}));
    DamageGeometryData(dir_ / "geometry-1-0.oxck");
    EXPECT_EQ(AllFeatures(*index, 20), before);
    ExpectEqualsFresh(*index, Range(0, 20));
  }
  SetCheckpointStageHookForTesting(nullptr);
  // Close wrote a checkpoint without the damaged file.
  EXPECT_EQ(HeadAndGeometryFiles(dir_), (std::vector<std::string>{"geometry-2-0.oxck", "postings-2.oxck"}));
  auto reopened = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(reopened) << reopened.error().ToString();
  ExpectEqualsFresh(**reopened, Range(0, 20));
}

// A remove or replace of an image whose checkpoint data is damaged, before anything used it, takes
// its words from its catalogue row before deleting that row: the statistics stay exact.
TEST_F(GeometryPartsTest, RemovingADamagedImageBeforeItsFirstUseKeepsTheIndexExact) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
  }
  DamageGeometryData(dir_ / "geometry-1-0.oxck");  // the data of the last images (i12 and i15 among them)
  std::vector<int> live = Range(0, 20);
  live.erase(live.begin() + 15);
  {
    std::promise<void> done = HoldBackGeometryVerification();
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    EXPECT_TRUE((*index)->Remove("i15"));
    EXPECT_TRUE((*index)->Replace("i12", Image(12), {}));
    ExpectEqualsFresh(**index, live);
    done.set_value();
    index->reset();
    SetCheckpointStageHookForTesting(nullptr);
  }
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  ExpectEqualsFresh(**index, live);
}

// Descriptors open in this process.
size_t OpenDescriptors() {
  size_t n = 0;
  for ([[maybe_unused]] const auto& item : fs::directory_iterator("/proc/self/fd")) ++n;
  return n;
}

// Add / replace / remove churn over a few ids with a checkpoint every few changes: the geometry files
// of removed and replaced images are dropped or compacted, so the files on disk and the descriptors
// their mappings keep stay bounded (each checkpoint wrote a new file that no later one dropped), and a
// reopen from the compacted checkpoint serves the same results.
TEST_F(GeometryPartsTest, GeometryFilesAndDescriptorsStayBoundedUnderChurn) {
  IndexOptions options;
  options.checkpoint_changes = 4;
  std::atomic<int> checkpoints{0};
  SetCheckpointStageHookForTesting([&](std::string_view stage) {
    if (stage == "geometry-viewed") ++checkpoints;
  });
  const size_t descriptors_before = OpenDescriptors();
  const auto geometry_files = [&] {
    const std::vector<std::string> files = CheckpointFiles(dir_);
    return static_cast<size_t>(
        std::count_if(files.begin(), files.end(), [](const std::string& f) { return f.starts_with("geometry-"); }));
  };
  constexpr int kIds = 8;
  std::set<int> live;
  size_t most_files = 0, most_descriptors = 0;
  {
    auto index = CreateIndex(options);
    std::mt19937_64 rng(5);
    for (int round = 0; round < 50; ++round) {
      const int seen = checkpoints.load();
      for (int k = 0; k < 4; ++k) {
        const int i = static_cast<int>(rng() % kIds);
        const std::string id = NumberedId("i", i);
        if (!live.count(i)) {
          ASSERT_TRUE(index->Add(id, Image(i), {}));
          live.insert(i);
        } else if (rng() % 2 == 0) {
          ASSERT_TRUE(index->Replace(id, Image(i), {}));
        } else {
          ASSERT_TRUE(index->Remove(id));
          live.erase(i);
        }
      }
      for (int t = 0; t < 600 && checkpoints.load() == seen; ++t) std::this_thread::sleep_for(std::chrono::milliseconds(100));
      ASSERT_GT(checkpoints.load(), seen) << "no checkpoint within 60 s in round " << round;
      most_files = std::max(most_files, geometry_files());
      most_descriptors = std::max(most_descriptors, OpenDescriptors());
    }
    // At most one file per live image (each file kept is at least half live) and the newest one.
    EXPECT_LE(most_files, size_t{kIds} + 1);
    // The files' descriptors, the catalogue's and the folder lock's.
    EXPECT_LE(most_descriptors, descriptors_before + kIds + 1 + 8);
    ExpectEqualsFresh(*index, std::vector<int>(live.begin(), live.end()));
  }
  SetCheckpointStageHookForTesting(nullptr);
  EXPECT_LE(geometry_files(), size_t{kIds} + 1);
  auto index = ImageIndex::Open(dir_.string(), options);
  ASSERT_TRUE(index) << index.error().ToString();
  ExpectEqualsFresh(**index, std::vector<int>(live.begin(), live.end()));
}

// A geometry file truncated under the running index, after or before its background check, is never
// read past its end (through the mapping that would kill the process with SIGBUS): its images are
// served from the catalogue. Run in a child, whose death would fail the parent's check.
TEST_F(GeometryPartsTest, AGeometryFileTruncatedUnderTheRunningIndexIsNeverReadPastItsEnd) {
  SKIP_KILL_TEST_UNDER_TSAN();
  std::vector<std::pair<std::vector<float>, std::vector<uint32_t>>> before;
  {
    auto index = CreateIndex();
    for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
    before = AllFeatures(*index, 20);
  }
  const fs::path geometry = dir_ / "geometry-1-0.oxck";
  const fs::path copy = dir_.string() + "_geometry";
  fs::copy_file(geometry, copy, fs::copy_options::overwrite_existing);
  for (const bool checked_first : {true, false}) {
    SCOPED_TRACE(checked_first ? "truncated after the background check" : "truncated before it");
    fs::copy_file(copy, geometry, fs::copy_options::overwrite_existing);
    const pid_t pid = fork();
    ASSERT_GE(pid, 0);
    if (pid == 0) {
      std::promise<void> checked;
      std::shared_future<void> checked_future = checked.get_future().share();
      std::atomic<bool> released{false};
      SetCheckpointStageHookForTesting([&, checked_first](std::string_view stage) {
        if (stage == "geometry-verified" && checked_first && !released.exchange(true)) checked.set_value();
        if (stage == "verifying-geometry" && !checked_first) checked_future.wait_for(std::chrono::seconds(60));
      });
      auto index = ImageIndex::Open(dir_.string());
      if (!index) ::_exit(2);
      if (checked_first && checked_future.wait_for(std::chrono::seconds(60)) != std::future_status::ready) ::_exit(3);
      fs::resize_file(geometry, fs::file_size(geometry) / 2);
      if (AllFeatures(**index, 20) != before) ::_exit(4);
      auto similar = (*index)->QuerySimilar("i3", Opts(5, 10));
      if (!similar || similar->results.empty() || similar->results[0].id != "i3") ::_exit(5);
      if (!checked_first) checked.set_value();
      ::_exit(0);
    }
    int status = 0;
    ASSERT_EQ(::waitpid(pid, &status, 0), pid);
    EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0)
        << "child " << (WIFSIGNALED(status) ? "killed by signal " + std::to_string(WTERMSIG(status))
                                            : "exit status " + std::to_string(WEXITSTATUS(status)));
  }
  fs::remove(copy);
}

// Geometry bytes changed on disk after the background check passed are not served either: each use
// of an image checks its own checksum.
TEST_F(GeometryPartsTest, GeometryDamagedAfterItsBackgroundCheckIsNeverServed) {
  std::vector<std::pair<std::vector<float>, std::vector<uint32_t>>> before;
  {
    auto index = CreateIndex();
    for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
    before = AllFeatures(*index, 20);
  }
  std::promise<void> checked;
  std::atomic<bool> released{false};
  SetCheckpointStageHookForTesting([&](std::string_view stage) {
    if (stage == "geometry-verified" && !released.exchange(true)) checked.set_value();
  });
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    ASSERT_EQ(checked.get_future().wait_for(std::chrono::seconds(60)), std::future_status::ready);
    DamageGeometryData(dir_ / "geometry-1-0.oxck");
    EXPECT_EQ(AllFeatures(**index, 20), before);
    ExpectEqualsFresh(**index, Range(0, 20));
  }
  SetCheckpointStageHookForTesting(nullptr);
  // The next checkpoint (at close) rewrote the damaged file.
  EXPECT_EQ(HeadAndGeometryFiles(dir_), (std::vector<std::string>{"geometry-2-0.oxck", "postings-2.oxck"}));
}

}  // namespace
}  // namespace oxbow::index
