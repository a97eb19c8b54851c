// The checkpointer (storage/checkpointer.h): checkpoints at close and in the background, segment
// files written once, the background check of the geometry files, a kill at every stage.
#include "index/storage/test_support.h"

#include <gtest/gtest.h>

namespace oxbow::index {
namespace {

using namespace test_support;  // NOLINT(google-build-using-namespace): the tests' shared fixtures

class CheckpointerTest : public CheckpointFixture {};
TEST_F(CheckpointerTest, CloseWritesACheckpointThatOpenUsesWithoutRebuilding) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 30; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
  }
  const std::vector<std::string> written = CheckpointFiles(dir_);
  EXPECT_EQ(written, (std::vector<std::string>{"geometry-1-0.oxck", "postings-1.oxck", "segment-1-0.oxck",
                                               "segment-1-1.oxck"}));
  // Reopened with nothing changed: no new checkpoint at open or close.
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    ExpectEqualsFresh(**index, Range(0, 30));
  }
  EXPECT_EQ(CheckpointFiles(dir_), written);
}

// A checkpoint writes only the postings segments new since the previous one: a segment already in a
// file of the previous manifest is named again, the file left as it was (same inode, same bytes).
TEST_F(CheckpointerTest, CheckpointsWriteOnlyTheSegmentsNewSinceThePreviousOne) {
  IndexOptions options;
  options.checkpoint_changes = 5;
  std::vector<sift::FeatureSet> images;
  images.reserve(10);
  for (int i = 0; i < 10; ++i) images.push_back(Image(i));
  const auto batch_of = [&](int begin) {
    std::vector<BatchImage> batch;
    batch.reserve(5);
    for (int i = begin; i < begin + 5; ++i) batch.push_back({NumberedId("i", i), &images[i], {}, {}, {}});
    return batch;
  };
  // Waits (at most 60 s) for a checkpoint of generation `g`, then gives its segment files.
  const auto wait_for = [&](int g) {
    const std::string head = NumberedId("postings-", g) + ".oxck";
    for (int t = 0; t < 600 && !fs::exists(dir_ / head); ++t) std::this_thread::sleep_for(std::chrono::milliseconds(100));
    EXPECT_TRUE(fs::exists(dir_ / head)) << "no checkpoint " << g << " within 60 s";
    return SegmentFiles(dir_);
  };
  auto index = CreateIndex(options);
  for (const auto& r : index->AddBatch(batch_of(0))) ASSERT_TRUE(r) << r.error().ToString();
  const std::vector<std::string> first = wait_for(1);
  ASSERT_EQ(first, (std::vector<std::string>{"segment-1-0.oxck"}));
  struct stat before{};
  ASSERT_EQ(::stat((dir_ / first[0]).c_str(), &before), 0);
  for (const auto& r : index->AddBatch(batch_of(5))) ASSERT_TRUE(r) << r.error().ToString();
  EXPECT_EQ(wait_for(2), (std::vector<std::string>{"segment-1-0.oxck", "segment-2-0.oxck"}));
  struct stat after{};
  ASSERT_EQ(::stat((dir_ / first[0]).c_str(), &after), 0);
  EXPECT_EQ(after.st_ino, before.st_ino);
  EXPECT_EQ(after.st_mtim.tv_nsec, before.st_mtim.tv_nsec);
  index.reset();
  auto reopened = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(reopened) << reopened.error().ToString();
  ExpectEqualsFresh(**reopened, Range(0, 10));
}

TEST_F(CheckpointerTest, GeometryIsCheckedInSchedIdleAndCheckpointsAreNot) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 30; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
  }
  // sched_getscheduler(0) is the calling thread's policy on Linux.
  std::atomic<int> verifying_policy{-2};
  std::atomic<int> writing_policy{-2};
  SetCheckpointStageHookForTesting([&](std::string_view stage) {
    if (stage == "verifying-geometry") verifying_policy = sched_getscheduler(0);
    if (stage == "files-written") writing_policy = sched_getscheduler(0);
  });
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    for (int wait = 0; wait < 1000 && verifying_policy == -2; ++wait) {
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    ASSERT_TRUE((*index)->Add("late", Image(30), {}));
  }  // closing writes a checkpoint with the new image
  SetCheckpointStageHookForTesting(nullptr);
  EXPECT_EQ(verifying_policy.load(), SCHED_IDLE);
  EXPECT_EQ(writing_policy.load(), SCHED_OTHER);
  EXPECT_EQ(sched_getscheduler(0), SCHED_OTHER);
}

