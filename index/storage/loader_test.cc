// Opening an index folder (storage/loader.h, ImageIndex::Open): what it refuses, damaged BLOBs and
// checkpoint files, replay of the changes since the checkpoint, migration, one process per folder.
#include "index/storage/test_support.h"

#include <gtest/gtest.h>

namespace oxbow::index {
namespace {

using namespace test_support;  // NOLINT(google-build-using-namespace): the tests' shared fixtures

class LoaderTest : public CheckpointFixture {};
TEST_F(LoaderTest, VocabularyMismatchIsRefused) {
  {
    auto index = CreateIndex();
    std::mt19937_64 rng(7);
    ASSERT_TRUE(index->Add("a", RandomImage(rng, 30), {}));
  }
  // Another vocabulary's file in place of the index's copy.
  ASSERT_TRUE(MakeVocabulary(99).Write((dir_ / "vocabulary.oxvoc").string()));
  const auto r = ImageIndex::Open(dir_.string());
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().code, ErrorCode::kIncompatible);
  EXPECT_NE(r.error().message.find("does not match"), std::string::npos) << r.error().message;
}

TEST_F(LoaderTest, UnknownSchemaVersionIsRefused) {
  CreateIndex();
  ExecSql(dir_ / "catalogue.sqlite", "UPDATE meta SET value = '99' WHERE key = 'schema_version'");
  const auto r = ImageIndex::Open(dir_.string());
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().code, ErrorCode::kIncompatible);
  EXPECT_NE(r.error().message.find("schema version 99"), std::string::npos) << r.error().message;
}

// A damaged BLOB that a rebuild reads costs that image only: the others are served, the damaged one
// is dropped (its row deleted, logged) and its id can be added again.
TEST_F(LoaderTest, DamagedFeatureBlobCostsThatImageOnly) {
  std::mt19937_64 rng(8);
  const auto b = RandomImage(rng, 30);
  {
    auto index = CreateIndex();
    ASSERT_TRUE(index->Add("a", RandomImage(rng, 30), {}));
    ASSERT_TRUE(index->Add("b", b, {}));
  }
  // Flip one byte inside the packed features (after the 24-byte header): the checksum must catch it
  // when Open reads the BLOBs (no checkpoint: a full rebuild).
  ExecSql(dir_ / "catalogue.sqlite",
          "UPDATE features SET blob = substr(blob, 1, 30) || x'ff' || substr(blob, 32) "
          "WHERE number = (SELECT number FROM images WHERE id = 'a'); DELETE FROM meta WHERE key = 'checkpoint'");
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    EXPECT_EQ((*index)->Stats().num_images, 1u);
    EXPECT_EQ((*index)->Get("a").error().code, ErrorCode::kNotFound);
    const auto features = FeaturesOf(**index, "b");
    ASSERT_TRUE(features) << features.error().ToString();
    EXPECT_EQ(features->keypoints.size(), b.keypoints.size());
    EXPECT_TRUE((*index)->Add("a", RandomImage(rng, 30), {}));
  }
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  EXPECT_EQ((*index)->Stats().num_images, 2u);
}


// A damaged image record (an id changed in place in the file: the table and its id index disagree)
// is refused at open, not served under the wrong id.
TEST_F(LoaderTest, DamagedImageRecordIsRefused) {
  const std::string id = "image-with-a-long-recognisable-id";
  {
    auto index = CreateIndex();
    std::mt19937_64 rng(8);
    for (int i = 0; i < 5; ++i) ASSERT_TRUE(index->Add(id + std::to_string(i), RandomImage(rng, 30), {}));
  }
  std::string bytes = FileBytes(dir_ / "catalogue.sqlite");
  const size_t at = bytes.rfind(id + "3");  // the table's row or the index's entry: either disagrees
  ASSERT_NE(at, std::string::npos);
  bytes[at] = 'J';
  std::ofstream(dir_ / "catalogue.sqlite", std::ios::binary | std::ios::trunc).write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  const auto r = ImageIndex::Open(dir_.string());
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().code, ErrorCode::kCorruptData) << r.error().ToString();
  EXPECT_NE(r.error().message.find("integrity check"), std::string::npos) << r.error().message;
}

