// Thumbnails: making them (sizes, colour, reduced decoding, errors), the SQLite store (round trip,
// persistence, other versions and damaged files refused) and the service's use of them (stored at add,
// replaced, deleted, stale entries not served, committed with their image across a kill -9).
#include "api/thumbnails.h"

#include <gtest/gtest.h>
#include <signal.h>
#include <sqlite3.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "api/service.h"
#include "tests/support/samples.h"
#include "tests/support/temp_dir.h"

namespace oxbow::api {
namespace {

using testing::ReadBytes;
using testing::SamplePath;

std::span<const uint8_t> AsBytes(const std::string& text) {
  return {reinterpret_cast<const uint8_t*>(text.data()), text.size()};
}

cv::Mat DecodeJpeg(const std::string& jpeg) {
  const cv::Mat raw(1, static_cast<int>(jpeg.size()), CV_8UC1, const_cast<char*>(jpeg.data()));
  return cv::imdecode(raw, cv::IMREAD_UNCHANGED);
}

TEST(MakeThumbnail, ScalesTheLongestSideDownNeverUpAndKeepsColour) {
  const auto bytes = ReadBytes(SamplePath("fruits.jpg"));  // 512 x 480, colour
  if (bytes.empty()) GTEST_SKIP() << "opencv-doc sample photos not installed";
  auto small = MakeThumbnail(bytes, 128, 80, {});
  ASSERT_TRUE(small) << small.error().ToString();
  EXPECT_EQ(small->width, 128);
  EXPECT_EQ(small->height, 120);
  const cv::Mat decoded = DecodeJpeg(small->jpeg);
  EXPECT_EQ(decoded.cols, 128);
  EXPECT_EQ(decoded.rows, 120);
  EXPECT_EQ(decoded.channels(), 3);
  auto same = MakeThumbnail(bytes, 2000, 80, {});
  ASSERT_TRUE(same);
  EXPECT_EQ(same->width, 512);
  EXPECT_EQ(same->height, 480);
  auto worse = MakeThumbnail(bytes, 128, 10, {});
  ASSERT_TRUE(worse);
  EXPECT_LT(worse->jpeg.size(), small->jpeg.size());  // quality is applied
}

TEST(MakeThumbnail, LargeJpegIsDecodedReducedToTheRightSize) {
  cv::Mat big(2000, 3000, CV_8UC3);
  cv::randu(big, cv::Scalar::all(0), cv::Scalar::all(255));
  std::vector<uchar> jpeg;
  ASSERT_TRUE(cv::imencode(".jpg", big, jpeg));
  auto thumb = MakeThumbnail(jpeg, 300, 80, {});
  ASSERT_TRUE(thumb) << thumb.error().ToString();
  EXPECT_EQ(thumb->width, 300);
  EXPECT_EQ(thumb->height, 200);
}

TEST(MakeThumbnail, AppliesTheExifOrientationAsTheExtractorDoes) {
  // A 64 x 48 JPEG whose EXIF Orientation 6 says "show rotated 90 degrees clockwise": the thumbnail is
  // upright (48 x 64), as sift::DecodeImage sees it, so regions in image pixels land where drawn.
  cv::Mat landscape(48, 64, CV_8UC3, cv::Scalar(40, 40, 40));
  landscape(cv::Rect(0, 0, 16, 16)).setTo(cv::Scalar(255, 255, 255));  // bright square top-left
  std::vector<uchar> plain;
  ASSERT_TRUE(cv::imencode(".jpg", landscape, plain));
  // APP1 "Exif": big-endian TIFF header, IFD0 with one entry: tag 0x0112 (Orientation), SHORT, 1, value 6.
  const std::string exif("\xFF\xE1\x00\x22" "Exif\0\0" "MM\x00\x2A\x00\x00\x00\x08" "\x00\x01"
                         "\x01\x12\x00\x03\x00\x00\x00\x01\x00\x06\x00\x00" "\x00\x00\x00\x00", 36);
  std::string jpeg(plain.begin(), plain.begin() + 2);
  jpeg += exif;
  jpeg.append(plain.begin() + 2, plain.end());
  auto thumb = MakeThumbnail(AsBytes(jpeg), 100, 90, {});
  ASSERT_TRUE(thumb) << thumb.error().ToString();
  EXPECT_EQ(thumb->width, 48);
  EXPECT_EQ(thumb->height, 64);
  const cv::Mat upright = DecodeJpeg(thumb->jpeg);
  ASSERT_EQ(upright.cols, 48);
  EXPECT_GT(upright.at<cv::Vec3b>(6, 40)[0], 200);  // the square is now top-right
  EXPECT_LT(upright.at<cv::Vec3b>(6, 6)[0], 100);
}

TEST(MakeThumbnail, RefusesBadInputWithErrors) {
  EXPECT_EQ(MakeThumbnail({}, 100, 80, {}).error().code, ErrorCode::kInvalidImage);
  EXPECT_EQ(MakeThumbnail(AsBytes("this is not an image at all"), 100, 80, {}).error().code, ErrorCode::kInvalidImage);
  const auto bytes = ReadBytes(SamplePath("box.png"));
  if (bytes.empty()) GTEST_SKIP() << "opencv-doc sample photos not installed";
  sift::DecodeOptions tight;
  tight.max_pixels = 1000;
  EXPECT_EQ(MakeThumbnail(bytes, 100, 80, tight).error().code, ErrorCode::kImageTooLarge);
  tight = {};
  tight.max_bytes = 100;
  EXPECT_EQ(MakeThumbnail(bytes, 100, 80, tight).error().code, ErrorCode::kImageTooLarge);
  EXPECT_EQ(MakeThumbnail(bytes, 0, 80, {}).error().code, ErrorCode::kInvalidArgument);
  EXPECT_EQ(MakeThumbnail(bytes, 100, 101, {}).error().code, ErrorCode::kInvalidArgument);
}

class ThumbnailStoreTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_FALSE(dir_.path().empty());
    path_ = dir_.path() + "/thumbnails.sqlite";
    cv::Mat image(30, 40, CV_8UC3, cv::Scalar(10, 200, 30));
    std::vector<uchar> jpeg;
    ASSERT_TRUE(cv::imencode(".jpg", image, jpeg));
    entry_.thumbnail.jpeg.assign(jpeg.begin(), jpeg.end());
    entry_.image_width = 400;
    entry_.image_height = 300;
    entry_.source = "http:photo.jpg";
  }
  oxbow::testing::TempDir dir_{"oxbow-thumbnail-store"};
  std::string path_;
  ThumbnailStore::Entry entry_;
};

