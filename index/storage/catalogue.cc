#include "index/storage/catalogue.h"

#include "index/storage/feature_store.h"
#include "index/storage/folder_lock.h"
#include "sift/base/log.h"

#include <sqlite3.h>
#include <unistd.h>

#include <chrono>
#include <cerrno>
#include <condition_variable>
#include <cinttypes>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <thread>

namespace oxbow::index {

// A named namespace, not an anonymous one: Catalogue::Db, a type with external linkage, holds a
// LogCopier.
namespace catalogue_internal {

// Copies the write-ahead log into the database file on a thread and connection of its own. SQLite's
// automatic checkpoint runs inside the COMMIT that takes the log past 1000 pages: that commit copies
// and fsyncs the database file before it returns, which for a batch of 1000 images (17 MB of BLOBs)
// took about a third of the commit. Here a commit waits only for its own frames to reach the log
// (synchronous=FULL), and the copy runs beside the writer's next work. Durability does not depend on
// when the copy runs: a committed transaction is in the fsync'ed log, which SQLite replays on open.
// The log stays bounded: a transaction that finds it over kMaxLogPages first waits for a copy of all
// of it, so that it starts the log again from its beginning.
class LogCopier {
 public:
  static constexpr int kWakePages = 1000;    // SQLite's own threshold for its automatic checkpoint
  static constexpr int kMaxLogPages = 8192;  // 32 MiB of 4 KiB pages: two batches of 1000 images

  // Starts copying for `writer` (a connection in WAL mode) and turns its automatic checkpoint off;
  // nullptr, with the automatic checkpoint left on, when the second connection cannot be opened.
  static std::unique_ptr<LogCopier> Start(const std::string& path, sqlite3* writer) {
    sqlite3* own = nullptr;
    if (sqlite3_open_v2(path.c_str(), &own, SQLITE_OPEN_READWRITE | SQLITE_OPEN_FULLMUTEX, nullptr) != SQLITE_OK ||
        sqlite3_exec(own, "PRAGMA synchronous=FULL", nullptr, nullptr, nullptr) != SQLITE_OK) {
      OXBOW_LOG(kWarning) << path << ": no second connection to copy the write-ahead log in the background ("
                          << (own ? sqlite3_errmsg(own) : "out of memory") << "); commits copy it themselves";
      sqlite3_close(own);
      return nullptr;
    }
    sqlite3_busy_timeout(own, 5000);
    std::unique_ptr<LogCopier> copier(new LogCopier(own, writer));
    copier->thread_ = std::thread([c = copier.get()] { c->Run(); });
    sqlite3_wal_hook(writer, &LogCopier::OnCommit, copier.get());  // replaces the automatic checkpoint
    return copier;
  }

  LogCopier(const LogCopier&) = delete;
  LogCopier& operator=(const LogCopier&) = delete;

  // Restores the writer's automatic checkpoint and stops the thread; what is left in the log is copied
  // when the writer's connection, the last one, closes.
  ~LogCopier() {
    sqlite3_wal_autocheckpoint(writer_, kWakePages);
    {
      std::lock_guard<std::mutex> lock(mutex_);
      stop_ = true;
    }
    wake_.notify_all();
    thread_.join();
    sqlite3_close(own_);
  }

  // Before the writer's BEGIN: waits for a copy of the whole log when it is over kMaxLogPages.
  void BeforeTransaction() {
    std::unique_lock<std::mutex> lock(mutex_);
    if (log_pages_ < kMaxLogPages) return;
    const uint64_t wanted = ++requested_;
    wake_.notify_all();
    done_cv_.wait(lock, [&] { return done_ >= wanted || stop_; });
  }

  // After the writer's transaction has ended (its locks released, so the copy can take all of it).
  void AfterTransaction() {
    std::lock_guard<std::mutex> lock(mutex_);
    if (log_pages_ < kWakePages || requested_ > done_) return;
    ++requested_;
    wake_.notify_all();
  }

 private:
  LogCopier(sqlite3* own, sqlite3* writer) : own_(own), writer_(writer) {}

  // SQLite's commit hook for WAL databases: `pages` is the length of the log after this commit.
  static int OnCommit(void* self, sqlite3* /*db*/, const char* /*name*/, int pages) {
    auto* copier = static_cast<LogCopier*>(self);
    std::lock_guard<std::mutex> lock(copier->mutex_);
    copier->log_pages_ = pages;
    return SQLITE_OK;
  }

  void Run() {
    std::unique_lock<std::mutex> lock(mutex_);
    while (true) {
      wake_.wait(lock, [&] { return stop_ || requested_ > done_; });
      if (stop_) break;
      const uint64_t target = requested_;
      lock.unlock();
      // Passive: never blocks the writer or readers; frames a reader still needs wait for the next one.
      int log = 0, copied = 0;
      const int rc = sqlite3_wal_checkpoint_v2(own_, "main", SQLITE_CHECKPOINT_PASSIVE, &log, &copied);
      if (rc != SQLITE_OK && rc != SQLITE_BUSY) {
        OXBOW_LOG(kWarning) << "copying the catalogue's write-ahead log: " << sqlite3_errmsg(own_)
                            << " (the log keeps every commit; the next copy tries again)";
      }
      lock.lock();
      if (rc == SQLITE_OK && copied == log) log_pages_ = 0;  // the next transaction starts the log again
      done_ = target;
      done_cv_.notify_all();
    }
    done_cv_.notify_all();
  }

