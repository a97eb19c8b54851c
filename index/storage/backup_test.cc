#include "index/storage/backup.h"

#include <gtest/gtest.h>
#include <sqlite3.h>

#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <optional>
#include <random>
#include <set>
#include <thread>

#include "index/storage/catalogue.h"
#include "index/storage/checkpoint.h"
#include "index/image_index.h"
#include "index/storage/test_support.h"
#include "tests/support/temp_dir.h"

namespace oxbow::index {
namespace {

namespace fs = std::filesystem;
constexpr int kWords = 64;

class BackupTest : public ::testing::Test {
 protected:
  // An image of 30 features on centroids (so each quantises to its word), seeded by `seed`.
  sift::FeatureSet Image(uint64_t seed) const {
    std::mt19937_64 rng(seed);
    std::uniform_int_distribution<int> word(0, kWords - 1);
    std::uniform_real_distribution<float> x(0, 600), y(0, 400), s(1.5f, 10.0f), o(0, 6.28f);
    sift::FeatureSet f;
    f.image_width = 640;
    f.image_height = 480;
    f.kind = sift::DescriptorKind::kRootSift;
    const auto centroids = vocabulary_->centroids();
    for (int i = 0; i < 30; ++i) {
      const int w = word(rng);
      f.keypoints.push_back({x(rng), y(rng), s(rng), o(rng), 1.0f, 0});
      f.descriptors.insert(f.descriptors.end(), centroids.begin() + w * 128, centroids.begin() + (w + 1) * 128);
    }
    return f;
  }

  std::unique_ptr<ImageIndex> Create(const IndexOptions& options) {
    auto index = ImageIndex::Create(Source(), *vocabulary_, "test/1", options);
    EXPECT_TRUE(index.has_value()) << (index ? "" : index.error().ToString());
    return index ? std::move(*index) : nullptr;
  }
  void Add(ImageIndex& index, int i) {
    ASSERT_TRUE(index.Add("img-" + std::to_string(i), Image(i), {}).has_value());
  }
  // A new index with images 0 .. n-1, checkpointing every `checkpoint_changes` changes.
  std::unique_ptr<ImageIndex> CreateWithImages(uint64_t checkpoint_changes, int n) {
    IndexOptions options;
    options.checkpoint_changes = checkpoint_changes;
    auto index = Create(options);
    for (int i = 0; index && i < n; ++i) Add(*index, i);
    return index;
  }

  static std::set<std::string> Ids(const ImageIndex& index) {
    std::set<std::string> ids;
    auto list = index.List(0, 1u << 20);
    EXPECT_TRUE(list.has_value());
    if (list) {
      for (const auto& r : *list) ids.insert(r.id);
    }
    return ids;
  }

  // Every file the backup's manifest names is there and passes its check: Open uses the checkpoint
  // instead of rebuilding.
  static void ExpectCompleteCheckpoint(const std::string& dir) {
    auto catalogue = Catalogue::Open((fs::path(dir) / kCatalogueFile).string());
    ASSERT_TRUE(catalogue.has_value());
    if ((*catalogue)->meta().checkpoint.empty()) return;
    auto manifest = CheckpointManifest::Parse((*catalogue)->meta().checkpoint);
    ASSERT_TRUE(manifest.has_value());
    for (const auto& file : manifest->files) {
      auto s = VerifyCheckpointFile(dir, file);
      EXPECT_TRUE(s.has_value()) << file.name << ": " << (s ? "" : s.error().ToString());
    }
  }

  std::string Source() const { return (root_ / "source").string(); }
  std::string Out(int n = 0) const { return (root_ / ("backup" + std::to_string(n))).string(); }