// `oxbow index check` (CheckIndexFolder): every BLOB, those a checkpoint covers too (an open does not
// read them), checked; the damaged ones reported by id, and dropped on request.
TEST_F(LoaderTest, TheCheckFindsAndDropsDamagedBlobsThatAnOpenDoesNotRead) {
  {
    auto index = CreateIndex();
    std::mt19937_64 rng(8);
    for (const char* id : {"a", "b", "c"}) ASSERT_TRUE(index->Add(id, RandomImage(rng, 30), {}));
  }
  ExecSql(dir_ / "catalogue.sqlite",
          "UPDATE features SET blob = substr(blob, 1, 30) || x'ff' || substr(blob, 32) "
          "WHERE number = (SELECT number FROM images WHERE id = 'b')");
  ASSERT_TRUE(ImageIndex::Open(dir_.string()));  // from the checkpoint: the BLOB is not read
  auto check = CheckIndexFolder(dir_.string(), /*drop_damaged=*/false);
  ASSERT_TRUE(check) << check.error().ToString();
  EXPECT_EQ(check->images, 3u);
  ASSERT_EQ(check->damaged.size(), 1u);
  EXPECT_EQ(check->damaged[0].id, "b");
  EXPECT_NE(check->damaged[0].why.find("checksum"), std::string::npos) << check->damaged[0].why;
  EXPECT_FALSE(check->dropped);
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index);
    EXPECT_EQ((*index)->Stats().num_images, 3u);
    // A folder in use is refused.
    EXPECT_FALSE(CheckIndexFolder(dir_.string(), false));
  }
  check = CheckIndexFolder(dir_.string(), /*drop_damaged=*/true);
  ASSERT_TRUE(check) << check.error().ToString();
  EXPECT_TRUE(check->dropped);
  check = CheckIndexFolder(dir_.string(), false);
  ASSERT_TRUE(check) << check.error().ToString();
  EXPECT_TRUE(check->damaged.empty());
  EXPECT_EQ(check->images, 2u);
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  EXPECT_EQ((*index)->Stats().num_images, 2u);
  EXPECT_EQ((*index)->Get("b").error().code, ErrorCode::kNotFound);
}

// A folder without an index: not found, as every command says it, and nothing written into it.
TEST_F(LoaderTest, TheCheckOfAFolderWithoutAnIndexIsNotFoundAndWritesNothing) {
  const fs::path empty = dir_ / "empty";
  fs::create_directories(empty);
  auto check = CheckIndexFolder(empty.string(), false);
  ASSERT_FALSE(check);
  EXPECT_EQ(check.error().code, ErrorCode::kNotFound) << check.error().ToString();
  EXPECT_TRUE(fs::is_empty(empty));
  check = CheckIndexFolder((dir_ / "missing").string(), false);
  ASSERT_FALSE(check);
  EXPECT_EQ(check.error().code, ErrorCode::kNotFound) << check.error().ToString();
  EXPECT_FALSE(fs::exists(dir_ / "missing"));
}

TEST_F(LoaderTest, DamagedCatalogueAndVocabularyAreRefused) {
  {
    auto index = CreateIndex();
    std::mt19937_64 rng(9);
    ASSERT_TRUE(index->Add("a", RandomImage(rng, 30), {}));
  }
  const fs::path vocab_path = dir_ / "vocabulary.oxvoc";
  const fs::path backup = dir_ / "vocab.bak";
  fs::copy_file(vocab_path, backup);
  // Truncated vocabulary copy.
  fs::resize_file(vocab_path, fs::file_size(vocab_path) / 2);
  auto r = ImageIndex::Open(dir_.string());
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().code, ErrorCode::kCorruptData) << r.error().ToString();
  // The message says how to restore it; `oxbow index check` finds it too.
  EXPECT_NE(r.error().message.find("copy that file to " + vocab_path.string()), std::string::npos) << r.error().message;
  auto check = CheckIndexFolder(dir_.string(), /*drop_damaged=*/false);
  ASSERT_FALSE(check);
  EXPECT_EQ(check.error().code, ErrorCode::kCorruptData) << check.error().ToString();
  fs::copy_file(backup, vocab_path, fs::copy_options::overwrite_existing);
  ASSERT_TRUE(ImageIndex::Open(dir_.string()));
  ASSERT_TRUE(CheckIndexFolder(dir_.string(), false));
  // Garbage over the SQLite header.
  {
    std::fstream f(dir_ / "catalogue.sqlite", std::ios::in | std::ios::out | std::ios::binary);
    f.write("this is not a database file at all", 32);
  }
  r = ImageIndex::Open(dir_.string());
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().code, ErrorCode::kCorruptData) << r.error().ToString();
}