  sqlite3* own_;
  sqlite3* writer_;
  std::thread thread_;
  std::mutex mutex_;
  std::condition_variable wake_, done_cv_;
  int log_pages_ = 0;                  // the log's length after the last commit, 0 once all copied
  uint64_t requested_ = 0, done_ = 0;  // copies asked for, and the last asked for that finished
  bool stop_ = false;
};

}  // namespace catalogue_internal

using catalogue_internal::LogCopier;

// Owns the connection and the prepared statements.
struct Catalogue::Db {
  sqlite3* handle = nullptr;
  sqlite3_stmt* insert = nullptr;
  sqlite3_stmt* insert_features = nullptr;
  sqlite3_stmt* remove = nullptr;
  sqlite3_stmt* remove_features = nullptr;
  std::unique_ptr<LogCopier> log_copier;  // writing connections only; stopped before `handle` closes
  ~Db() {
    log_copier.reset();
    sqlite3_finalize(insert);
    sqlite3_finalize(insert_features);
    sqlite3_finalize(remove);
    sqlite3_finalize(remove_features);
    if (handle) sqlite3_close(handle);
  }
};

namespace {

std::string SqliteMessage(sqlite3* db) { return db ? sqlite3_errmsg(db) : "out of memory"; }

ErrorCode CodeFor(int rc) {
  switch (rc & 0xff) {
    case SQLITE_CORRUPT:
    case SQLITE_NOTADB:
      return ErrorCode::kCorruptData;
    default:  // SQLITE_FULL, SQLITE_IOERR, SQLITE_CANTOPEN, SQLITE_READONLY, SQLITE_BUSY, SQLITE_LOCKED, ...
      return ErrorCode::kIoError;
  }
}

// A failure of the environment (I/O, permissions, locks, space) rather than of the file's content.
bool IsEnvironmentFailure(int rc) {
  switch (rc & 0xff) {
    case SQLITE_IOERR:
    case SQLITE_READONLY:
    case SQLITE_CANTOPEN:
    case SQLITE_PERM:
    case SQLITE_BUSY:
    case SQLITE_LOCKED:
    case SQLITE_FULL:
    case SQLITE_NOMEM:
      return true;
    default:
      return false;
  }
}

// What to tell the user about a failure that comes from the environment rather than the content: a
// read-only folder or file is not a damaged catalogue.
std::string Hint(int rc) {
  switch (rc & 0xff) {
    case SQLITE_READONLY:
    case SQLITE_CANTOPEN:
    case SQLITE_PERM:
      return " (the catalogue or its folder cannot be written or opened: check the permissions of the index "
             "folder and that its file system is not mounted read-only)";
    default:
      return "";
  }
}

Status Exec(sqlite3* db, const std::string& sql, const std::string& path) {
  char* error = nullptr;
  const int rc = sqlite3_exec(db, sql.c_str(), nullptr, nullptr, &error);
  if (rc != SQLITE_OK) {
    std::string message = error ? error : SqliteMessage(db);
    sqlite3_free(error);
    return Fail(CodeFor(rc), path + ": " + message + Hint(rc));
  }
  return Ok();
}

Result<std::unique_ptr<Catalogue::Db>> Connect(const std::string& path, int flags) {
  auto db = std::make_unique<Catalogue::Db>();
  const int rc = sqlite3_open_v2(path.c_str(), &db->handle, flags | SQLITE_OPEN_FULLMUTEX, nullptr);
  if (rc != SQLITE_OK) return Fail(CodeFor(rc), "cannot open " + path + ": " + SqliteMessage(db->handle) + Hint(rc));
  sqlite3_busy_timeout(db->handle, 5000);
  sqlite3_extended_result_codes(db->handle, 1);
  return db;
}

int64_t NowUnixMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::system_clock::now().time_since_epoch())
      .count();
}

std::string Quote(const std::string& s) {
  std::string out = "'";
  for (char c : s) {
    out += c;
    if (c == '\'') out += '\'';
  }
  return out + "'";
}

Status Prepare(Catalogue::Db* db, const std::string& path) {
  const char* insert_sql =
      "INSERT INTO images(id, source_path, width, height, num_features, metadata_json, added_unix_ms) "
      "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)";
  if (sqlite3_prepare_v2(db->handle, insert_sql, -1, &db->insert, nullptr) != SQLITE_OK ||
      sqlite3_prepare_v2(db->handle, "INSERT INTO features(number, blob) VALUES (?1, ?2)", -1, &db->insert_features,
                         nullptr) != SQLITE_OK ||
      sqlite3_prepare_v2(db->handle, "DELETE FROM images WHERE number = ?1", -1, &db->remove, nullptr) != SQLITE_OK ||
      sqlite3_prepare_v2(db->handle, "DELETE FROM features WHERE number = ?1", -1, &db->remove_features, nullptr) !=
          SQLITE_OK) {
    return Fail(ErrorCode::kCorruptData, path + ": not an oxbow catalogue (" + SqliteMessage(db->handle) + ")");
  }
  return Ok();
}

