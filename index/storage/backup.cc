#include "index/storage/backup.h"

#include <fcntl.h>
#include <sqlite3.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <climits>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <memory>
#include <mutex>
#include <optional>
#include <utility>
#include <vector>

#include "index/storage/catalogue.h"
#include "index/storage/checkpoint.h"
#include "sift/base/log.h"
#include "sift/base/system.h"

namespace oxbow::index {
namespace {

namespace fs = std::filesystem;

// Attempts before giving up when every snapshot's checkpoint files were replaced before they could be
// opened. A checkpoint follows at least IndexOptions::checkpoint_changes writes, so a second attempt
// practically always succeeds; more than a few means the index checkpoints faster than files open.
constexpr int kMaxAttempts = 8;

Status SyncPath(const std::string& path, int flags) {
  const int fd = ::open(path.c_str(), flags | O_CLOEXEC);
  if (fd < 0 || ::fsync(fd) != 0) {
    const std::string error = ErrnoText();
    if (fd >= 0) ::close(fd);
    return Fail(ErrorCode::kIoError, "cannot sync " + path + ": " + error);
  }
  ::close(fd);
  return Ok();
}

class Fd {
 public:
  explicit Fd(int fd) : fd_(fd) {}
  ~Fd() {
    if (fd_ >= 0) ::close(fd_);
  }
  Fd(Fd&& other) noexcept : fd_(std::exchange(other.fd_, -1)) {}
  Fd(const Fd&) = delete;
  Fd& operator=(const Fd&) = delete;
  Fd& operator=(Fd&&) = delete;
  int get() const { return fd_; }

 private:
  int fd_;
};

// Copies the open file `from` (its whole content) to the new file `to`, fsync'ed; returns the bytes.
Result<uint64_t> CopyFile(const Fd& from, const std::string& what, const std::string& to) {
  Fd out(::open(to.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0644));
  if (out.get() < 0) return Fail(ErrorCode::kIoError, "cannot create " + to + ": " + ErrnoText());
  std::vector<char> buffer(size_t{1} << 20);
  uint64_t total = 0;
  for (;;) {
    const ssize_t n = ::pread(from.get(), buffer.data(), buffer.size(), static_cast<off_t>(total));
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) return Fail(ErrorCode::kIoError, "cannot read " + what + ": " + ErrnoText());
    if (n == 0) break;
    for (ssize_t done = 0; done < n;) {
      const ssize_t w = ::write(out.get(), buffer.data() + done, static_cast<size_t>(n - done));
      if (w < 0 && errno == EINTR) continue;
      if (w < 0) return Fail(ErrorCode::kIoError, "cannot write " + to + ": " + ErrnoText());
      done += w;
    }
    total += static_cast<uint64_t>(n);
  }
  if (::fsync(out.get()) != 0) return Fail(ErrorCode::kIoError, "cannot sync " + to + ": " + ErrnoText());
  return total;
}

// One read transaction on a SQLite file through its own read-only connection: every read, and the
// copy, see the database as it was when the transaction began, whatever other connections commit.
class SqliteSnapshot {
 public:
  static Result<std::unique_ptr<SqliteSnapshot>> Begin(const std::string& path) {
    std::unique_ptr<SqliteSnapshot> s(new SqliteSnapshot(path));
    if (sqlite3_open_v2(path.c_str(), &s->db_, SQLITE_OPEN_READONLY, nullptr) != SQLITE_OK) {
      return s->Failure("cannot open");
    }
    sqlite3_busy_timeout(s->db_, 5000);
    // BEGIN is deferred: the first read starts the transaction (and fixes its WAL snapshot).
    if (sqlite3_exec(s->db_, "BEGIN; SELECT count(*) FROM sqlite_master;", nullptr, nullptr, nullptr) != SQLITE_OK) {
      return s->Failure("cannot read");
    }
    return s;
  }
  ~SqliteSnapshot() {
    if (db_) sqlite3_exec(db_, "ROLLBACK", nullptr, nullptr, nullptr);
    sqlite3_close(db_);
  }
  SqliteSnapshot(const SqliteSnapshot&) = delete;
  SqliteSnapshot& operator=(const SqliteSnapshot&) = delete;