// A catalogue.sqlite-wal that belongs to another index (here one on another vocabulary, with images)
// beside the catalogue: the open is refused, and closing the refused open must not checkpoint that WAL
// into catalogue.sqlite (a read-write connection would, overwriting every image of the index).
TEST_F(LoaderTest, ForeignWalIsRefusedAndLeavesTheCatalogueAlone) {
  {
    auto index = CreateIndex();
    std::mt19937_64 rng(11);
    for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add(NumberedId("a", i), RandomImage(rng, 80), {}));
  }
  ASSERT_FALSE(fs::exists(dir_ / "catalogue.sqlite-wal"));  // a clean close checkpointed it
  const fs::path other_dir = dir_.string() + "_other";
  fs::remove_all(other_dir);
  std::string foreign_wal;
  {
    const vocab::Vocabulary other_vocabulary = MakeVocabulary(2);
    auto other = ImageIndex::Create(other_dir.string(), other_vocabulary, "test-extractor/1");
    ASSERT_TRUE(other) << other.error().ToString();
    std::mt19937_64 rng(12);
    ASSERT_TRUE((*other)->Add("b", RandomImage(rng, 10), {}));
    foreign_wal = FileBytes(other_dir / "catalogue.sqlite-wal");  // committed, not yet checkpointed
  }
  fs::remove_all(other_dir);
  ASSERT_GT(foreign_wal.size(), 32u);
  const std::string catalogue = FileBytes(dir_ / "catalogue.sqlite");
  std::ofstream(dir_ / "catalogue.sqlite-wal", std::ios::binary) << foreign_wal;

  const auto refused = ImageIndex::Open(dir_.string());
  ASSERT_FALSE(refused);
  EXPECT_EQ(refused.error().code, ErrorCode::kIncompatible) << refused.error().ToString();
  EXPECT_TRUE(FileBytes(dir_ / "catalogue.sqlite") == catalogue) << "the refused open wrote to the catalogue";
  EXPECT_TRUE(FileBytes(dir_ / "catalogue.sqlite-wal") == foreign_wal) << "the foreign WAL changed";

  // Once the stray file is gone the index opens whole.
  fs::remove(dir_ / "catalogue.sqlite-wal");
  fs::remove(dir_ / "catalogue.sqlite-shm");
  auto reopened = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(reopened) << reopened.error().ToString();
  EXPECT_EQ((*reopened)->Stats().num_images, 20u);
  EXPECT_TRUE((*reopened)->Contains("a19"));
}

TEST_F(LoaderTest, ReadOnlyFolderIsAnIoErrorNotDamage) {
  {
    auto index = CreateIndex();
    std::mt19937_64 rng(14);
    ASSERT_TRUE(index->Add("a", RandomImage(rng, 30), {}));
  }
  const std::string catalogue = FileBytes(dir_ / "catalogue.sqlite");
  // The child may run as user nobody: it must reach dir_ through the test's folder (mkdtemp makes it 0700).
  fs::permissions(temp_.path(), fs::perms::group_exec | fs::perms::others_exec, fs::perm_options::add);
  fs::permissions(dir_, fs::perms::owner_write | fs::perms::group_write | fs::perms::others_write,
                  fs::perm_options::remove);
  for (const auto& file : fs::directory_iterator(dir_)) {
    fs::permissions(file.path(), fs::perms::owner_write | fs::perms::group_write | fs::perms::others_write,
                    fs::perm_options::remove);
  }
  int fds[2];
  ASSERT_EQ(pipe(fds), 0);
  std::fflush(nullptr);
  const pid_t pid = fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    close(fds[0]);
    if (geteuid() == 0 && (setgid(65534) != 0 || setuid(65534) != 0)) _exit(99);
    const auto r = ImageIndex::Open(dir_.string());
    const std::string report = r ? std::string("opened") : r.error().ToString();
    if (write(fds[1], report.data(), report.size()) < 0) _exit(98);
    _exit(r ? 1 : (r.error().code == ErrorCode::kIoError ? 0 : 2));
  }
  close(fds[1]);
  std::string report;
  char buf[512];
  for (ssize_t n; (n = read(fds[0], buf, sizeof buf)) > 0;) report.append(buf, static_cast<size_t>(n));
  close(fds[0]);
  int status = 0;
  ASSERT_EQ(waitpid(pid, &status, 0), pid);
  fs::permissions(dir_, fs::perms::owner_write, fs::perm_options::add);
  for (const auto& file : fs::directory_iterator(dir_)) fs::permissions(file.path(), fs::perms::owner_write, fs::perm_options::add);
  ASSERT_TRUE(WIFEXITED(status));
  if (WEXITSTATUS(status) == 99) GTEST_SKIP() << "running as root and cannot drop to user nobody (65534)";
  EXPECT_EQ(WEXITSTATUS(status), 0) << report;
  EXPECT_NE(report.find("read-only"), std::string::npos) << report;
  EXPECT_NE(report.find("permissions"), std::string::npos) << report;
  EXPECT_TRUE(FileBytes(dir_ / "catalogue.sqlite") == catalogue) << "the catalogue changed";
  ASSERT_TRUE(ImageIndex::Open(dir_.string()));
}