  oxbow::testing::TempDir temp_;
  fs::path root_ = temp_.path();
  std::unique_ptr<vocab::Vocabulary> vocabulary_ =
      std::make_unique<vocab::Vocabulary>(test_support::RandomVocabulary(1, kWords, "test/1"));
};

// One writer adds and removes images (each op acknowledged when its call returns) while backups run and
// the index checkpoints every few changes (deleting the previous checkpoint's files). The writes are
// serial, so the committed states are the prefixes of the op sequence: each backup must equal one of
// them, at least the prefix acknowledged before the backup started and at most the prefix started
// before it returned.
TEST_F(BackupTest, EqualsOnePrefixOfTheAcknowledgedWritesUnderConcurrentWrites) {
  auto index = CreateWithImages(4, 20);
  ASSERT_TRUE(index);

  // Op k: add image 20 + k, or (every third op) remove an image added earlier and not yet removed.
  struct Op {
    bool add;
    int image;
  };
  std::vector<Op> ops;
  std::vector<std::set<std::string>> states{Ids(*index)};  // states[k]: after the first k ops
  int next_image = 20, next_removed = 0;
  for (int k = 0; k < 240; ++k) {
    const Op op = k % 3 == 2 ? Op{false, next_removed++ * 2} : Op{true, next_image++};
    std::set<std::string> state = states.back();
    const std::string id = "img-" + std::to_string(op.image);
    if (op.add) {
      state.insert(id);
    } else {
      ASSERT_EQ(state.erase(id), 1u);
    }
    ops.push_back(op);
    states.push_back(std::move(state));
  }

  std::atomic<size_t> started{0}, acknowledged{0};
  std::thread writer([&] {
    for (const Op& op : ops) {
      started.fetch_add(1);
      const std::string id = "img-" + std::to_string(op.image);
      if (op.add) {
        EXPECT_TRUE(index->Add(id, Image(op.image), {}).has_value());
      } else {
        EXPECT_TRUE(index->Remove(id).has_value());
      }
      acknowledged.fetch_add(1);
    }
  });
  int backups = 0, retried = 0;
  std::vector<size_t> matched;
  while (acknowledged.load() < ops.size() || backups < 2) {
    const size_t before = acknowledged.load();
    auto result = BackupIndex(Source(), Out(backups));
    const size_t after = started.load();
    if (!result) {
      ADD_FAILURE() << result.error().ToString();
      break;
    }
    retried += result->attempts > 1;
    ExpectCompleteCheckpoint(Out(backups));
    auto copy = ImageIndex::Open(Out(backups));
    if (!copy) {
      ADD_FAILURE() << copy.error().ToString();
      break;
    }
    const std::set<std::string> ids = Ids(**copy);
    EXPECT_EQ(result->images, static_cast<int64_t>(ids.size()));
    std::optional<size_t> prefix;
    for (size_t k = before; k <= after && !prefix; ++k) {
      if (states[k] == ids) prefix = k;
    }
    EXPECT_TRUE(prefix.has_value()) << "backup " << backups << " (" << ids.size()
                                    << " images) equals no state between ops " << before << " and " << after;
    if (prefix) matched.push_back(*prefix);
    ++backups;
  }
  writer.join();
  // The test means something only when backups saw different states.
  EXPECT_GE(std::set<size_t>(matched.begin(), matched.end()).size(), 2u);
  std::cout << backups << " backups, " << retried << " retried after a checkpoint replaced their files\n";
}

// A checkpoint that commits after the snapshot and deletes the files it names: the backup takes a new
// snapshot and holds the writes before it.
TEST_F(BackupTest, RetriesWhenACheckpointDeletesTheSnapshotsFiles) {
  IndexOptions options;
  options.checkpoint_changes = 10;  // the 10 adds below start exactly one checkpoint
  ASSERT_TRUE(CreateWithImages(options.checkpoint_changes, 10));  // Close checkpoints
  auto opened = ImageIndex::Open(Source(), options);
  ASSERT_TRUE(opened.has_value());
  auto& index = **opened;
  auto first = Catalogue::Open((fs::path(Source()) / kCatalogueFile).string());
  ASSERT_TRUE(first.has_value());
  auto manifest = CheckpointManifest::Parse((*first)->meta().checkpoint);
  ASSERT_TRUE(manifest.has_value());
  first->reset();
  // The postings file: a new checkpoint keeps the older geometry files and replaces only it.
  fs::path old_postings;
  for (const auto& file : manifest->files) {
    if (file.name.starts_with("postings-")) old_postings = fs::path(Source()) / file.name;
  }
  ASSERT_TRUE(fs::exists(old_postings));

  BackupOptions backup_options;
  backup_options.after_snapshot_for_testing = [&](int attempt) {
    if (attempt != 1) return;
    for (int i = 10; i < 20; ++i) Add(index, i);
    // The background checkpoint commits and deletes the previous generation's files.
    for (int waited = 0; fs::exists(old_postings) && waited < 600; ++waited) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    ASSERT_FALSE(fs::exists(old_postings)) << "no checkpoint within 60 s";
  };
  auto result = BackupIndex(Source(), Out(), backup_options);
  ASSERT_TRUE(result.has_value()) << result.error().ToString();
  EXPECT_EQ(result->attempts, 2);
  EXPECT_GT(result->generation, manifest->generation);
  ExpectCompleteCheckpoint(Out());
  auto copy = ImageIndex::Open(Out());
  ASSERT_TRUE(copy.has_value());
  EXPECT_EQ(Ids(**copy), Ids(index));
  EXPECT_EQ(Ids(**copy).size(), 20u);
}

// The restored copy answers queries as the source does: same ids, same scores (source with a checkpoint
// and changes after it, so the copy replays them as the source would).
TEST_F(BackupTest, RestoredCopySearchesLikeTheSource) {
  IndexOptions options;
  options.checkpoint_changes = 1000;
  ASSERT_TRUE(CreateWithImages(options.checkpoint_changes, 30));  // Close checkpoints
  auto source = ImageIndex::Open(Source(), options);
  ASSERT_TRUE(source.has_value());
  for (int i = 30; i < 40; ++i) Add(**source, i);
  for (int i = 0; i < 5; ++i) ASSERT_TRUE((*source)->Remove("img-" + std::to_string(i * 3)).has_value());

  auto result = BackupIndex(Source(), Out());
  ASSERT_TRUE(result.has_value()) << result.error().ToString();
  EXPECT_EQ(result->images, 35);
  EXPECT_GT(result->generation, 0u);
  auto copy = ImageIndex::Open(Out(), options);
  ASSERT_TRUE(copy.has_value()) << copy.error().ToString();
  EXPECT_EQ(Ids(**copy), Ids(**source));
  QueryOptions query;
  query.top_k = 10;
  query.rerank_depth = 10;
  for (int q = 100; q < 105; ++q) {
    auto a = (*source)->Query(Image(q), query);
    auto b = (*copy)->Query(Image(q), query);
    ASSERT_TRUE(a.has_value() && b.has_value());
    ASSERT_EQ(a->results.size(), b->results.size());
    for (size_t i = 0; i < a->results.size(); ++i) {
      EXPECT_EQ(a->results[i].id, b->results[i].id);
      EXPECT_DOUBLE_EQ(a->results[i].score, b->results[i].score);
    }
  }
}

TEST_F(BackupTest, DamagedCheckpointFileIsReportedAndNothingIsLeft) {
  ASSERT_TRUE(CreateWithImages(IndexOptions{}.checkpoint_changes, 10));  // Close checkpoints
  fs::path postings;
  for (const auto& entry : fs::directory_iterator(Source())) {
    if (entry.path().filename().string().starts_with("postings-")) postings = entry.path();
  }
  ASSERT_FALSE(postings.empty());
  {
    std::fstream f(postings, std::ios::in | std::ios::out | std::ios::binary);
    f.seekp(40);
    f.put('\x5a');
  }
  auto result = BackupIndex(Source(), Out());
  ASSERT_FALSE(result.has_value());
  EXPECT_EQ(result.error().code, ErrorCode::kCorruptData);
  EXPECT_NE(result.error().message.find(postings.filename().string()), std::string::npos) << result.error().message;
  EXPECT_FALSE(fs::exists(Out()));
  EXPECT_FALSE(fs::exists(Out() + ".tmp"));
}

// The vocabulary copy is read by an open only: damaged after the source was opened, the backup's copy is
// checked against the catalogue.
TEST_F(BackupTest, DamagedVocabularyCopyIsReportedAndNothingIsLeft) {
  ASSERT_TRUE(CreateWithImages(IndexOptions{}.checkpoint_changes, 10));
  {
    std::fstream f(fs::path(Source()) / kVocabularyFile, std::ios::in | std::ios::out | std::ios::binary);
    f.seekp(100);
    f.put('\x5a');
  }
  auto result = BackupIndex(Source(), Out());
  ASSERT_FALSE(result.has_value());
  EXPECT_EQ(result.error().code, ErrorCode::kCorruptData) << result.error().ToString();
  EXPECT_NE(result.error().message.find("nothing was backed up"), std::string::npos) << result.error().message;
  EXPECT_NE(result.error().message.find(kVocabularyFile), std::string::npos) << result.error().message;
  EXPECT_FALSE(fs::exists(Out()));
  EXPECT_FALSE(fs::exists(Out() + ".tmp"));
}

// A damaged page that the backup's own reads never touch (the `features` table): the page copy takes it
// as it is, SQLite's quick_check of the copy finds it.
TEST_F(BackupTest, DamagedCatalogueIsReportedAndNothingIsLeft) {
  ASSERT_TRUE(CreateWithImages(IndexOptions{}.checkpoint_changes, 10));
  const std::string catalogue = (fs::path(Source()) / kCatalogueFile).string();
  ASSERT_FALSE(fs::exists(catalogue + "-wal"));  // closed: everything is in the file
  int64_t page = 0, page_size = 0;
  {
    sqlite3* db = nullptr;
    ASSERT_EQ(sqlite3_open_v2(catalogue.c_str(), &db, SQLITE_OPEN_READONLY, nullptr), SQLITE_OK);
    auto integer = [&](const char* sql) {
      sqlite3_stmt* stmt = nullptr;
      sqlite3_prepare_v2(db, sql, -1, &stmt, nullptr);
      const int64_t value = sqlite3_step(stmt) == SQLITE_ROW ? sqlite3_column_int64(stmt, 0) : 0;
      sqlite3_finalize(stmt);
      return value;
    };
    page = integer("SELECT rootpage FROM sqlite_master WHERE name = 'features'");
    page_size = integer("PRAGMA page_size");
    sqlite3_close(db);
  }
  ASSERT_GT(page, 1);
  {
    std::fstream f(catalogue, std::ios::in | std::ios::out | std::ios::binary);
    f.seekp((page - 1) * page_size);
    const std::string garbage(static_cast<size_t>(page_size), '\xff');
    f.write(garbage.data(), static_cast<std::streamsize>(garbage.size()));
  }
  auto result = BackupIndex(Source(), Out());
  ASSERT_FALSE(result.has_value());
  EXPECT_EQ(result.error().code, ErrorCode::kCorruptData) << result.error().ToString();
  EXPECT_NE(result.error().message.find("quick_check"), std::string::npos) << result.error().message;
  EXPECT_NE(result.error().message.find(kCatalogueFile), std::string::npos) << result.error().message;
  EXPECT_FALSE(fs::exists(Out()));
  EXPECT_FALSE(fs::exists(Out() + ".tmp"));
}

TEST_F(BackupTest, DestinationMustBeNewOrEmpty) {
  { auto index = Create({}); }
  fs::create_directories(Out(1));
  std::ofstream(fs::path(Out(1)) / "keep") << "x";
  auto taken = BackupIndex(Source(), Out(1));
  ASSERT_FALSE(taken.has_value());
  EXPECT_EQ(taken.error().code, ErrorCode::kAlreadyExists);
  EXPECT_TRUE(fs::exists(fs::path(Out(1)) / "keep"));

  fs::create_directories(Out(2) + ".tmp");
  auto leftover = BackupIndex(Source(), Out(2));
  ASSERT_FALSE(leftover.has_value());
  EXPECT_EQ(leftover.error().code, ErrorCode::kAlreadyExists);
  EXPECT_FALSE(fs::exists(Out(2)));

  fs::create_directories(Out(3));  // empty: used
  ASSERT_TRUE(BackupIndex(Source(), Out(3) + "/").has_value());
  EXPECT_TRUE(ImageIndex::Open(Out(3)).has_value());

  auto missing = BackupIndex((root_ / "nothing").string(), Out(4));
  ASSERT_FALSE(missing.has_value());
  EXPECT_EQ(missing.error().code, ErrorCode::kNotFound);
  EXPECT_FALSE(fs::exists(Out(4) + ".tmp"));
}

// The folder a client names is checked before anything is written: its mistakes are kInvalidArgument
// (HTTP 400), never an I/O error (500), and nothing is written for them, beside the folder or elsewhere.
TEST_F(BackupTest, ClientPathMistakesAreRefusedBeforeAnythingIsWritten) {
  { auto index = Create({}); }
  const auto refused = [&](const std::string& out, ErrorCode code, const std::string& what) {
    auto result = BackupIndex(Source(), out);
    EXPECT_FALSE(result.has_value()) << what << ": backed up to " << out;
    if (result) return;
    EXPECT_EQ(result.error().code, code) << what << ": " << result.error().ToString();
    const auto checked = CheckBackupFolder(Source(), out);
    EXPECT_TRUE(!checked.has_value() && checked.error().code == code) << what;
    std::error_code ec;
    EXPECT_FALSE(fs::exists(fs::symlink_status(out + ".tmp", ec))) << what;
  };
  fs::create_directories(root_ / "real");
  fs::create_directory_symlink(root_ / "real", root_ / "link");
  refused((root_ / "link").string(), ErrorCode::kInvalidArgument, "a link to an empty folder");
  refused((root_ / "link" / "sub").string(), ErrorCode::kInvalidArgument, "a new folder under a link");
  EXPECT_TRUE(fs::is_empty(root_ / "real"));
  fs::create_symlink(root_ / "nowhere", root_ / "dangling");
  refused((root_ / "dangling").string(), ErrorCode::kInvalidArgument, "a dangling link");
  EXPECT_FALSE(fs::exists(root_ / "nowhere"));
  refused((root_ / std::string(300, 'n')).string(), ErrorCode::kInvalidArgument, "a 300-byte name");
  refused((root_ / std::string(252, 'n')).string(), ErrorCode::kInvalidArgument, "a name whose .tmp is over NAME_MAX");
  std::string long_path(kMaxBackupPathBytes + 1, 'p');
  long_path.front() = '/';
  refused(long_path, ErrorCode::kInvalidArgument, "a path over the limit");
  refused(Out(5) + std::string("\0suffix", 7), ErrorCode::kInvalidArgument, "a NUL byte");
  EXPECT_FALSE(fs::exists(Out(5))) << "the path was cut at its NUL byte";
  refused(Out(6) + "\n2026-01-01T00:00:00Z I forged", ErrorCode::kInvalidArgument, "a newline");
  refused(Out(6) + "\x7f", ErrorCode::kInvalidArgument, "DEL");
  refused("", ErrorCode::kInvalidArgument, "an empty path");
  refused("/", ErrorCode::kInvalidArgument, "the root folder");
  refused((root_ / "missing" / ".." / "x").string(), ErrorCode::kInvalidArgument, "a '..' past a missing folder");
  EXPECT_FALSE(fs::exists(root_ / "x"));
  refused((root_ / "real" / ".." / "y").string(), ErrorCode::kInvalidArgument, "a '..' component");
  refused(Source(), ErrorCode::kInvalidArgument, "the index folder itself");
  refused(Source() + "/", ErrorCode::kInvalidArgument, "the index folder with a trailing slash");
  refused(Source() + "/inside", ErrorCode::kInvalidArgument, "a new folder inside the index folder");
  EXPECT_FALSE(fs::exists(Source() + "/inside"));
  std::ofstream(root_ / "file") << "x";
  refused((root_ / "file" / "x").string(), ErrorCode::kInvalidArgument, "a parent that is a file");
  refused((root_ / "file").string(), ErrorCode::kAlreadyExists, "an existing file");
  refused((root_ / "absent" / "x").string(), ErrorCode::kNotFound, "a missing parent");
  EXPECT_FALSE(fs::exists(root_ / "absent"));
  // The index folder named through a link is still the index folder.
  fs::create_directory_symlink(Source(), root_ / "source-link");
  auto through = BackupIndex((root_ / "source-link").string(), Source() + "/inside");
  ASSERT_FALSE(through.has_value());
  EXPECT_EQ(through.error().code, ErrorCode::kInvalidArgument) << through.error().ToString();
  // A plain new folder, relative or absolute, with "." components, is backed up.
  EXPECT_TRUE(CheckBackupFolder(Source(), "relative-backup").has_value());
  ASSERT_TRUE(BackupIndex(Source(), (root_ / "." / "fine").string()).has_value());
  EXPECT_TRUE(ImageIndex::Open((root_ / "fine").string()).has_value());
}

}  // namespace
}  // namespace oxbow::index