TEST_F(ThumbnailStoreTest, RoundTripPersistsAndRemoves) {
  {
    auto store = ThumbnailStore::Open(path_);
    ASSERT_TRUE(store) << store.error().ToString();
    ASSERT_TRUE((*store)->Put("a b/c", entry_));
    auto missing = (*store)->Get("other");
    ASSERT_TRUE(missing);
    EXPECT_FALSE(missing->has_value());
  }
  auto store = ThumbnailStore::Open(path_);  // reopened: the entry was durable
  ASSERT_TRUE(store);
  auto got = (*store)->Get("a b/c");
  ASSERT_TRUE(got) << got.error().ToString();
  ASSERT_TRUE(got->has_value());
  const ThumbnailStore::Entry& stored = got->value();
  EXPECT_EQ(stored.thumbnail.jpeg, entry_.thumbnail.jpeg);
  EXPECT_EQ(stored.thumbnail.width, 40);  // read from the JPEG header
  EXPECT_EQ(stored.thumbnail.height, 30);
  EXPECT_EQ(stored.image_width, 400);
  EXPECT_EQ(stored.image_height, 300);
  EXPECT_EQ(stored.source, "http:photo.jpg");
  entry_.source = "replaced";
  ASSERT_TRUE((*store)->Put("a b/c", entry_));
  EXPECT_EQ((*store)->Get("a b/c")->value().source, "replaced");
  ASSERT_TRUE((*store)->Remove("a b/c"));
  EXPECT_FALSE((*store)->Get("a b/c")->has_value());
  EXPECT_TRUE((*store)->Remove("never there"));
}