  // The first column of the first row of `sql` as text; nullopt when there is no row.
  Result<std::optional<std::string>> Value(const char* sql) {
    sqlite3_stmt* stmt = nullptr;
    if (sqlite3_prepare_v2(db_, sql, -1, &stmt, nullptr) != SQLITE_OK) return Failure("not an oxbow catalogue:");
    const int rc = sqlite3_step(stmt);
    std::optional<std::string> value;
    if (rc == SQLITE_ROW) {
      const auto* text = reinterpret_cast<const char*>(sqlite3_column_text(stmt, 0));
      value = text ? text : "";
    }
    sqlite3_finalize(stmt);
    if (rc != SQLITE_ROW && rc != SQLITE_DONE) return Failure("cannot read");
    return value;
  }

  // Copies the snapshot into the new file `to` with the online backup API, checks the copy with
  // quick_check and fsyncs it; returns its size.
  Result<uint64_t> CopyTo(const std::string& to) {
    sqlite3* dest = nullptr;
    auto close_dest = [&] { sqlite3_close(dest); };
    if (sqlite3_open_v2(to.c_str(), &dest, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE, nullptr) != SQLITE_OK) {
      const std::string message = dest ? sqlite3_errmsg(dest) : "out of memory";
      close_dest();
      return Fail(ErrorCode::kIoError, "cannot create " + to + ": " + message);
    }
    sqlite3_backup* backup = sqlite3_backup_init(dest, "main", db_, "main");
    int rc = backup ? sqlite3_backup_step(backup, -1) : sqlite3_errcode(dest);
    if (backup) sqlite3_backup_finish(backup);
    if (rc != SQLITE_DONE) {
      const std::string message = sqlite3_errstr(rc);
      close_dest();
      const bool damaged = (rc & 0xff) == SQLITE_CORRUPT || (rc & 0xff) == SQLITE_NOTADB;
      return Fail(damaged ? ErrorCode::kCorruptData : ErrorCode::kIoError,
                  "cannot copy " + path_ + " to " + to + ": " + message);
    }
    // The page copy does not look inside the pages: a damaged source page would be copied silently.
    std::string check;
    sqlite3_exec(
        dest, "PRAGMA quick_check(1)",
        [](void* out, int, char** values, char**) {
          *static_cast<std::string*>(out) = values[0] ? values[0] : "";
          return 0;
        },
        &check, nullptr);
    close_dest();
    if (check != "ok") {
      return Fail(ErrorCode::kCorruptData, path_ + " is damaged (SQLite quick_check of its copy: " +
                                               (check.empty() ? "no answer" : check) + "); nothing was backed up");
    }
    if (auto s = SyncPath(to, O_RDONLY); !s) return std::unexpected(s.error());
    std::error_code ec;
    return static_cast<uint64_t>(fs::file_size(to, ec));
  }