TEST_F(LoaderTest, OpenReplaysChangesAfterTheCheckpointAndEqualsAFreshIndex) {
  SKIP_KILL_TEST_UNDER_TSAN();
  {
    auto index = CreateIndex();
    for (int i = 0; i < 30; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
  }
  // Killed after more adds, removes (of checkpointed and new images) and a replace: only the catalogue
  // has them.
  InChildThenKill([&](ImageIndex& index) {
    for (int i = 30; i < 45; ++i) ASSERT_TRUE(index.Add(NumberedId("i", i), Image(i), {}));
    for (const int i : {3, 17, 40}) ASSERT_TRUE(index.Remove(NumberedId("i", i)));
    ASSERT_TRUE(index.Replace("i5", Image(5), {}));
  });
  std::vector<int> live;
  for (int i = 0; i < 45; ++i) {
    if (i != 3 && i != 17 && i != 40) live.push_back(i);
  }
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    EXPECT_EQ(CheckpointFiles(dir_), (std::vector<std::string>{"geometry-1-0.oxck", "postings-1.oxck",
                                                                "segment-1-0.oxck", "segment-1-1.oxck"}))
        << "open replays the delta instead of rebuilding";
    ExpectEqualsFresh(**index, live);
    EXPECT_FALSE((*index)->Contains("i3"));
  }
  // The close checkpointed the replayed changes: generation 2 adds geometry for the new numbers only,
  // and a segment file for the new segment; the segments of generation 1 are named again, not rewritten.
  EXPECT_EQ(CheckpointFiles(dir_),
            (std::vector<std::string>{"geometry-1-0.oxck", "geometry-2-0.oxck", "postings-2.oxck",
                                      "segment-1-0.oxck", "segment-1-1.oxck", "segment-2-0.oxck"}));
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  ExpectEqualsFresh(**index, live);
}