TEST_F(ThumbnailStoreTest, PendingEntriesAreCommittedOrDropped) {
  auto store = ThumbnailStore::Open(path_);
  ASSERT_TRUE(store);
  ASSERT_TRUE((*store)->Put("a", entry_));
  ThumbnailStore::Entry next = entry_;
  next.source = "next";
  ASSERT_TRUE((*store)->PutPending("a", next, 7));
  ASSERT_TRUE((*store)->PutPending("b", next, 7));
  EXPECT_EQ((*store)->Get("a")->value().source, "http:photo.jpg");  // committed entry untouched
  EXPECT_FALSE((*store)->Get("b")->has_value());
  EXPECT_EQ((*store)->GetPending("a")->value().after_sequence, 7u);
  EXPECT_EQ(*(*store)->Ids(true), (std::vector<std::string>{"a", "b"}));
  ASSERT_TRUE((*store)->Commit("a"));
  ASSERT_TRUE((*store)->DropPending("b"));
  ASSERT_TRUE((*store)->Commit("never pending"));
  store->reset();
  store = ThumbnailStore::Open(path_);  // reopened: both were durable
  ASSERT_TRUE(store);
  EXPECT_EQ((*store)->Get("a")->value().source, "next");
  EXPECT_FALSE((*store)->Get("b")->has_value());
  EXPECT_TRUE((*store)->Ids(true)->empty());
  EXPECT_EQ(*(*store)->Ids(false), std::vector<std::string>{"a"});
}

TEST_F(ThumbnailStoreTest, RefusesAnotherSchemaVersion) {
  ASSERT_TRUE(ThumbnailStore::Open(path_));
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open(path_.c_str(), &db), SQLITE_OK);
  ASSERT_EQ(sqlite3_exec(db, "PRAGMA user_version=2", nullptr, nullptr, nullptr), SQLITE_OK);
  sqlite3_close(db);
  auto store = ThumbnailStore::Open(path_);
  ASSERT_FALSE(store);
  EXPECT_EQ(store.error().code, ErrorCode::kIncompatible);
  EXPECT_NE(store.error().message.find("version 2"), std::string::npos) << store.error().message;
}

TEST_F(ThumbnailStoreTest, RefusesADamagedFile) {
  {
    std::ofstream out(path_, std::ios::binary);
    out << std::string(8192, 'x');
  }
  auto store = ThumbnailStore::Open(path_);
  ASSERT_FALSE(store);
  EXPECT_EQ(store.error().code, ErrorCode::kCorruptData) << store.error().ToString();
}

TEST_F(ThumbnailStoreTest, AnEntryThatIsNotAJpegIsCorruptData) {
  auto store = ThumbnailStore::Open(path_);
  ASSERT_TRUE(store);
  entry_.thumbnail.jpeg = "garbage";
  ASSERT_TRUE((*store)->Put("bad", entry_));
  auto got = (*store)->Get("bad");
  ASSERT_FALSE(got);
  EXPECT_EQ(got.error().code, ErrorCode::kCorruptData);
}