 private:
  explicit SqliteSnapshot(std::string path) : path_(std::move(path)) {}
  std::unexpected<Error> Failure(const std::string& what) const {
    const int rc = db_ ? sqlite3_extended_errcode(db_) : SQLITE_NOMEM;
    const bool damaged = (rc & 0xff) == SQLITE_CORRUPT || (rc & 0xff) == SQLITE_NOTADB;
    return Fail(damaged ? ErrorCode::kCorruptData : ErrorCode::kIoError,
                what + " " + path_ + ": " + (db_ ? sqlite3_errmsg(db_) : "out of memory"));
  }
  std::string path_;
  sqlite3* db_ = nullptr;
};

// What one attempt holds: the snapshots and the open checkpoint files their manifest names.
struct Attempt {
  std::unique_ptr<SqliteSnapshot> catalogue;
  std::vector<std::pair<std::string, std::unique_ptr<SqliteSnapshot>>> extras;  // name, snapshot
  int64_t images = 0;
  CheckpointManifest manifest;
  std::vector<Fd> files;  // manifest.files' order
};

Status BeginSnapshots(const std::string& dir, const BackupOptions& options, Attempt& attempt) {
  std::unique_lock<std::mutex> lock;
  if (options.snapshot_mutex) lock = std::unique_lock<std::mutex>(*options.snapshot_mutex);
  auto catalogue = SqliteSnapshot::Begin((fs::path(dir) / kCatalogueFile).string());
  if (!catalogue) return std::unexpected(catalogue.error());
  attempt.catalogue = std::move(*catalogue);
  for (const auto& name : options.extra_databases) {
    const std::string path = (fs::path(dir) / name).string();
    std::error_code ec;
    if (!fs::exists(path, ec)) continue;
    auto extra = SqliteSnapshot::Begin(path);
    if (!extra) return std::unexpected(extra.error());
    attempt.extras.emplace_back(name, std::move(*extra));
  }
  return Ok();
}

// Begins the snapshots and opens the checkpoint files they name; false when one is already deleted
// (a newer checkpoint committed since: try again).
Result<bool> Prepare(const std::string& dir, const BackupOptions& options, int number, Attempt& attempt) {
  if (auto s = BeginSnapshots(dir, options, attempt); !s) return std::unexpected(s.error());
  if (options.after_snapshot_for_testing) options.after_snapshot_for_testing(number);
  auto images = attempt.catalogue->Value("SELECT count(*) FROM images");
  if (!images) return std::unexpected(images.error());
  attempt.images = std::stoll(images->value_or("0"));
  auto text = attempt.catalogue->Value("SELECT value FROM meta WHERE key = 'checkpoint'");
  if (!text) return std::unexpected(text.error());
  const std::string manifest_text = text->value_or("");
  if (manifest_text.empty()) return true;
  auto manifest = CheckpointManifest::Parse(manifest_text);
  if (!manifest) {
    return Fail(ErrorCode::kCorruptData, "the checkpoint manifest of " + dir + " is damaged: " +
                                             manifest.error().message);
  }
  attempt.manifest = std::move(*manifest);
  for (const auto& file : attempt.manifest.files) {
    const std::string path = (fs::path(dir) / file.name).string();
    Fd fd(::open(path.c_str(), O_RDONLY | O_CLOEXEC));
    if (fd.get() < 0 && errno == ENOENT) return false;
    if (fd.get() < 0) return Fail(ErrorCode::kIoError, "cannot open " + path + ": " + ErrnoText());
    attempt.files.push_back(std::move(fd));
  }
  return true;
}

// Writes the backup into the empty folder `tmp`.
Result<BackupResult> WriteBackup(const std::string& dir, const std::string& tmp, const BackupOptions& options) {
  BackupResult result;
  Attempt attempt;
  for (;;) {
    if (++result.attempts > kMaxAttempts) {
      return Fail(ErrorCode::kResourceExhausted,
                  "the index at " + dir + " wrote a new checkpoint during each of " + std::to_string(kMaxAttempts) +
                      " backup attempts; retry when it is writing less");
    }
    attempt = Attempt{};
    auto ready = Prepare(dir, options, result.attempts, attempt);
    if (!ready) return std::unexpected(ready.error());
    if (*ready) break;
    OXBOW_LOG(kInfo) << "backup of " << dir << ": a new checkpoint replaced the files of generation "
                     << attempt.manifest.generation << "; taking a new snapshot";
  }
  result.images = attempt.images;
  result.generation = attempt.manifest.generation;

  auto copied = attempt.catalogue->CopyTo((fs::path(tmp) / kCatalogueFile).string());
  if (!copied) return std::unexpected(copied.error());
  if (auto s = CheckFeatureBlobs((fs::path(tmp) / kCatalogueFile).string()); !s) return std::unexpected(s.error());
  result.bytes += *copied;
  for (const auto& [name, snapshot] : attempt.extras) {
    auto extra = snapshot->CopyTo((fs::path(tmp) / name).string());
    if (!extra) return std::unexpected(extra.error());
    result.bytes += *extra;
  }
  // The read transactions end here: the writers' WAL can be checkpointed again while files are copied.
  attempt.catalogue.reset();
  attempt.extras.clear();

  for (size_t i = 0; i < attempt.files.size(); ++i) {
    const CheckpointFile& file = attempt.manifest.files[i];
    const std::string source = (fs::path(dir) / file.name).string();
    auto bytes = CopyFile(attempt.files[i], source, (fs::path(tmp) / file.name).string());
    if (!bytes) return std::unexpected(bytes.error());
    result.bytes += *bytes;
    if (auto s = VerifyCheckpointFile(tmp, file); !s) {
      return Fail(s.error().code == ErrorCode::kNotFound ? ErrorCode::kIoError : s.error().code,
                  "checkpoint file " + source + " fails its check against the manifest (" + s.error().message +
                      "); nothing was backed up. Restarting the index rebuilds its checkpoint from the catalogue");
    }
  }
  // The vocabulary copy is never rewritten, but a disk can still damage it: the backup's copy is read
  // and checked against the catalogue, as an open would.
  const std::string vocabulary = (fs::path(dir) / kVocabularyFile).string();
  Fd fd(::open(vocabulary.c_str(), O_RDONLY | O_CLOEXEC));
  if (fd.get() < 0) return Fail(ErrorCode::kIoError, "cannot open " + vocabulary + ": " + ErrnoText());
  const std::string vocabulary_copy = (fs::path(tmp) / kVocabularyFile).string();
  auto bytes = CopyFile(fd, vocabulary, vocabulary_copy);
  if (!bytes) return std::unexpected(bytes.error());
  auto copied_catalogue = Catalogue::Open((fs::path(tmp) / kCatalogueFile).string());
  if (!copied_catalogue) return std::unexpected(copied_catalogue.error());
  if (auto s = CheckVocabularyCopy(dir, (*copied_catalogue)->meta(), vocab::Vocabulary::Read(vocabulary_copy)); !s) {
    return Fail(s.error().code, "nothing was backed up: " + s.error().message);
  }
  result.bytes += *bytes;
  for (const std::string& name : options.extra_files) {
    const std::string source = (fs::path(dir) / name).string();
    Fd extra(::open(source.c_str(), O_RDONLY | O_CLOEXEC));
    if (extra.get() < 0 && errno == ENOENT) continue;
    if (extra.get() < 0) return Fail(ErrorCode::kIoError, "cannot open " + source + ": " + ErrnoText());
    auto extra_bytes = CopyFile(extra, source, (fs::path(tmp) / name).string());
    if (!extra_bytes) return std::unexpected(extra_bytes.error());
    result.bytes += *extra_bytes;
  }
  if (auto s = SyncPath(tmp, O_RDONLY | O_DIRECTORY); !s) return std::unexpected(s.error());
  return result;
}

// A path for a message (CheckBackupFolder refused control characters before any is shown), cut when long.
std::string Shown(const fs::path& path) {
  const std::string& text = path.native();
  return text.size() <= 200 ? text : text.substr(0, 200) + "...";
}

Status Invalid(const std::string& message) { return Fail(ErrorCode::kInvalidArgument, message); }

// The errno of a failed mkdir or rename of the backup folder: the client's choice of place (a name too
// long, a component not a folder, a folder the server may not write, a read-only file system) is 400,
// the disk's failure 500.
Status FolderError(const std::string& what, int error) {
  const std::string message = what + ": " + std::strerror(error);
  switch (error) {
    case ENOENT: return Fail(ErrorCode::kNotFound, message);
    case EEXIST:
    case ENOTEMPTY: return Fail(ErrorCode::kAlreadyExists, message);
    case ENAMETOOLONG:
    case ELOOP:
    case ENOTDIR:
    case EACCES:
    case EPERM:
    case EROFS:
    case EXDEV: return Invalid(message);
    default: return Fail(ErrorCode::kIoError, message);
  }
}

// True when `path` is `folder` or lies inside it (both absolute and normal).
bool IsWithin(const fs::path& path, const fs::path& folder) {
  return std::mismatch(folder.begin(), folder.end(), path.begin(), path.end()).first == folder.end();
}

// `out` as CheckBackupFolder checks it: absolute and lexically normal, without a trailing slash.
Result<fs::path> BackupTarget(const std::string& out) {
  std::error_code ec;
  fs::path target = fs::absolute(out, ec).lexically_normal();
  if (ec) return Fail(ErrorCode::kIoError, "cannot resolve " + Shown(out) + " against the working directory: " + ec.message());
  if (!target.has_filename()) target = target.parent_path();  // a trailing slash
  return target;
}

}  // namespace