// WAL: readers do not block the writer; synchronous=FULL: a commit is fsync'ed before it returns.
Status ConfigureDurability(sqlite3* db, const std::string& path) {
  if (auto s = Exec(db, "PRAGMA journal_mode=WAL; PRAGMA synchronous=FULL;", path); !s) return s;
  return Ok();
}

}  // namespace

Catalogue::Catalogue(std::unique_ptr<Db> db, std::string path, CatalogueMeta meta)
    : db_(std::move(db)), path_(std::move(path)), meta_(std::move(meta)) {}

Catalogue::~Catalogue() = default;

Result<std::unique_ptr<Catalogue>> Catalogue::Create(const std::string& path, const CatalogueMeta& meta_in) {
  std::error_code ec;
  if (std::filesystem::exists(path, ec)) return Fail(ErrorCode::kAlreadyExists, path + " already exists");
  auto db = Connect(path, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE);
  if (!db) return std::unexpected(db.error());
  sqlite3* h = (*db)->handle;
  if (auto s = ConfigureDurability(h, path); !s) return std::unexpected(s.error());
  CatalogueMeta meta = meta_in;
  meta.schema_version = kSchemaVersion;
  meta.created_unix_ms = NowUnixMs();
  char fingerprint[32];
  std::snprintf(fingerprint, sizeof(fingerprint), "%016" PRIx64, meta.vocabulary_fingerprint);
  const std::string sql =
      "BEGIN IMMEDIATE;"
      "CREATE TABLE meta(key TEXT PRIMARY KEY, value TEXT NOT NULL);"
      "CREATE TABLE images(number INTEGER PRIMARY KEY AUTOINCREMENT, id TEXT NOT NULL UNIQUE,"
      " source_path TEXT NOT NULL, width INTEGER NOT NULL, height INTEGER NOT NULL,"
      " num_features INTEGER NOT NULL, metadata_json TEXT NOT NULL, added_unix_ms INTEGER NOT NULL);"
      "CREATE TABLE features(number INTEGER PRIMARY KEY, blob BLOB NOT NULL);"
      "INSERT INTO meta VALUES ('schema_version', " + Quote(std::to_string(meta.schema_version)) + ");"
      "INSERT INTO meta VALUES ('vocabulary_fingerprint', " + Quote(fingerprint) + ");"
      "INSERT INTO meta VALUES ('vocabulary_size', " + Quote(std::to_string(meta.vocabulary_size)) + ");"
      "INSERT INTO meta VALUES ('descriptor_kind', " + Quote(meta.descriptor_kind) + ");"
      "INSERT INTO meta VALUES ('extractor_settings', " + Quote(meta.extractor_settings) + ");"
      "INSERT INTO meta VALUES ('created_unix_ms', " + Quote(std::to_string(meta.created_unix_ms)) + ");"
      "COMMIT;";
  if (auto s = Exec(h, sql, path); !s) return std::unexpected(s.error());
  if (auto s = Prepare(db->get(), path); !s) return std::unexpected(s.error());
  (*db)->log_copier = LogCopier::Start(path, (*db)->handle);
  return std::unique_ptr<Catalogue>(new Catalogue(std::move(*db), path, std::move(meta)));
}

