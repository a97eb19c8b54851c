#include "api/thumbnails.h"

#include <sqlite3.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>  // the IMREAD_ flags only; the library is loaded by sift/opencv_codecs.cc
#include <opencv2/imgproc.hpp>

#include "sift/opencv_codecs.h"

namespace oxbow::api {

namespace {

constexpr int kSchemaVersion = 1;

Error SqliteError(sqlite3* db, const std::string& what, const std::string& path) {
  return Error{ErrorCode::kIoError, "thumbnail store '" + path + "': " + what + ": " + sqlite3_errmsg(db)};
}

// Finalises a prepared statement on every path out of a function.
struct Statement {
  sqlite3_stmt* stmt = nullptr;
  ~Statement() { sqlite3_finalize(stmt); }
};

}  // namespace

std::optional<std::string> ThumbnailOptions::Check() const {
  if (stored_side_px < 32 || stored_side_px > 2048) return "thumbnail stored_side_px must be in [32, 2048]";
  if (jpeg_quality < 1 || jpeg_quality > 100) return "thumbnail jpeg_quality must be in [1, 100]";
  return std::nullopt;
}

Result<Thumbnail> MakeThumbnail(std::span<const uint8_t> image, int max_side_px, int jpeg_quality,
                                const sift::DecodeOptions& decode) {
  if (max_side_px < 1) return Fail(ErrorCode::kInvalidArgument, "thumbnail size must be >= 1 pixel");
  if (jpeg_quality < 1 || jpeg_quality > 100) return Fail(ErrorCode::kInvalidArgument, "JPEG quality must be in [1, 100]");
  if (image.size() > decode.max_bytes) {
    return Fail(ErrorCode::kImageTooLarge, "image of " + std::to_string(image.size()) + " bytes is over the limit of " +
                                               std::to_string(decode.max_bytes));
  }
  // The header check refuses decompression bombs before OpenCV allocates anything.
  auto header = sift::ReadImageHeader(image);
  if (!header) return std::unexpected(header.error());
  if (header->width * header->height > decode.max_pixels) {
    return Fail(ErrorCode::kImageTooLarge, "image of " + std::to_string(header->width) + " x " +
                                               std::to_string(header->height) + " pixels is over the limit of " +
                                               std::to_string(decode.max_pixels) + " pixels");
  }
  // Decode at the smallest power-of-two reduction that still leaves >= max_side_px (libjpeg scales
  // while decoding, so a 24 MP JPEG never becomes 72 MB of pixels here).
  // A reduction must leave the shortest side >= 1 pixel: OpenCV asserts on an 8000 x 1 panorama reduced
  // to 1000 x 0.
  const uint64_t longest = std::max(header->width, header->height);
  const uint64_t shortest = std::min(header->width, header->height);
  int flags = cv::IMREAD_COLOR;
  if (longest >= 8ull * static_cast<uint64_t>(max_side_px) && shortest >= 8) {
    flags = cv::IMREAD_REDUCED_COLOR_8;
  } else if (longest >= 4ull * static_cast<uint64_t>(max_side_px) && shortest >= 4) {
    flags = cv::IMREAD_REDUCED_COLOR_4;
  } else if (longest >= 2ull * static_cast<uint64_t>(max_side_px) && shortest >= 2) {
    flags = cv::IMREAD_REDUCED_COLOR_2;
  }
  auto decoded = sift::opencv_codecs::Decode(image, flags);  // applies the EXIF orientation (no IMREAD_IGNORE_ORIENTATION)
  if (!decoded) {
    if (decoded.error().code == ErrorCode::kUnsupportedFormat) return std::unexpected(decoded.error());
    return Fail(ErrorCode::kInvalidImage, "cannot decode the image for its thumbnail: " + decoded.error().message);
  }
  cv::Mat pixels = std::move(*decoded);
  if (pixels.empty()) return Fail(ErrorCode::kInvalidImage, "cannot decode the image for its thumbnail");
  const int side = std::max(pixels.cols, pixels.rows);
  if (side > max_side_px) {
    const double scale = static_cast<double>(max_side_px) / side;
    const cv::Size size(std::max(1, static_cast<int>(std::lround(pixels.cols * scale))),
                        std::max(1, static_cast<int>(std::lround(pixels.rows * scale))));
    cv::Mat small;
    cv::resize(pixels, small, size, 0, 0, cv::INTER_AREA);
    pixels = small;
  }
  std::vector<uint8_t> jpeg;
  const auto encoded = sift::opencv_codecs::Encode(".jpg", pixels, jpeg, {cv::IMWRITE_JPEG_QUALITY, jpeg_quality});
  if (!encoded) return std::unexpected(encoded.error());
  if (!*encoded) return Fail(ErrorCode::kInternal, "JPEG encoding of a thumbnail failed");
  return Thumbnail{std::string(jpeg.begin(), jpeg.end()), pixels.cols, pixels.rows};
}

Result<std::unique_ptr<ThumbnailStore>> ThumbnailStore::Open(const std::string& path) {
  sqlite3* db = nullptr;
  const int rc = sqlite3_open_v2(path.c_str(), &db, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE, nullptr);
  if (rc != SQLITE_OK) {
    Error error{ErrorCode::kIoError, "cannot open thumbnail store '" + path + "': " +
                                         (db ? sqlite3_errmsg(db) : sqlite3_errstr(rc))};
    sqlite3_close(db);
    return std::unexpected(error);
  }
  std::unique_ptr<ThumbnailStore> store(new ThumbnailStore(db, path));
  sqlite3_busy_timeout(db, 5000);
  int version = -1;
  {
    Statement s;
    if (sqlite3_prepare_v2(db, "PRAGMA user_version", -1, &s.stmt, nullptr) != SQLITE_OK ||
        sqlite3_step(s.stmt) != SQLITE_ROW) {
      const bool not_db = sqlite3_errcode(db) == SQLITE_NOTADB;
      return Fail(not_db ? ErrorCode::kCorruptData : ErrorCode::kIoError,
                  "thumbnail store '" + path + "' cannot be read: " + sqlite3_errmsg(db));
    }
    version = sqlite3_column_int(s.stmt, 0);
  }
  if (version != 0 && version != kSchemaVersion) {
    return Fail(ErrorCode::kIncompatible, "thumbnail store '" + path + "' has schema version " +
                                              std::to_string(version) + "; this oxbow reads version " +
                                              std::to_string(kSchemaVersion));
  }
  const std::string setup =
      "PRAGMA journal_mode=WAL; PRAGMA synchronous=FULL;"
      "CREATE TABLE IF NOT EXISTS thumbnails(id TEXT PRIMARY KEY, jpeg BLOB NOT NULL, width INTEGER NOT NULL,"
      " height INTEGER NOT NULL, source TEXT NOT NULL);"
      "CREATE TABLE IF NOT EXISTS pending(id TEXT PRIMARY KEY, jpeg BLOB NOT NULL, width INTEGER NOT NULL,"
      " height INTEGER NOT NULL, source TEXT NOT NULL, after_sequence INTEGER NOT NULL);"
      "PRAGMA user_version=" + std::to_string(kSchemaVersion) + ";";
  char* message = nullptr;
  if (sqlite3_exec(db, setup.c_str(), nullptr, nullptr, &message) != SQLITE_OK) {
    Error error{sqlite3_errcode(db) == SQLITE_NOTADB ? ErrorCode::kCorruptData : ErrorCode::kIoError,
                "thumbnail store '" + path + "': " + (message ? message : "setup failed")};
    sqlite3_free(message);
    return std::unexpected(error);
  }
  return store;
}

ThumbnailStore::~ThumbnailStore() { sqlite3_close(db_); }

Status ThumbnailStore::Put(const std::string& id, const Entry& entry) {
  std::lock_guard<std::mutex> lock(mutex_);
  return Write(id, entry, std::nullopt);
}

Status ThumbnailStore::Write(const std::string& id, const Entry& entry, std::optional<uint64_t> after_sequence) {
  Statement s;
  const char* sql = after_sequence.has_value()
                        ? "INSERT OR REPLACE INTO pending(id, jpeg, width, height, source, after_sequence)"
                          " VALUES(?,?,?,?,?,?)"
                        : "INSERT OR REPLACE INTO thumbnails(id, jpeg, width, height, source) VALUES(?,?,?,?,?)";
  if (sqlite3_prepare_v2(db_, sql, -1, &s.stmt, nullptr) != SQLITE_OK) {
    return std::unexpected(SqliteError(db_, "prepare", path_));
  }
  sqlite3_bind_text(s.stmt, 1, id.data(), static_cast<int>(id.size()), SQLITE_TRANSIENT);
  sqlite3_bind_blob(s.stmt, 2, entry.thumbnail.jpeg.data(), static_cast<int>(entry.thumbnail.jpeg.size()), SQLITE_TRANSIENT);
  sqlite3_bind_int(s.stmt, 3, entry.image_width);
  sqlite3_bind_int(s.stmt, 4, entry.image_height);
  sqlite3_bind_text(s.stmt, 5, entry.source.data(), static_cast<int>(entry.source.size()), SQLITE_TRANSIENT);
  if (after_sequence.has_value()) sqlite3_bind_int64(s.stmt, 6, static_cast<sqlite3_int64>(*after_sequence));
  if (sqlite3_step(s.stmt) != SQLITE_DONE) return std::unexpected(SqliteError(db_, "write", path_));
  return Ok();
}

Result<std::optional<ThumbnailStore::Entry>> ThumbnailStore::Get(const std::string& id) const {
  std::lock_guard<std::mutex> lock(mutex_);
  auto read = Read(id, false);
  if (!read) return std::unexpected(read.error());
  auto& found = *read;
  if (!found.has_value()) return std::optional<Entry>();
  return std::optional<Entry>(std::move(found->entry));
}

Result<std::optional<ThumbnailStore::Pending>> ThumbnailStore::GetPending(const std::string& id) const {
  std::lock_guard<std::mutex> lock(mutex_);
  return Read(id, true);
}

Result<std::optional<ThumbnailStore::Pending>> ThumbnailStore::Read(const std::string& id, bool pending) const {
  Statement s;
  const char* sql = pending ? "SELECT jpeg, width, height, source, after_sequence FROM pending WHERE id = ?"
                            : "SELECT jpeg, width, height, source, 0 FROM thumbnails WHERE id = ?";
  if (sqlite3_prepare_v2(db_, sql, -1, &s.stmt, nullptr) != SQLITE_OK) {
    return std::unexpected(SqliteError(db_, "prepare", path_));
  }
  sqlite3_bind_text(s.stmt, 1, id.data(), static_cast<int>(id.size()), SQLITE_TRANSIENT);
  const int rc = sqlite3_step(s.stmt);
  if (rc == SQLITE_DONE) return std::optional<Pending>();
  if (rc != SQLITE_ROW) return std::unexpected(SqliteError(db_, "read", path_));
  Pending read;
  Entry& entry = read.entry;
  const auto* blob = static_cast<const char*>(sqlite3_column_blob(s.stmt, 0));
  entry.thumbnail.jpeg.assign(blob ? blob : "", static_cast<size_t>(sqlite3_column_bytes(s.stmt, 0)));
  entry.image_width = sqlite3_column_int(s.stmt, 1);
  entry.image_height = sqlite3_column_int(s.stmt, 2);
  const auto* source = reinterpret_cast<const char*>(sqlite3_column_text(s.stmt, 3));
  entry.source = source ? source : "";
  read.after_sequence = static_cast<uint64_t>(sqlite3_column_int64(s.stmt, 4));
  // The thumbnail's own size, from its JPEG header (not stored twice).
  auto header = sift::ReadImageHeader(
      {reinterpret_cast<const uint8_t*>(entry.thumbnail.jpeg.data()), entry.thumbnail.jpeg.size()});
  if (!header) {
    return Fail(ErrorCode::kCorruptData, "thumbnail store '" + path_ + "': the thumbnail of '" + id +
                                             "' is not a readable JPEG: " + header.error().message);
  }
  entry.thumbnail.width = static_cast<int>(header->width);
  entry.thumbnail.height = static_cast<int>(header->height);
  return std::optional<Pending>(std::move(read));
}

Status ThumbnailStore::Remove(const std::string& id) {
  std::lock_guard<std::mutex> lock(mutex_);
  return Run("DELETE FROM thumbnails WHERE id = ?", id, "delete");
}

Status ThumbnailStore::PutPending(const std::string& id, const Entry& entry, uint64_t after_sequence) {
  std::lock_guard<std::mutex> lock(mutex_);
  return Write(id, entry, after_sequence);
}

Status ThumbnailStore::Commit(const std::string& id) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (sqlite3_exec(db_, "BEGIN IMMEDIATE", nullptr, nullptr, nullptr) != SQLITE_OK) {
    return std::unexpected(SqliteError(db_, "begin", path_));
  }
  Status moved = Run("INSERT OR REPLACE INTO thumbnails(id, jpeg, width, height, source)"
                     " SELECT id, jpeg, width, height, source FROM pending WHERE id = ?",
                     id, "commit");
  if (moved) moved = Run("DELETE FROM pending WHERE id = ?", id, "commit");
  if (moved && sqlite3_exec(db_, "COMMIT", nullptr, nullptr, nullptr) != SQLITE_OK) {
    moved = std::unexpected(SqliteError(db_, "commit", path_));
  }
  if (!moved) sqlite3_exec(db_, "ROLLBACK", nullptr, nullptr, nullptr);
  return moved;
}