// The service: thumbnails stored with adds, replaced with them, removed with deletes; an entry made for
// another image under the same id is not served.
TEST(ServiceThumbnails, FollowAddsReplacesAndDeletes) {
  if (!std::filesystem::exists(SamplePath("box_in_scene.png"))) GTEST_SKIP() << "opencv-doc sample photos not installed";
  oxbow::testing::TempDir dir("oxbow-service-thumbnails");
  const std::string vocab = dir.path() + "/vocab.oxvoc";
  ASSERT_TRUE(testing::BuildTestVocabulary({"box_in_scene.png", "graf1.png"}, 128, vocab));
  const std::string index_dir = dir.path() + "/index";
  auto service = Service::Open(index_dir, vocab, {});
  ASSERT_TRUE(service) << service.error().ToString();
  const auto scene = ReadBytes(SamplePath("box_in_scene.png"));  // 512 x 384
  const auto graf = ReadBytes(SamplePath("graf1.png"));          // 800 x 640
  AddImageRequest add;
  add.id = "x";
  add.image = scene;
  add.source_name = "http:scene.png";
  ASSERT_TRUE((*service)->AddImage(add));
  auto thumb = (*service)->GetThumbnail("x", 128);
  ASSERT_TRUE(thumb) << thumb.error().ToString();
  EXPECT_EQ(thumb->thumbnail.width, 128);
  EXPECT_EQ(thumb->thumbnail.height, 96);
  EXPECT_EQ((*service)->GetThumbnail("x", 15).error().code, ErrorCode::kInvalidArgument);
  EXPECT_EQ((*service)->GetThumbnail("x", 2049).error().code, ErrorCode::kInvalidArgument);
  thumb = (*service)->GetThumbnail("x", 2048);  // clamped to the stored 512
  ASSERT_TRUE(thumb);
  EXPECT_EQ(thumb->thumbnail.width, 512);
  EXPECT_EQ((*service)->GetThumbnail("nope", 128).error().code, ErrorCode::kNotFound);

  add.image = graf;
  add.replace = true;
  ASSERT_TRUE((*service)->AddImage(add));
  thumb = (*service)->GetThumbnail("x", 512);
  ASSERT_TRUE(thumb);
  EXPECT_EQ(thumb->thumbnail.width, 512);
  EXPECT_EQ(thumb->thumbnail.height, 410);  // graf1's shape now

  // A stale entry (made for a 512 x 384 image) under the id of the 800 x 640 one is not served; the
  // source "http:scene.png" is no file, so there is nothing to make one from.
  {
    auto store = ThumbnailStore::Open(index_dir + "/thumbnails.sqlite");
    ASSERT_TRUE(store);
    auto entry = (*store)->Get("x");
    ASSERT_TRUE(entry && entry->has_value());
    entry->value().image_width = 512;
    entry->value().image_height = 384;
    ASSERT_TRUE((*store)->Put("x", entry->value()));
  }
  EXPECT_EQ((*service)->GetThumbnail("x", 128).error().code, ErrorCode::kNotFound);

  ASSERT_TRUE((*service)->DeleteImage("x"));
  auto store = ThumbnailStore::Open(index_dir + "/thumbnails.sqlite");
  ASSERT_TRUE(store);
  EXPECT_FALSE((*store)->Get("x")->has_value());

  // With no stored entry but a readable source file, one is made from the file, then kept.
  add.id = "from-file";
  add.replace = false;
  add.source_name = SamplePath("graf1.png");
  ASSERT_TRUE((*service)->AddImage(add));
  ASSERT_TRUE((*store)->Remove("from-file"));
  thumb = (*service)->GetThumbnail("from-file", 200);
  ASSERT_TRUE(thumb) << thumb.error().ToString();
  EXPECT_TRUE(thumb->from_source);
  EXPECT_EQ(thumb->thumbnail.width, 200);
  thumb = (*service)->GetThumbnail("from-file", 200);
  ASSERT_TRUE(thumb);
  EXPECT_FALSE(thumb->from_source);
}