Result<std::unique_ptr<Catalogue>> Catalogue::Open(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) return Fail(ErrorCode::kNotFound, "no index catalogue at " + path);
  // Read-only until validated: a read-write connection checkpoints whatever WAL it finds beside the file
  // into it when it closes, so a foreign WAL would overwrite the catalogue even though the open fails.
  auto db = Connect(path, SQLITE_OPEN_READONLY);
  if (!db) return std::unexpected(db.error());
  sqlite3* h = (*db)->handle;
  sqlite3_db_config(h, SQLITE_DBCONFIG_NO_CKPT_ON_CLOSE, 1, nullptr);
  // Reading the meta table is the first access to the file: a damaged header fails here.
  std::map<std::string, std::string> values;
  sqlite3_stmt* stmt = nullptr;
  int rc = sqlite3_prepare_v2(h, "SELECT key, value FROM meta", -1, &stmt, nullptr);
  if (rc != SQLITE_OK) {
    const std::string message = SqliteMessage(h);
    if (IsEnvironmentFailure(rc)) return Fail(ErrorCode::kIoError, path + " cannot be read: " + message + Hint(rc));
    const bool damaged = (rc & 0xff) == SQLITE_NOTADB || (rc & 0xff) == SQLITE_CORRUPT;
    return Fail(ErrorCode::kCorruptData, path + (damaged ? " is damaged or not a SQLite database: "
                                                         : " is not an oxbow index catalogue (incomplete or foreign): ") +
                                             message);
  }
  while ((rc = sqlite3_step(stmt)) == SQLITE_ROW) {
    const auto* key = reinterpret_cast<const char*>(sqlite3_column_text(stmt, 0));
    const auto* value = reinterpret_cast<const char*>(sqlite3_column_text(stmt, 1));
    if (key == nullptr || value == nullptr) {  // NULL in a damaged meta table (or out of memory)
      sqlite3_finalize(stmt);
      return Fail(ErrorCode::kCorruptData, path + " is damaged: a catalogue meta row holds NULL");
    }
    values[key] = value;
  }
  sqlite3_finalize(stmt);
  if (rc != SQLITE_DONE) {
    if (IsEnvironmentFailure(rc)) return Fail(ErrorCode::kIoError, path + " cannot be read: " + SqliteMessage(h) + Hint(rc));
    return Fail(ErrorCode::kCorruptData, path + " is damaged: " + SqliteMessage(h));
  }
  for (const char* key : {"schema_version", "vocabulary_fingerprint", "vocabulary_size", "extractor_settings"}) {
    if (!values.count(key)) return Fail(ErrorCode::kCorruptData, path + ": catalogue meta lacks '" + key + "'");
  }
  CatalogueMeta meta;
  try {
    meta.schema_version = std::stoi(values["schema_version"]);
    meta.vocabulary_fingerprint = std::stoull(values["vocabulary_fingerprint"], nullptr, 16);
    meta.vocabulary_size = std::stoull(values["vocabulary_size"]);
    meta.created_unix_ms = values.count("created_unix_ms") ? std::stoll(values["created_unix_ms"]) : 0;
  } catch (const std::exception&) {
    return Fail(ErrorCode::kCorruptData, path + ": unreadable catalogue meta values");
  }
  meta.descriptor_kind = values["descriptor_kind"];
  meta.extractor_settings = values["extractor_settings"];
  meta.checkpoint = values["checkpoint"];
  if (meta.schema_version != kSchemaVersion && meta.schema_version != 1) {
    return Fail(ErrorCode::kIncompatible, path + " has schema version " + std::to_string(meta.schema_version) +
                                              "; this build reads version " + std::to_string(kSchemaVersion) +
                                              " (rebuild the index with this version)");
  }
  return std::unique_ptr<Catalogue>(new Catalogue(std::move(*db), path, std::move(meta)));
}

Status Catalogue::OpenForWriting() {
  if (db_->insert != nullptr) return Ok();
  // access() rather than the mode bits: it also sees a read-only mount (and root's permissions).
  const std::string folder = std::filesystem::path(path_).parent_path().string();
  if (::access(folder.empty() ? "." : folder.c_str(), W_OK) != 0) {
    return Fail(ErrorCode::kIoError, "the index folder " + folder + " is not writable (" + std::strerror(errno) +
                                         "): oxbow needs to write its catalogue there; check its permissions and "
                                         "that its file system is not mounted read-only");
  }
  auto db = Connect(path_, SQLITE_OPEN_READWRITE);
  if (!db) return std::unexpected(db.error());
  // SQLite falls back to a read-only connection when the file itself cannot be opened for writing.
  if (sqlite3_db_readonly((*db)->handle, "main") == 1) {
    return Fail(ErrorCode::kIoError, path_ + " is read-only: oxbow needs to write it" + Hint(SQLITE_READONLY));
  }
  if (auto s = ConfigureDurability((*db)->handle, path_); !s) return s;
  if (meta_.schema_version == 1) {
    // The BLOBs move to their own table; DROP COLUMN rewrites `images` without them. One transaction.
    OXBOW_LOG(kInfo) << "migrating the catalogue " << path_ << " from schema version 1 to 2 (one transaction)";
    const std::string sql =
        "BEGIN IMMEDIATE;"
        "CREATE TABLE features(number INTEGER PRIMARY KEY, blob BLOB NOT NULL);"
        "INSERT INTO features(number, blob) SELECT number, features FROM images;"
        "ALTER TABLE images DROP COLUMN features;"
        "UPDATE meta SET value = '2' WHERE key = 'schema_version';"
        "COMMIT;";
    if (auto s = Exec((*db)->handle, sql, path_); !s) {
      sqlite3_exec((*db)->handle, "ROLLBACK", nullptr, nullptr, nullptr);
      return s;
    }
    meta_.schema_version = kSchemaVersion;
    // The migration went through the WAL (about twice the BLOBs' size): copy it into the database and
    // give its space back now rather than when the index closes. Best effort: a reader may hold it.
    sqlite3_exec((*db)->handle, "PRAGMA wal_checkpoint(TRUNCATE)", nullptr, nullptr, nullptr);
  }
  if (auto s = Prepare(db->get(), path_); !s) return s;
  (*db)->log_copier = LogCopier::Start(path_, (*db)->handle);
  db_ = std::move(*db);  // closes the read-only connection, which never checkpoints
  return Ok();
}