Status ThumbnailStore::DropPending(const std::string& id) {
  std::lock_guard<std::mutex> lock(mutex_);
  return Run("DELETE FROM pending WHERE id = ?", id, "delete");
}

Result<std::vector<std::string>> ThumbnailStore::Ids(bool pending) const {
  std::lock_guard<std::mutex> lock(mutex_);
  Statement s;
  const char* sql = pending ? "SELECT id FROM pending ORDER BY id" : "SELECT id FROM thumbnails ORDER BY id";
  if (sqlite3_prepare_v2(db_, sql, -1, &s.stmt, nullptr) != SQLITE_OK) {
    return std::unexpected(SqliteError(db_, "prepare", path_));
  }
  std::vector<std::string> ids;
  int rc = SQLITE_ROW;
  while ((rc = sqlite3_step(s.stmt)) == SQLITE_ROW) {
    const auto* text = reinterpret_cast<const char*>(sqlite3_column_text(s.stmt, 0));
    ids.emplace_back(text ? text : "", static_cast<size_t>(sqlite3_column_bytes(s.stmt, 0)));
  }
  if (rc != SQLITE_DONE) return std::unexpected(SqliteError(db_, "read", path_));
  return ids;
}

Status ThumbnailStore::Run(const char* sql, const std::string& id, const char* what) {
  Statement s;
  if (sqlite3_prepare_v2(db_, sql, -1, &s.stmt, nullptr) != SQLITE_OK) {
    return std::unexpected(SqliteError(db_, "prepare", path_));
  }
  sqlite3_bind_text(s.stmt, 1, id.data(), static_cast<int>(id.size()), SQLITE_TRANSIENT);
  if (sqlite3_step(s.stmt) != SQLITE_DONE) return std::unexpected(SqliteError(db_, what, path_));
  return Ok();
}

}  // namespace oxbow::api