// Service tests of races and failures around one id; box_in_scene is 512 x 384, graf1 800 x 640.
class ServiceWritesTest : public ::testing::Test {
 protected:
  void SetUp() override {
    if (!std::filesystem::exists(SamplePath("box_in_scene.png"))) GTEST_SKIP() << "opencv-doc sample photos not installed";
    ASSERT_TRUE(testing::BuildTestVocabulary({"box_in_scene.png", "graf1.png"}, 64, vocab_));
    for (const char* sample : {"box_in_scene.png", "graf1.png"}) bytes_[sample] = ReadBytes(SamplePath(sample));
    Reopen();
  }
  void Reopen() {
    service_.reset();
    auto opened = Service::Open(index_dir_, vocab_, {});
    ASSERT_TRUE(opened) << opened.error().ToString();
    service_ = std::move(*opened);
  }
  AddImageRequest Upload(const std::string& id, const std::string& sample, bool replace) const {
    AddImageRequest add;
    add.id = id;
    add.image = bytes_.at(sample);
    add.source_name = "http:" + sample;
    add.replace = replace;
    return add;
  }
  oxbow::testing::TempDir dir_{"oxbow-service-writes"};
  const std::string vocab_ = dir_.path() + "/vocab.oxvoc";
  const std::string index_dir_ = dir_.path() + "/index";
  std::map<std::string, std::vector<uint8_t>> bytes_;  // of the samples (requests do not own theirs)
  std::unique_ptr<Service> service_;
};

// An image indexed from a file (as `oxbow index build` does: no stored thumbnail) gets its thumbnail
// made on the first GET. If the image is deleted and uploaded again, or replaced, while that thumbnail is
// being made, the new image's thumbnail must survive: the late one is not stored over it (stored, it
// would then be dropped as stale: 404 for the new image, also after a restart).
TEST_F(ServiceWritesTest, AThumbnailMadeFromAFileNeverOverwritesANewerImage) {
  for (const bool replace : {false, true}) {
    SCOPED_TRACE(replace ? "replace=true" : "delete + add");
    const std::string id = replace ? "replaced" : "re-added";
    AddImageRequest from_file = Upload(id, "graf1.png", false);
    from_file.source_name = SamplePath("graf1.png");
    ASSERT_TRUE(service_->AddImage(from_file));
    {
      auto store = ThumbnailStore::Open(index_dir_ + "/thumbnails.sqlite");
      ASSERT_TRUE(store);
      ASSERT_TRUE((*store)->Remove(id));
    }
    int hook_calls = 0;
    service_->SetThumbnailMadeHookForTesting([&](const std::string& made_for) {
      if (made_for != id || hook_calls++ > 0) return;
      if (!replace) {
        ASSERT_TRUE(service_->DeleteImage(id));
      }
      const auto added = service_->AddImage(Upload(id, "box_in_scene.png", replace));
      ASSERT_TRUE(added) << added.error().ToString();
    });
    ASSERT_TRUE(service_->GetThumbnail(id, 512));  // made from graf1, the image it started with
    ASSERT_EQ(hook_calls, 1);
    service_->SetThumbnailMadeHookForTesting(nullptr);
    for (int restart = 0; restart < 2; ++restart) {
      const auto thumb = service_->GetThumbnail(id, 512);
      ASSERT_TRUE(thumb) << "restart " << restart << ": " << thumb.error().ToString();
      EXPECT_FALSE(thumb->from_source);
      EXPECT_EQ(thumb->thumbnail.width, 512);  // box_in_scene's shape, not graf1's 512 x 410
      EXPECT_EQ(thumb->thumbnail.height, 384);
      Reopen();
    }
  }
}

void ExecSql(const std::string& db_path, const std::string& sql) {
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open(db_path.c_str(), &db), SQLITE_OK);
  char* error = nullptr;
  EXPECT_EQ(sqlite3_exec(db, sql.c_str(), nullptr, nullptr, &error), SQLITE_OK) << (error ? error : "");
  sqlite3_free(error);
  sqlite3_close(db);
}