Status CheckBackupFolder(const std::string& dir, const std::string& out) {
  if (out.empty()) return Invalid("the backup folder is empty: name a new folder");
  for (size_t i = 0; i < out.size(); ++i) {
    const auto c = static_cast<unsigned char>(out[i]);
    if (c < 0x20 || c == 0x7f) {
      char byte[8];
      std::snprintf(byte, sizeof byte, "0x%02x", c);
      return Invalid("the backup folder's path holds the control character " + std::string(byte) + " at byte " +
                     std::to_string(i) + ": name a folder without control characters");
    }
  }
  if (out.size() > kMaxBackupPathBytes) {
    return Invalid("the backup folder's path is " + std::to_string(out.size()) + " bytes long, at most " +
                   std::to_string(kMaxBackupPathBytes) + " accepted");
  }
  constexpr size_t kMaxName = NAME_MAX - 4;  // the backup is written as "<name>.tmp" first
  for (const fs::path& part : fs::path(out)) {
    if (part == "..") {
      return Invalid("the backup folder " + Shown(out) + " has a '..' component: name the folder by its path without one");
    }
    if (part.native().size() > kMaxName) {
      return Invalid("the name '" + Shown(part) + "' in the backup folder's path is " + std::to_string(part.native().size()) +
                     " bytes long, at most " + std::to_string(kMaxName) + " accepted (the file system's " +
                     std::to_string(NAME_MAX) + " less the '.tmp' of the name the backup is written under first)");
    }
  }
  auto target = BackupTarget(out);
  if (!target) return std::unexpected(target.error());
  if (!target->has_filename()) return Invalid("the root folder cannot be a backup folder: name a new folder");
  // From the root down: no component is a symbolic link and every one above the last is a folder. The
  // path then is its own real path (no link, no "..").
  const fs::path relative = target->relative_path();
  const auto components = static_cast<size_t>(std::distance(relative.begin(), relative.end()));
  fs::path prefix = target->root_path();
  size_t i = 0;
  bool taken = false;  // the last component exists and is not an empty folder
  bool taken_by_file = false;
  for (const fs::path& part : relative) {
    prefix /= part;
    const bool last = ++i == components;
    struct stat st {};
    if (::lstat(prefix.c_str(), &st) != 0) {
      const int error = errno;
      if (error == ENOENT && last) break;
      if (error == ENOENT) {
        return Fail(ErrorCode::kNotFound, "the backup's parent folder " + Shown(target->parent_path()) + " does not exist");
      }
      return FolderError("cannot inspect " + Shown(prefix) + " (a component of the backup folder's path)", error);
    }
    if (S_ISLNK(st.st_mode)) {
      std::error_code ec;
      const fs::path real = fs::weakly_canonical(*target, ec);
      return Invalid(Shown(prefix) + " is a symbolic link: a backup is never written through one; name the folder by its "
                     "real path" + (ec ? std::string() : " (" + Shown(real) + ")"));
    }
    if (!S_ISDIR(st.st_mode) && !last) {
      return Invalid(Shown(prefix) + " is not a folder (it is a component of the backup folder's path)");
    }
    std::error_code ec;
    taken = last && !(S_ISDIR(st.st_mode) && fs::is_empty(prefix, ec));
    taken_by_file = taken && !S_ISDIR(st.st_mode);
  }
  if (!dir.empty()) {
    std::error_code ec;
    const fs::path served = fs::weakly_canonical(fs::absolute(dir, ec), ec);
    if (!ec && IsWithin(*target, served)) {
      return Invalid(Shown(*target) + (*target == served ? " is" : " is inside") + " the index folder " + Shown(served) +
                     " being backed up: back up to a folder outside it");
    }
  }
  if (taken) {
    return Fail(ErrorCode::kAlreadyExists, Shown(*target) + (taken_by_file ? " is a file" : " exists and is not an empty folder") +
                                               "; back up to a new folder");
  }
  return Ok();
}