// While a search runs, the check of the geometry files waits (it competes for the disk and the memory
// bus, which SCHED_IDLE does not share out). A search is held inside its filter; the check, let go
// while it is held, must not finish until the search does; then it finishes.
TEST_F(CheckpointerTest, GeometryCheckWaitsWhileASearchRuns) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 30; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
  }
  std::promise<void> start_check;
  std::shared_future<void> check_may_start = start_check.get_future().share();
  std::atomic<bool> checked{false};
  SetCheckpointStageHookForTesting([&, check_may_start](std::string_view stage) {
    if (stage == "verifying-geometry") check_may_start.wait_for(std::chrono::seconds(60));
    if (stage == "geometry-verified") checked = true;
  });
  class HoldingFilter final : public ImageFilter {
   public:
    std::promise<void> entered;
    std::shared_future<void> release;
    mutable std::once_flag once;
    bool Matches(const ImageRecord&) const override {
      std::call_once(once, [this] { const_cast<std::promise<void>&>(entered).set_value(); });
      release.wait_for(std::chrono::seconds(60));
      return true;
    }
  };
  std::promise<void> release_search;
  auto filter = std::make_shared<HoldingFilter>();
  filter->release = release_search.get_future().share();
  std::future<void> entered = filter->entered.get_future();
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    QueryOptions options;
    options.filter = filter;
    std::thread search([&] { EXPECT_TRUE((*index)->Query(Image(3), options)); });
    ASSERT_EQ(entered.wait_for(std::chrono::seconds(60)), std::future_status::ready);
    start_check.set_value();  // the search is running: the check starts now, and must wait for it
    // Unpaused, 30 images' files are checked in about a millisecond.
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
    EXPECT_FALSE(checked.load()) << "the geometry check went on while a search ran";
    release_search.set_value();
    search.join();
    for (int wait = 0; wait < 6000 && !checked; ++wait) std::this_thread::sleep_for(std::chrono::milliseconds(10));
    EXPECT_TRUE(checked.load()) << "the geometry check did not finish once the search had";
  }
  SetCheckpointStageHookForTesting(nullptr);
}

// Within a second of a search's end the check reads at most one block per 50 ms (VerifyParts): its first
// read comes no sooner than 50 ms after it starts (or a second after the search, whichever is first).
TEST_F(CheckpointerTest, GeometryCheckSlowsRightAfterASearch) {
  using Clock = std::chrono::steady_clock;
  {
    auto index = CreateIndex();
    for (int i = 0; i < 30; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
  }
  std::promise<void> start_check;
  std::shared_future<void> check_may_start = start_check.get_future().share();
  std::mutex mutex;
  std::optional<Clock::time_point> released, first_read;
  std::atomic<bool> checked{false};
  SetCheckpointStageHookForTesting([&, check_may_start](std::string_view stage) {
    if (stage == "verifying-geometry") {
      check_may_start.wait_for(std::chrono::seconds(60));
      std::lock_guard<std::mutex> lock(mutex);
      released = Clock::now();
    }
    if (stage == "geometry-read") {
      std::lock_guard<std::mutex> lock(mutex);
      if (!first_read) first_read = Clock::now();
    }
    if (stage == "geometry-verified") checked = true;
  });
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    const Clock::time_point search_began = Clock::now();
    ASSERT_TRUE((*index)->Query(Image(3), {}));
    start_check.set_value();
    for (int wait = 0; wait < 6000 && !checked; ++wait) std::this_thread::sleep_for(std::chrono::milliseconds(10));
    ASSERT_TRUE(checked.load()) << "the geometry check did not finish";
    std::lock_guard<std::mutex> lock(mutex);
    ASSERT_TRUE(released && first_read);
    const Clock::time_point earliest = std::min(*released + std::chrono::milliseconds(50), search_began + std::chrono::seconds(1));
    EXPECT_GE(*first_read, earliest - std::chrono::milliseconds(1))
        << "read " << std::chrono::duration<double, std::milli>(*first_read - *released).count()
        << " ms after the check started, right after a search";
  }
  SetCheckpointStageHookForTesting(nullptr);
}

// Without any use, the checkpointer verifies every geometry file after open and rewrites a damaged
// one while the index stays open.
TEST_F(CheckpointerTest, GeometryFilesAreVerifiedInTheBackgroundAfterOpen) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
  }
  DamageGeometryData(dir_ / "geometry-1-0.oxck");
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  const std::vector<std::string> rewritten = {"geometry-2-0.oxck", "postings-2.oxck"};
  for (int i = 0; i < 600 && HeadAndGeometryFiles(dir_) != rewritten; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  EXPECT_EQ(HeadAndGeometryFiles(dir_), rewritten) << "no rewrite within 60 s of open";
  ExpectEqualsFresh(**index, Range(0, 20));
}