Status Catalogue::InTransaction(const std::function<Status()>& body) {
  OXBOW_CHECK(db_->insert != nullptr, "catalogue opened without OpenForWriting");
  // The statements inside BEGIN ... COMMIT are committed (and fsync'ed) together, by the COMMIT.
  if (db_->log_copier) db_->log_copier->BeforeTransaction();
  if (auto s = Exec(db_->handle, "BEGIN IMMEDIATE", path_); !s) return s;
  Status status = body();
  if (status) {
    status = Exec(db_->handle, "COMMIT", path_);
    if (db_->log_copier) db_->log_copier->AfterTransaction();
    if (status) return status;
  }
  // Fails harmlessly when SQLite already rolled the transaction back (a failed COMMIT may do so).
  sqlite3_exec(db_->handle, "ROLLBACK", nullptr, nullptr, nullptr);
  return status;
}

Result<int64_t> Catalogue::Replace(int64_t old_number, const ImageRecord& r, std::span<const uint8_t> features) {
  int64_t number = 0;
  auto status = InTransaction([&]() -> Status {
    if (auto s = Delete(old_number); !s) return s;
    auto inserted = Insert(r, features);
    if (!inserted) return std::unexpected(inserted.error());
    number = *inserted;
    return Ok();
  });
  if (!status) return std::unexpected(status.error());
  return number;
}

Result<std::vector<int64_t>> Catalogue::InsertMany(const std::function<Result<std::optional<Row>>()>& next) {
  std::vector<int64_t> numbers;
  auto status = InTransaction([&]() -> Status {
    while (true) {
      auto row = next();
      if (!row) return std::unexpected(row.error());
      if (!*row) return Ok();
      auto inserted = Insert(*(*row)->record, (*row)->features);
      if (!inserted) return std::unexpected(inserted.error());
      numbers.push_back(*inserted);
    }
  });
  if (!status) return std::unexpected(status.error());
  return numbers;
}

Result<int64_t> Catalogue::Insert(const ImageRecord& r, std::span<const uint8_t> features) {
  OXBOW_CHECK(db_->insert != nullptr, "catalogue opened without OpenForWriting");
  if (sqlite3_get_autocommit(db_->handle) != 0) {  // not inside InTransaction: the two rows commit together
    int64_t number = 0;
    auto status = InTransaction([&]() -> Status {
      auto inserted = Insert(r, features);
      if (!inserted) return std::unexpected(inserted.error());
      number = *inserted;
      return Ok();
    });
    if (!status) return std::unexpected(status.error());
    return number;
  }
  sqlite3_stmt* s = db_->insert;
  sqlite3_reset(s);
  sqlite3_clear_bindings(s);
  sqlite3_bind_text(s, 1, r.id.data(), static_cast<int>(r.id.size()), SQLITE_TRANSIENT);
  sqlite3_bind_text(s, 2, r.source_path.data(), static_cast<int>(r.source_path.size()), SQLITE_TRANSIENT);
  sqlite3_bind_int(s, 3, r.width);
  sqlite3_bind_int(s, 4, r.height);
  sqlite3_bind_int64(s, 5, r.num_features);
  sqlite3_bind_text(s, 6, r.metadata_json.data(), static_cast<int>(r.metadata_json.size()), SQLITE_TRANSIENT);
  sqlite3_bind_int64(s, 7, r.added_unix_ms);
  int rc = sqlite3_step(s);
  sqlite3_reset(s);
  if (rc == SQLITE_CONSTRAINT_UNIQUE || rc == SQLITE_CONSTRAINT_PRIMARYKEY) {
    return Fail(ErrorCode::kAlreadyExists, "an image with id '" + r.id + "' is already indexed");
  }
  const int64_t number = sqlite3_last_insert_rowid(db_->handle);
  if (rc == SQLITE_DONE) {
    sqlite3_stmt* f = db_->insert_features;
    sqlite3_reset(f);
    sqlite3_bind_int64(f, 1, number);
    // Bound without a copy (SQLITE_STATIC): step writes it into the database's pages, and the binding
    // is cleared before `features` can go away.
    sqlite3_bind_blob64(f, 2, features.data(), features.size(), SQLITE_STATIC);
    rc = sqlite3_step(f);
    sqlite3_reset(f);
    sqlite3_clear_bindings(f);
  }
  if (rc != SQLITE_DONE) {
    return Fail(CodeFor(rc), path_ + ": cannot add '" + r.id + "': " + SqliteMessage(db_->handle) + Hint(rc));
  }
  return number;
}

Result<uint64_t> Catalogue::WriteSequence() const {
  sqlite3_stmt* stmt = nullptr;
  int rc = sqlite3_prepare_v2(db_->handle,
                              "SELECT COALESCE((SELECT seq FROM sqlite_sequence WHERE name = 'images'), 0),"
                              " (SELECT COUNT(*) FROM images)",
                              -1, &stmt, nullptr);
  int64_t inserted = 0;
  int64_t live = 0;
  if (rc == SQLITE_OK) {
    rc = sqlite3_step(stmt);
    if (rc == SQLITE_ROW) {
      inserted = sqlite3_column_int64(stmt, 0);
      live = sqlite3_column_int64(stmt, 1);
      rc = SQLITE_OK;
    }
  }
  sqlite3_finalize(stmt);
  if (rc != SQLITE_OK) {
    return Fail(CodeFor(rc), path_ + ": cannot read the write sequence: " + SqliteMessage(db_->handle) + Hint(rc));
  }
  if (live > inserted || live < 0) {
    return Fail(ErrorCode::kCorruptData, path_ + " is damaged: more image rows than numbers ever given");
  }
  return static_cast<uint64_t>(2 * inserted - live);
}