TEST_F(LoaderTest, DamagedTruncatedOrMissingFilesAreRepairedFromTheCatalogue) {
  const std::vector<std::pair<std::string, std::function<void(const fs::path&)>>> damages = {
      {"flipped byte", [](const fs::path& p) {
         std::fstream f(p, std::ios::in | std::ios::out | std::ios::binary);
         f.seekg(40);
         const char c = static_cast<char>(f.get());
         f.seekp(40);
         f.put(static_cast<char>(c ^ 0x5a));
       }},
      {"truncated", [](const fs::path& p) { fs::resize_file(p, fs::file_size(p) / 2); }},
      {"missing", [](const fs::path& p) { fs::remove(p); }},
  };
  for (const std::string target : {"postings-1.oxck", "segment-1-0.oxck", "geometry-1-0.oxck"}) {
    for (const auto& [what, damage] : damages) {
      std::string trace = target;
      trace += " ";
      trace += what;
      SCOPED_TRACE(trace);
      fs::remove_all(dir_);
      {
        auto index = CreateIndex();
        for (int i = 0; i < 20; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
      }
      damage(dir_ / target);
      auto index = ImageIndex::Open(dir_.string());
      ASSERT_TRUE(index) << index.error().ToString();
      ExpectEqualsFresh(**index, Range(0, 20));
      // Rebuilt from the catalogue and checkpointed again (generation 2, in the background or at the
      // latest at close); the old files are gone.
      index->reset();
      EXPECT_EQ(CheckpointFiles(dir_),
                (std::vector<std::string>{"geometry-2-0.oxck", "postings-2.oxck", "segment-2-0.oxck"}));
    }
  }
}

// Read-only opens (ImageIndex::OpenReadOnly) share the folder with each other and with no writer; they
// take no write and leave every file of the folder as it was.
TEST_F(LoaderTest, ReadOnlyOpensShareTheFolderAndWriteNothing) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 5; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
  }
  const auto files = [&] {
    std::map<std::string, std::pair<uintmax_t, std::filesystem::file_time_type>> out;
    for (const auto& entry : std::filesystem::directory_iterator(dir_)) {
      // SQLite's side files: a read-only connection leaves an empty WAL (nothing to replay) and its
      // shared-memory index.
      const std::string name = entry.path().filename().string();
      if (name == "LOCK" || name.ends_with("-shm") || (name.ends_with("-wal") && entry.file_size() == 0)) continue;
      out[entry.path().filename().string()] = {entry.file_size(), entry.last_write_time()};
    }
    return out;
  };
  const auto before = files();
  {
    auto first = ImageIndex::OpenReadOnly(dir_.string());
    auto second = ImageIndex::OpenReadOnly(dir_.string());
    ASSERT_TRUE(first) << first.error().ToString();
    ASSERT_TRUE(second) << second.error().ToString();
    EXPECT_EQ((*first)->Stats().num_images, 5u);
    ASSERT_TRUE((*second)->Get(NumberedId("i", 3)));
    const auto writer = ImageIndex::Open(dir_.string());
    ASSERT_FALSE(writer);
    EXPECT_NE(writer.error().message.find("open in another process"), std::string::npos) << writer.error().ToString();
    EXPECT_EQ((*first)->Add(NumberedId("j", 0), Image(7), {}).error().code, ErrorCode::kIncompatible);
    EXPECT_EQ((*first)->Remove(NumberedId("i", 0)).error().code, ErrorCode::kIncompatible);
    const std::vector<uint32_t> df((*first)->vocabulary().size(), 1);
    EXPECT_EQ((*first)->PinCollectionStatistics(5, df).error().code, ErrorCode::kIncompatible);
  }
  EXPECT_EQ(files(), before);
  auto writer = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(writer) << writer.error().ToString();
  EXPECT_EQ(ImageIndex::OpenReadOnly(dir_.string()).error().code, ErrorCode::kIoError);
  EXPECT_EQ((*writer)->Stats().num_images, 5u);
}

// One process at a time in a folder (folder_lock.h): a second open, in this process or another, is
// refused while the first holds it, and works once it closed or died by kill -9 (no stale lock).
TEST_F(LoaderTest, AnIndexFolderIsOpenInOneProcessAtATime) {
  SKIP_KILL_TEST_UNDER_TSAN();
  const auto refused_by = [&](const std::string& holder) {
    auto second = ImageIndex::Open(dir_.string());
    if (second) return ::testing::AssertionFailure() << "a second open of the folder was allowed";
    const std::string& message = second.error().message;
    if (second.error().code != ErrorCode::kIoError || message.find("open in another process") == std::string::npos ||
        message.find("(pid " + holder + ")") == std::string::npos) {
      return ::testing::AssertionFailure() << second.error().ToString();
    }
    return ::testing::AssertionSuccess();
  };
  {
    auto index = CreateIndex();
    for (int i = 0; i < 5; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
    EXPECT_TRUE(refused_by(std::to_string(::getpid())));
    EXPECT_EQ(ImageIndex::Create(dir_.string(), vocabulary_, "test-extractor/1").error().code, ErrorCode::kAlreadyExists);
  }
  int ready[2];
  ASSERT_EQ(::pipe(ready), 0);
  const pid_t pid = fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    auto index = ImageIndex::Open(dir_.string());
    if (!index) ::_exit(2);
    (void)!::write(ready[1], "o", 1);
    while (true) ::pause();  // holds the folder until killed
  }
  ::close(ready[1]);
  char byte = 0;
  ASSERT_EQ(::read(ready[0], &byte, 1), 1) << "the child could not open the index";
  ::close(ready[0]);
  EXPECT_TRUE(refused_by(std::to_string(pid)));
  ::kill(pid, SIGKILL);
  int status = 0;
  ASSERT_EQ(::waitpid(pid, &status, 0), pid);
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  ExpectEqualsFresh(**index, Range(0, 5));
}

