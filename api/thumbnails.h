// Thumbnails of indexed images, for the web page and any client that shows results: small colour
// JPEGs kept in their own SQLite file beside the index (thumbnails.sqlite), so that an uploaded image
// (which has no source file on the server) can still be shown after a restart.
//
//   MakeThumbnail      encoded image bytes -> JPEG whose longest side is at most N pixels (colour,
//                      EXIF orientation applied, area downscaling, never upscaled)
//   ThumbnailStore     id -> {JPEG, the image's width/height/source when it was made}
//
// The store holds one thumbnail per id at ThumbnailOptions::stored_side_px; smaller sizes are made
// from it on request (api::Service::Thumbnail). A stored entry remembers the image's size and source
// so a reader can tell that the image under that id was since replaced by another (stale entry).
//
// File format: SQLite, `PRAGMA user_version` = 1, table thumbnails(id TEXT PRIMARY KEY, jpeg BLOB,
// width INTEGER, height INTEGER, source TEXT); WAL with synchronous=FULL, so a Put that returned is
// durable. Other versions are refused (kIncompatible). A second table pending(id TEXT PRIMARY KEY, the
// same columns, after_sequence INTEGER) holds the thumbnail of an image whose index commit is under way
// (created when missing; a reader that does not know it ignores it).
//
// Committing with the index (two files, no shared transaction): a writer first puts the new thumbnail
// durably as pending, stamped with the index's write sequence (index::ImageIndex::write_sequence) before
// the commit, then commits the image in the index, then moves the pending entry over the committed one
// (Commit, one transaction), or drops it when the index refused the image. The committed entry of an id
// is never overwritten before its image is, so a crash between the two files' commits can leave the old
// image with its own thumbnail and a pending entry, or the new image with its thumbnail pending; opening
// the service settles both (api::Service::Open): a pending entry is committed when its image is indexed
// and the index's write sequence moved past its stamp, else dropped, and committed entries of ids that
// are not indexed (a crash between an index delete and the thumbnail's) are removed.
//
// Thread safety: MakeThumbnail is reentrant; a ThumbnailStore may be used from any number of threads
// (one connection behind a mutex; each call is one short statement).
#pragma once

#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "sift/base/error.h"
#include "sift/image.h"

struct sqlite3;

namespace oxbow::api {

struct ThumbnailOptions {
  // Longest side of the stored thumbnail, pixels, [32, 2048]. 512 keeps enough detail for the web
  // page's match view (features are re-extracted from it) at about 20-50 KB per photo.
  int stored_side_px = 512;
  // JPEG quality of stored and resized thumbnails, [1, 100].
  int jpeg_quality = 80;

  std::optional<std::string> Check() const;
};

struct Thumbnail {
  std::string jpeg;  // JPEG bytes
  int width = 0;     // pixels of the thumbnail
  int height = 0;
};

// Decodes `image` in colour (limits of `decode`: max_bytes, max_pixels; its max_image_side_px is
// ignored), applies the EXIF orientation and downscales it (cv::INTER_AREA) so that the longest side is
// at most max_side_px; never upscales. Large JPEGs are decoded at 1/2, 1/4 or 1/8 scale directly.
// Errors as sift::DecodeImage (kInvalidImage, kImageTooLarge, kUnsupportedFormat), kInvalidArgument for
// max_side_px < 1 or quality outside [1, 100].
[[nodiscard]] Result<Thumbnail> MakeThumbnail(std::span<const uint8_t> image, int max_side_px, int jpeg_quality,
                                              const sift::DecodeOptions& decode);

class ThumbnailStore {
 public:
  struct Entry {
    Thumbnail thumbnail;
    int image_width = 0;   // the indexed image's size (pixels) and source when the thumbnail was made
    int image_height = 0;
    std::string source;
  };

  // Opens or creates the store file. kIoError when it cannot be opened, kIncompatible for another
  // schema version, kCorruptData when it is not a SQLite file.
  [[nodiscard]] static Result<std::unique_ptr<ThumbnailStore>> Open(const std::string& path);
  ~ThumbnailStore();
  ThumbnailStore(const ThumbnailStore&) = delete;
  ThumbnailStore& operator=(const ThumbnailStore&) = delete;

  // Inserts or replaces the entry of `id`, durably. kIoError on a write failure.
  [[nodiscard]] Status Put(const std::string& id, const Entry& entry);
  // The entry of `id`, nullopt when there is none. kIoError / kCorruptData on read failures.
  [[nodiscard]] Result<std::optional<Entry>> Get(const std::string& id) const;
  // Removes the entry of `id` (no error when there is none).
  [[nodiscard]] Status Remove(const std::string& id);

  // The pending entry of an image being committed in the index (see the file comment), durably.
  // `after_sequence`: the index's write sequence before that commit. kIoError on a write failure.
  [[nodiscard]] Status PutPending(const std::string& id, const Entry& entry, uint64_t after_sequence);
  // The pending entry of `id` and its stamp, nullopt when there is none. Errors as Get.
  struct Pending {
    Entry entry;
    uint64_t after_sequence = 0;
  };
  [[nodiscard]] Result<std::optional<Pending>> GetPending(const std::string& id) const;
  // Makes the pending entry of `id` its entry, in one transaction (no-op when none is pending).
  [[nodiscard]] Status Commit(const std::string& id);
  // Drops the pending entry of `id` (no error when there is none).
  [[nodiscard]] Status DropPending(const std::string& id);
  // The ids with an entry (pending = false) or a pending entry (pending = true), in id order.
  [[nodiscard]] Result<std::vector<std::string>> Ids(bool pending) const;

  const std::string& path() const { return path_; }

 private:
  ThumbnailStore(sqlite3* db, std::string path) : db_(db), path_(std::move(path)) {}
  Result<std::optional<Pending>> Read(const std::string& id, bool pending) const;  // mutex_ held
  // Writes `entry` under `id` into the committed table, or into the pending one stamped with
  // `after_sequence` when it has a value.
  Status Write(const std::string& id, const Entry& entry, std::optional<uint64_t> after_sequence);  // mutex_ held
  Status Run(const char* sql, const std::string& id, const char* what);           // mutex_ held
  mutable std::mutex mutex_;  // guards db_ (one statement at a time)
  sqlite3* db_;
  std::string path_;
};

}  // namespace oxbow::api