Status Catalogue::Delete(int64_t number) {
  OXBOW_CHECK(db_->remove != nullptr, "catalogue opened without OpenForWriting");
  if (sqlite3_get_autocommit(db_->handle) != 0) return InTransaction([&] { return Delete(number); });
  sqlite3_stmt* s = db_->remove;
  sqlite3_reset(s);
  sqlite3_bind_int64(s, 1, number);
  int rc = sqlite3_step(s);
  sqlite3_reset(s);
  const bool found = rc == SQLITE_DONE && sqlite3_changes(db_->handle) > 0;
  if (found) {
    sqlite3_stmt* f = db_->remove_features;
    sqlite3_reset(f);
    sqlite3_bind_int64(f, 1, number);
    rc = sqlite3_step(f);
    sqlite3_reset(f);
  }
  if (rc != SQLITE_DONE) {
    return Fail(CodeFor(rc), path_ + ": cannot remove image: " + SqliteMessage(db_->handle) + Hint(rc));
  }
  if (!found) return Fail(ErrorCode::kNotFound, "no image number " + std::to_string(number));
  return Ok();
}

Status Catalogue::SetCheckpoint(const std::string& manifest) {
  return InTransaction([&]() -> Status {
    sqlite3_stmt* stmt = nullptr;
    if (sqlite3_prepare_v2(db_->handle, "INSERT OR REPLACE INTO meta(key, value) VALUES ('checkpoint', ?1)", -1,
                           &stmt, nullptr) != SQLITE_OK) {
      return Fail(ErrorCode::kIoError, path_ + ": " + SqliteMessage(db_->handle));
    }
    sqlite3_bind_text(stmt, 1, manifest.data(), static_cast<int>(manifest.size()), SQLITE_TRANSIENT);
    const int rc = sqlite3_step(stmt);
    sqlite3_finalize(stmt);
    if (rc != SQLITE_DONE) {
      return Fail(CodeFor(rc), path_ + ": cannot record the checkpoint: " + SqliteMessage(db_->handle) + Hint(rc));
    }
    meta_.checkpoint = manifest;
    return Ok();
  });
}

namespace {

// Steps `stmt` to its end, calling row() for each row; the error of row() or of SQLite.
Status StepAll(sqlite3* db, sqlite3_stmt* stmt, const std::string& path, const std::function<Status()>& row) {
  int rc;
  Status status = Ok();
  while ((rc = sqlite3_step(stmt)) == SQLITE_ROW) {
    status = row();
    if (!status) break;
  }
  const bool done = rc == SQLITE_DONE || !status;
  const std::string message = SqliteMessage(db);
  sqlite3_finalize(stmt);
  if (!status) return status;
  if (!done && IsEnvironmentFailure(rc)) return Fail(ErrorCode::kIoError, path + " cannot be read: " + message + Hint(rc));
  if (!done) return Fail(ErrorCode::kCorruptData, path + " is damaged: " + message);
  return Ok();
}

}  // namespace

Status Catalogue::ForEachFeaturesAfter(int64_t after,
                                       const std::function<Status(int64_t, std::span<const uint8_t>)>& fn) const {
  OXBOW_CHECK(meta_.schema_version == kSchemaVersion);
  sqlite3_stmt* stmt = nullptr;
  if (sqlite3_prepare_v2(db_->handle, "SELECT number, blob FROM features WHERE number > ?1 ORDER BY number", -1,
                         &stmt, nullptr) != SQLITE_OK) {
    return Fail(ErrorCode::kCorruptData, path_ + ": " + SqliteMessage(db_->handle));
  }
  sqlite3_bind_int64(stmt, 1, after);
  return StepAll(db_->handle, stmt, path_, [&] {
    const auto* blob = static_cast<const uint8_t*>(sqlite3_column_blob(stmt, 1));
    return fn(sqlite3_column_int64(stmt, 0),
              std::span<const uint8_t>(blob, static_cast<size_t>(sqlite3_column_bytes(stmt, 1))));
  });
}

Result<std::vector<uint8_t>> Catalogue::ReadFeatures(int64_t number) const {
  OXBOW_CHECK(meta_.schema_version == kSchemaVersion);
  sqlite3_stmt* stmt = nullptr;
  if (sqlite3_prepare_v2(db_->handle, "SELECT blob FROM features WHERE number = ?1", -1, &stmt, nullptr) != SQLITE_OK) {
    return Fail(ErrorCode::kCorruptData, path_ + ": " + SqliteMessage(db_->handle));
  }
  sqlite3_bind_int64(stmt, 1, number);
  std::optional<std::vector<uint8_t>> out;
  auto status = StepAll(db_->handle, stmt, path_, [&] {
    const auto* blob = static_cast<const uint8_t*>(sqlite3_column_blob(stmt, 0));
    out.emplace(blob, blob + sqlite3_column_bytes(stmt, 0));
    return Ok();
  });
  if (!status) return std::unexpected(status.error());
  if (!out) return Fail(ErrorCode::kNotFound, path_ + ": no features of image number " + std::to_string(number));
  return std::move(*out);
}