// A version-1 catalogue (features as the last column of `images`) as the previous code wrote it,
// made from a version-2 index's rows.
TEST_F(LoaderTest, VersionOneCatalogueIsMigratedInPlace) {
  {
    auto index = CreateIndex();
    for (int i = 0; i < 12; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
    ASSERT_TRUE(index->Remove("i11"));  // the sequence is above the highest number left
  }
  const fs::path v2 = dir_ / "v2.sqlite";
  fs::rename(dir_ / "catalogue.sqlite", v2);
  for (const auto& name : CheckpointFiles(dir_)) fs::remove(dir_ / name);
  ExecSql(dir_ / "catalogue.sqlite",
          "CREATE TABLE meta(key TEXT PRIMARY KEY, value TEXT NOT NULL);"
          "CREATE TABLE images(number INTEGER PRIMARY KEY AUTOINCREMENT, id TEXT NOT NULL UNIQUE,"
          " source_path TEXT NOT NULL, width INTEGER NOT NULL, height INTEGER NOT NULL,"
          " num_features INTEGER NOT NULL, metadata_json TEXT NOT NULL, added_unix_ms INTEGER NOT NULL,"
          " features BLOB NOT NULL);"
          "ATTACH '" + v2.string() + "' AS v2;"
          "INSERT INTO meta SELECT key, value FROM v2.meta WHERE key != 'checkpoint';"
          "UPDATE meta SET value = '1' WHERE key = 'schema_version';"
          "INSERT INTO images SELECT i.*, f.blob FROM v2.images i JOIN v2.features f USING (number);"
          "UPDATE sqlite_sequence SET seq = (SELECT seq FROM v2.sqlite_sequence WHERE name = 'images');");
  fs::remove(v2);
  {
    auto index = ImageIndex::Open(dir_.string());
    ASSERT_TRUE(index) << index.error().ToString();
    ExpectEqualsFresh(**index, Range(0, 11));
    // Numbers continue above the removed one: a new image gets number 13.
    ASSERT_TRUE((*index)->Add("i12", Image(12), {}));
  }
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open((dir_ / "catalogue.sqlite").c_str(), &db), SQLITE_OK);
  sqlite3_stmt* stmt = nullptr;
  ASSERT_EQ(sqlite3_prepare_v2(db,
                               "SELECT (SELECT value FROM meta WHERE key = 'schema_version'),"
                               " (SELECT number FROM images WHERE id = 'i12'), (SELECT count(*) FROM features)",
                               -1, &stmt, nullptr),
            SQLITE_OK);
  ASSERT_EQ(sqlite3_step(stmt), SQLITE_ROW);
  EXPECT_STREQ(reinterpret_cast<const char*>(sqlite3_column_text(stmt, 0)), "2");
  EXPECT_EQ(sqlite3_column_int(stmt, 1), 13);
  EXPECT_EQ(sqlite3_column_int(stmt, 2), 12);
  sqlite3_finalize(stmt);
  sqlite3_close(db);
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  std::vector<int> live = Range(0, 11);
  live.push_back(12);
  ExpectEqualsFresh(**index, live);
}

// A damaged BLOB of an image added after the checkpoint (read by the replay) costs that image only.
TEST_F(LoaderTest, DamagedBlobAddedAfterTheCheckpointCostsThatImageOnly) {
  SKIP_KILL_TEST_UNDER_TSAN();
  {
    auto index = CreateIndex();
    for (int i = 0; i < 5; ++i) ASSERT_TRUE(index->Add(NumberedId("i", i), Image(i), {}));
  }
  InChildThenKill([&](ImageIndex& index) { ASSERT_TRUE(index.Add("late", Image(9), {})); });
  ExecSql(dir_ / "catalogue.sqlite",
          "UPDATE features SET blob = substr(blob, 1, 30) || x'ff' || substr(blob, 32) "
          "WHERE number = (SELECT number FROM images WHERE id = 'late')");
  auto index = ImageIndex::Open(dir_.string());
  ASSERT_TRUE(index) << index.error().ToString();
  EXPECT_EQ((*index)->Get("late").error().code, ErrorCode::kNotFound);
  ExpectEqualsFresh(**index, Range(0, 5));
}

}  // namespace
}  // namespace oxbow::index