Result<BackupResult> BackupIndex(const std::string& dir, const std::string& out_in, const BackupOptions& options) {
  if (auto s = CheckHoldsCatalogue(dir); !s) return std::unexpected(s.error());
  if (auto checked = CheckBackupFolder(dir, out_in); !checked) return std::unexpected(checked.error());
  auto target = BackupTarget(out_in);
  if (!target) return std::unexpected(target.error());
  const fs::path out = *target;
  const fs::path parent = out.parent_path();
  const fs::path tmp = out.string() + ".tmp";
  if (::mkdir(tmp.c_str(), 0755) != 0) {
    const int error = errno;
    if (error == EEXIST) {
      return Fail(ErrorCode::kAlreadyExists, tmp.string() + " exists: the leftover of an interrupted backup (or "
                                                             "one running now); remove it and retry");
    }
    return std::unexpected(FolderError("cannot create " + Shown(tmp), error).error());
  }
  auto result = WriteBackup(dir, tmp.string(), options);
  if (result && ::rename(tmp.c_str(), out.c_str()) != 0) {
    const int error = errno;
    result = std::unexpected(FolderError("cannot rename " + Shown(tmp) + " to " + Shown(out), error).error());
  }
  if (result) {
    if (auto s = SyncPath(parent.string(), O_RDONLY | O_DIRECTORY); !s) result = std::unexpected(s.error());
  }
  if (!result) {
    std::error_code ec;
    fs::remove_all(tmp, ec);
    return result;
  }
  OXBOW_LOG(kInfo) << "backed up " << dir << " to " << out.string() << ": " << result->images
                   << " images, checkpoint generation " << result->generation << ", " << result->bytes << " bytes, "
                   << result->attempts << (result->attempts == 1 ? " snapshot" : " snapshots");
  return result;
}

}  // namespace oxbow::index