Status Catalogue::CheckRecords() const {
  sqlite3_stmt* stmt = nullptr;
  if (sqlite3_prepare_v2(db_->handle, "PRAGMA integrity_check(images)", -1, &stmt, nullptr) != SQLITE_OK) {
    return Fail(ErrorCode::kCorruptData, path_ + " is damaged: " + SqliteMessage(db_->handle));
  }
  std::vector<std::string> findings;
  auto status = StepAll(db_->handle, stmt, path_, [&] {
    const auto* text = reinterpret_cast<const char*>(sqlite3_column_text(stmt, 0));
    findings.emplace_back(text != nullptr ? text : "");
    return Ok();
  });
  if (!status) return status;
  if (findings.size() == 1 && findings[0] == "ok") return Ok();
  std::string message = path_ + " is damaged (SQLite's integrity check of its image records: " +
                        (findings.empty() ? std::string("no answer") : findings[0]);
  if (findings.size() > 1) message += ", and " + std::to_string(findings.size() - 1) + " more";
  return Fail(ErrorCode::kCorruptData, message + "); restore it from a backup, or rebuild the index from the source images");
}

namespace {

// Catalogue::FindDamagedFeatures of the catalogue open as `db` (`path` names it in errors).
Result<std::vector<Catalogue::DamagedImage>> FindDamagedFeaturesIn(sqlite3* db, const std::string& path,
                                                                   uint64_t* images) {
  sqlite3_stmt* stmt = nullptr;
  if (sqlite3_prepare_v2(db,
                         "SELECT i.number, i.id, f.blob FROM images i LEFT JOIN features f ON f.number = i.number "
                         "ORDER BY i.number",
                         -1, &stmt, nullptr) != SQLITE_OK) {
    return Fail(ErrorCode::kCorruptData, path + ": " + SqliteMessage(db));
  }
  std::vector<Catalogue::DamagedImage> out;
  uint64_t rows = 0;
  auto status = StepAll(db, stmt, path, [&] {
    ++rows;
    Catalogue::DamagedImage image;
    image.number = sqlite3_column_int64(stmt, 0);
    const auto* id = reinterpret_cast<const char*>(sqlite3_column_text(stmt, 1));
    image.id.assign(id != nullptr ? id : "", static_cast<size_t>(sqlite3_column_bytes(stmt, 1)));
    if (sqlite3_column_type(stmt, 2) == SQLITE_NULL) {
      image.why = "no feature BLOB";
      out.push_back(std::move(image));
      return Ok();
    }
    const auto* blob = static_cast<const uint8_t*>(sqlite3_column_blob(stmt, 2));
    auto features = PackedFeatures::Deserialize(
        std::span<const uint8_t>(blob, static_cast<size_t>(sqlite3_column_bytes(stmt, 2))), "its feature BLOB");
    if (!features) {
      image.why = features.error().message;
      out.push_back(std::move(image));
    }
    return Ok();
  });
  if (!status) return std::unexpected(status.error());
  if (images != nullptr) *images = rows;
  return out;
}

}  // namespace

Result<std::vector<Catalogue::DamagedImage>> Catalogue::FindDamagedFeatures(uint64_t* images) const {
  OXBOW_CHECK(meta_.schema_version == kSchemaVersion);
  return FindDamagedFeaturesIn(db_->handle, path_, images);
}

Status CheckFeatureBlobs(const std::string& path) {
  // Read-write: the last connection to close removes the WAL and shared-memory files it made.
  auto db = Connect(path, SQLITE_OPEN_READWRITE);
  if (!db) return std::unexpected(db.error());
  auto damaged = FindDamagedFeaturesIn((*db)->handle, path, nullptr);
  if (!damaged) return std::unexpected(damaged.error());
  if (damaged->empty()) return Ok();
  const Catalogue::DamagedImage& first = damaged->front();
  return Fail(ErrorCode::kCorruptData,
              path + ": the feature BLOB of image '" + first.id + "' fails its check (" + first.why + ")" +
                  (damaged->size() > 1 ? ", and " + std::to_string(damaged->size() - 1) + " more" : std::string()) +
                  "; `oxbow index check --index DIR` lists them, --drop-damaged deletes them");
}

Status CheckHoldsCatalogue(const std::string& dir) {
  std::error_code ec;
  if (std::filesystem::is_regular_file(std::filesystem::path(dir) / kCatalogueFile, ec)) return Ok();
  return Fail(ErrorCode::kNotFound, "no index at " + dir + " (missing " + kCatalogueFile + ")");
}