// Checkpoints do not wait for that check: on cores kept busy its SCHED_IDLE thread may not run for
// minutes (held back here). A checkpoint meanwhile keeps the geometry file not checked yet.
TEST_F(CheckpointerTest, CheckpointsDoNotWaitForTheBackgroundCheckOfTheGeometryFiles) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
  }
  ASSERT_EQ(HeadAndGeometryFiles(dir_), (std::vector<std::string>{"geometry-1-0.oxck", "postings-1.oxck"}));
  // A later checkpoint was committed (postings-1 deleted), and it kept the file not checked yet.
  const auto checkpointed = [&] {
    const std::vector<std::string> files = CheckpointFiles(dir_);
    return std::find(files.begin(), files.end(), "postings-1.oxck") == files.end() &&
           std::find(files.begin(), files.end(), "geometry-1-0.oxck") != files.end();
  };
  {
    std::promise<void> release = HoldBackGeometryVerification();
    IndexOptions options;
    options.checkpoint_changes = 1;
    auto index = ImageIndex::Open(dir_.string(), options);
    ASSERT_TRUE(index) << index.error().ToString();
    for (int i = 20; i < 25; ++i) ASSERT_TRUE((*index)->Add(NumberedId("i", i), Image(i), {}));
    for (int i = 0; i < 300 && !checkpointed(); ++i) std::this_thread::sleep_for(std::chrono::milliseconds(100));
    EXPECT_TRUE(checkpointed()) << "no checkpoint within 30 s while the geometry check waited";
    release.set_value();
    index->reset();
    SetCheckpointStageHookForTesting(nullptr);
  }
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  ExpectEqualsFresh(**index, Range(0, 25));
  EXPECT_TRUE(checkpointed());
}

TEST_F(CheckpointerTest, KillAtEveryStageOfACheckpointLosesNothing) {
  SKIP_KILL_TEST_UNDER_TSAN();
  for (const std::string stage : {"file-unsynced", "segment-written", "files-written", "manifest-committed", "cleaned"}) {
    SCOPED_TRACE(stage);
    fs::remove_all(dir_);
    {
      auto index = CreateIndex();
      for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
    }
    InChildThenKill(
        [&](ImageIndex& index) {
          for (int i = 20; i < 30; ++i) ASSERT_TRUE(index.Add(NumberedId("i", i), Image(i), {}));
          ASSERT_TRUE(index.Remove("i2"));
        },
        stage);
    std::vector<int> live = Range(0, 30);
    live.erase(live.begin() + 2);
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    ExpectEqualsFresh(**index, live);
    // Whichever manifest is committed, the open deleted every file it does not name.
    // Segment files: those of generation 1 the new manifest still names, and new ones of generation 2.
    const bool committed = stage == "manifest-committed" || stage == "cleaned";
    const std::vector<std::string> expected =
        committed ? std::vector<std::string>{"geometry-1-0.oxck", "geometry-2-0.oxck", "postings-2.oxck"}
                  : std::vector<std::string>{"geometry-1-0.oxck", "postings-1.oxck"};
    EXPECT_EQ(HeadAndGeometryFiles(dir_), expected);
    for (const std::string& segment : SegmentFiles(dir_)) {
      EXPECT_TRUE(segment.starts_with("segment-1-") || (committed && segment.starts_with("segment-2-"))) << segment;
    }
  }
}

TEST_F(CheckpointerTest, BackgroundCheckpointWhileWritingIsConsistent) {
  SKIP_KILL_TEST_UNDER_TSAN();
  CreateIndex();
  IndexOptions options;
  options.checkpoint_changes = 4;
  InChildThenKill([&](ImageIndex& index) {
    for (int i = 0; i < 40; ++i) ASSERT_TRUE(index.Add(NumberedId("i", i), Image(i), {}));
    ASSERT_TRUE(index.Remove("i7"));
    // Wait (at most 60 s) for a background checkpoint after the one of the open's rebuild (there was
    // none before), then die without closing.
    const auto later_checkpoint = [&] {
      const auto files = CheckpointFiles(dir_);
      return std::any_of(files.begin(), files.end(),
                         [](const std::string& f) { return f.starts_with("postings-") && f != "postings-1.oxck"; });
    };
    for (int t = 0; t < 600 && !later_checkpoint(); ++t) std::this_thread::sleep_for(std::chrono::milliseconds(100));
    ASSERT_TRUE(later_checkpoint());
  }, "", options);
  std::vector<int> live = Range(0, 40);
  live.erase(live.begin() + 7);
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  // Opened from a background checkpoint (no rebuild: no generation above the last one written).
  const auto files = CheckpointFiles(dir_);
  EXPECT_EQ(std::count_if(files.begin(), files.end(), [](const std::string& f) { return f.starts_with("postings-"); }), 1);
  ExpectEqualsFresh(**index, live);
}

}  // namespace
}  // namespace oxbow::index