// replace=true whose add part fails after the old image's removal (an injected insert failure, as a
// full disk would give): the old image and its thumbnail stay, also after a restart (a replace is one
// commit, so the id is never gone).
TEST_F(ServiceWritesTest, AFailedReplacementKeepsTheOldImageAndThumbnail) {
  const auto added = service_->AddImage(Upload("x", "box_in_scene.png", false));
  ASSERT_TRUE(added) << added.error().ToString();
  service_.reset();
  ExecSql(index_dir_ + "/catalogue.sqlite",
          "CREATE TRIGGER injected_failure BEFORE INSERT ON images WHEN NEW.id = 'x'"
          " BEGIN SELECT RAISE(ABORT, 'injected insert failure'); END;");
  Reopen();
  const auto failed = service_->AddImage(Upload("x", "graf1.png", true));
  ASSERT_FALSE(failed);
  EXPECT_NE(failed.error().message.find("injected insert failure"), std::string::npos) << failed.error().message;
  for (int restart = 0; restart < 2; ++restart) {
    const auto kept = service_->GetImage("x");
    ASSERT_TRUE(kept) << "restart " << restart << ": the failed replacement removed the image";
    EXPECT_EQ(*kept, added->record);
    const auto thumb = service_->GetThumbnail("x", 512);
    ASSERT_TRUE(thumb) << thumb.error().ToString();
    EXPECT_EQ(thumb->thumbnail.width, 512);
    EXPECT_EQ(thumb->thumbnail.height, 384);
    Reopen();
  }
}

// Runs `child` on its own Service over index_dir_ in a forked process that then SIGKILLs itself (a
// crash: nothing closed); `child` returns 0 when all it did succeeded. The fixture's service is closed
// meanwhile and reopened after.
class ServiceCrashTest : public ServiceWritesTest {
 protected:
  void RunKilled(const std::function<int(Service&)>& child) {
    service_.reset();
    std::fflush(nullptr);
    const pid_t pid = fork();
    ASSERT_GE(pid, 0);
    if (pid == 0) {
      auto opened = Service::Open(index_dir_, vocab_, {});
      if (!opened) _exit(100);
      const int failed = child(**opened);
      if (failed != 0) _exit(failed);
      raise(SIGKILL);
      _exit(101);
    }
    int status = 0;
    ASSERT_EQ(waitpid(pid, &status, 0), pid);
    ASSERT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == SIGKILL) << "child exited with " << WEXITSTATUS(status);
    Reopen();
  }
  std::unique_ptr<ThumbnailStore> OpenStore() const {
    auto store = ThumbnailStore::Open(index_dir_ + "/thumbnails.sqlite");
    EXPECT_TRUE(store) << store.error().ToString();
    return store ? std::move(*store) : nullptr;
  }
  AddBatchItem Item(const std::string& id, const std::string& sample) const {
    return AddBatchItem{id, bytes_.at(sample), "", "http:" + sample};
  }
};

// Acknowledged adds (one alone, two in a batch, one replacement) keep their thumbnails through a kill -9
// that closes nothing.
TEST_F(ServiceCrashTest, AcknowledgedAddsKeepTheirThumbnailsThroughAKill) {
  ASSERT_TRUE(service_->AddImage(Upload("r", "graf1.png", false)));
  RunKilled([&](Service& service) {
    if (!service.AddImage(Upload("a", "box_in_scene.png", false))) return 1;
    AddBatchRequest batch;
    batch.images = {Item("b", "graf1.png"), Item("c", "box_in_scene.png")};
    auto added = service.AddImages(batch);
    if (!added || !added->results[0] || !added->results[1]) return 2;
    if (!service.AddImage(Upload("r", "box_in_scene.png", true))) return 3;
    return 0;
  });
  for (const auto& [id, height] : std::map<std::string, int>{{"a", 384}, {"b", 410}, {"c", 384}, {"r", 384}}) {
    const auto thumb = service_->GetThumbnail(id, 512);
    ASSERT_TRUE(thumb) << id << ": " << thumb.error().ToString();
    EXPECT_FALSE(thumb->from_source) << id;
    EXPECT_EQ(thumb->thumbnail.width, 512) << id;
    EXPECT_EQ(thumb->thumbnail.height, height) << id;
  }
}