Status CheckVocabularyCopy(const std::string& dir, const CatalogueMeta& meta, const Result<vocab::Vocabulary>& copy) {
  char fingerprint[17];
  std::snprintf(fingerprint, sizeof fingerprint, "%016" PRIx64, meta.vocabulary_fingerprint);
  const std::string restore = "; the index was built with a vocabulary of " + std::to_string(meta.vocabulary_size) +
                              " words, fingerprint " + fingerprint + " (`oxbow vocab info FILE` prints a file's): " +
                              "copy that file to " + (std::filesystem::path(dir) / kVocabularyFile).string() +
                              ", or restore a backup";
  if (!copy) {
    return Fail(copy.error().code, "index " + dir + ": its vocabulary copy is unusable: " + copy.error().message + restore);
  }
  if (copy->fingerprint() != meta.vocabulary_fingerprint || copy->size() != meta.vocabulary_size) {
    return Fail(ErrorCode::kIncompatible, "index " + dir + ": vocabulary copy " + kVocabularyFile +
                                              " does not match the catalogue (fingerprint or size differ)" + restore);
  }
  return Ok();
}

Result<IndexCheck> CheckIndexFolder(const std::string& dir, bool drop_damaged) {
  // Before the lock, which would create its file: a folder that holds no index is left as it is.
  if (auto s = CheckHoldsCatalogue(dir); !s) return std::unexpected(s.error());
  auto lock = FolderLock::Acquire(dir);
  if (!lock) return std::unexpected(lock.error());
  auto catalogue = Catalogue::Open((std::filesystem::path(dir) / kCatalogueFile).string());
  if (!catalogue) return std::unexpected(catalogue.error());
  if ((*catalogue)->meta().schema_version != kSchemaVersion) {
    return Fail(ErrorCode::kIncompatible, "the catalogue of " + dir + " has schema version " +
                                              std::to_string((*catalogue)->meta().schema_version) +
                                              ": open the index once (oxbow index info) to migrate it, then check it");
  }
  if (auto s = CheckVocabularyCopy(dir, (*catalogue)->meta(),
                                   vocab::Vocabulary::Read((std::filesystem::path(dir) / kVocabularyFile).string()));
      !s) {
    return std::unexpected(s.error());
  }
  if (auto s = (*catalogue)->CheckRecords(); !s) return std::unexpected(s.error());
  IndexCheck out;
  auto damaged = (*catalogue)->FindDamagedFeatures(&out.images);
  if (!damaged) return std::unexpected(damaged.error());
  out.damaged = std::move(*damaged);
  if (drop_damaged && !out.damaged.empty()) {
    if (auto s = (*catalogue)->OpenForWriting(); !s) return std::unexpected(s.error());
    for (const Catalogue::DamagedImage& image : out.damaged) {
      if (auto s = (*catalogue)->Delete(image.number); !s) return std::unexpected(s.error());
      OXBOW_LOG(kWarning) << "index " << dir << ": dropped image '" << image.id << "' (" << image.why << ")";
    }
    out.dropped = true;
  }
  return out;
}

Status Catalogue::ForEach(const std::function<Status(CatalogueRow&&)>& fn, bool with_features) const {
  sqlite3_stmt* stmt = nullptr;
  const std::string columns = "i.number, i.id, i.source_path, i.width, i.height, i.num_features, i.metadata_json, "
                              "i.added_unix_ms";
  std::string sql = "SELECT " + columns + " FROM images i ORDER BY i.number";
  if (with_features) {
    sql = meta_.schema_version == 1
              ? "SELECT " + columns + ", i.features FROM images i ORDER BY i.number"
              : "SELECT " + columns + ", f.blob FROM images i LEFT JOIN features f ON f.number = i.number "
                                      "ORDER BY i.number";
  }
  if (sqlite3_prepare_v2(db_->handle, sql.c_str(), -1, &stmt, nullptr) != SQLITE_OK) {
    return Fail(ErrorCode::kCorruptData, path_ + ": " + SqliteMessage(db_->handle));
  }
  auto text = [&](int col) {
    const auto* p = reinterpret_cast<const char*>(sqlite3_column_text(stmt, col));
    return std::string(p ? p : "", static_cast<size_t>(sqlite3_column_bytes(stmt, col)));
  };
  return StepAll(db_->handle, stmt, path_, [&]() -> Status {
    CatalogueRow row;
    row.number = sqlite3_column_int64(stmt, 0);
    row.record.id = text(1);
    row.record.source_path = text(2);
    row.record.width = sqlite3_column_int(stmt, 3);
    row.record.height = sqlite3_column_int(stmt, 4);
    row.record.num_features = static_cast<uint32_t>(sqlite3_column_int64(stmt, 5));
    row.record.metadata_json = text(6);
    row.record.added_unix_ms = sqlite3_column_int64(stmt, 7);
    if (with_features) {
      if (sqlite3_column_type(stmt, 8) == SQLITE_NULL) {
        return Fail(ErrorCode::kCorruptData, path_ + " is damaged: image '" + row.record.id + "' has no features");
      }
      const auto* blob = static_cast<const uint8_t*>(sqlite3_column_blob(stmt, 8));
      row.features.assign(blob, blob + sqlite3_column_bytes(stmt, 8));
    }
    return fn(std::move(row));
  });
}

}  // namespace oxbow::index