// A replacement killed after its thumbnail was stored and before the index committed it: the old image
// stays indexed, and so must its thumbnail (overwritten first, the new image's thumbnail no longer fits
// the old image's size: 404 for an acknowledged image).
TEST_F(ServiceCrashTest, AReplacementKilledBeforeItsIndexCommitKeepsTheOldThumbnail) {
  const auto added = service_->AddImage(Upload("x", "box_in_scene.png", false));
  ASSERT_TRUE(added) << added.error().ToString();
  RunKilled([&](Service& service) {
    service.SetBeforeIndexCommitHookForTesting([](const std::string&) { raise(SIGKILL); });
    return service.AddImage(Upload("x", "graf1.png", true)) ? 1 : 2;  // never returns
  });
  for (int restart = 0; restart < 2; ++restart) {
    const auto kept = service_->GetImage("x");
    ASSERT_TRUE(kept);
    EXPECT_EQ(*kept, added->record);
    const auto thumb = service_->GetThumbnail("x", 512);
    ASSERT_TRUE(thumb) << "restart " << restart << ": " << thumb.error().ToString();
    EXPECT_EQ(thumb->thumbnail.width, 512);  // box_in_scene's 512 x 384, not graf1's 512 x 410
    EXPECT_EQ(thumb->thumbnail.height, 384);
    Reopen();
  }
  auto store = OpenStore();
  ASSERT_TRUE(store);
  EXPECT_TRUE(store->Ids(true)->empty());  // the killed replacement's thumbnail was dropped at open
}

// Thumbnail rows of ids the index does not hold (a batch add killed before its index commit, a delete
// killed between the index and the thumbnail store) are removed at open; the others stay.
TEST_F(ServiceCrashTest, ThumbnailsOfImagesNotIndexedAreRemovedAtOpen) {
  ASSERT_TRUE(service_->AddImage(Upload("kept", "graf1.png", false)));
  RunKilled([&](Service& service) {
    service.SetBeforeIndexCommitHookForTesting([](const std::string&) { raise(SIGKILL); });
    AddBatchRequest batch;
    batch.images = {Item("killed-1", "graf1.png"), Item("killed-2", "box_in_scene.png")};
    return service.AddImages(batch) ? 1 : 2;  // never returns
  });
  service_.reset();
  {
    auto store = OpenStore();
    ASSERT_TRUE(store);
    ThumbnailStore::Entry entry = store->Get("kept")->value();
    ASSERT_TRUE(store->Put("deleted", entry));  // as an interrupted delete leaves it
  }
  Reopen();
  EXPECT_EQ(service_->GetImage("killed-1").error().code, ErrorCode::kNotFound);
  auto store = OpenStore();
  ASSERT_TRUE(store);
  EXPECT_EQ(*store->Ids(false), std::vector<std::string>{"kept"});
  EXPECT_TRUE(store->Ids(true)->empty());
  const auto thumb = service_->GetThumbnail("kept", 512);
  ASSERT_TRUE(thumb) << thumb.error().ToString();
  EXPECT_EQ(thumb->thumbnail.height, 410);
}

// A crash after the index committed an image and before its thumbnail left the pending entry: it is
// served meanwhile and committed at open.
TEST_F(ServiceCrashTest, AThumbnailLeftPendingByAnIndexedImageIsCommittedAtOpen) {
  ASSERT_TRUE(service_->AddImage(Upload("y", "graf1.png", false)));
  const uint64_t sequence = service_->index().write_sequence();
  service_.reset();
  {
    auto store = OpenStore();
    ASSERT_TRUE(store);
    const ThumbnailStore::Entry entry = store->Get("y")->value();
    ASSERT_TRUE(store->Remove("y"));
    ASSERT_TRUE(store->PutPending("y", entry, sequence - 1));  // stamped before the add's commit
  }
  Reopen();
  auto store = OpenStore();
  ASSERT_TRUE(store);
  EXPECT_TRUE(store->Ids(true)->empty());
  EXPECT_EQ(*store->Ids(false), std::vector<std::string>{"y"});
  const auto thumb = service_->GetThumbnail("y", 512);
  ASSERT_TRUE(thumb) << thumb.error().ToString();
  EXPECT_FALSE(thumb->from_source);
  EXPECT_EQ(thumb->thumbnail.height, 410);
}

}  // namespace
}  // namespace oxbow::api
