// The geometry files of an index's checkpoints as the running index uses them: each file whose images
// view its mapping is a GeometryPart, which checks an image's data at every use, checks the whole file
// once on request (the checkpointer's background check), and reads the images of a damaged file from
// the catalogue instead; and the compaction rule that decides which files a checkpoint keeps.
//
// Why on use: Open checks a geometry file's size and image table but not its checksum (reading every
// geometry byte took most of an open at 1M images). Every use of an image copies the image's data out
// of the file (MappedFile::Copy: pread, so no page is mapped, and a file truncated under the running
// index gives a short read, not SIGBUS), checks the copy against the image's checksum (format
// version 3; ~9 KB hashed per image) and hands out the copy: the bytes used are the bytes checked,
// whatever happens to the file meanwhile (truncated, written in place, a read error). A file without
// per-image checksums (versions 1 and 2, which only older builds wrote) is checked whole at the first
// use of one of its images (the caller waits, concurrent callers wait for the same check), and not
// again; a copy from it is checked for truncation only. A part that fails a check is never served: its
// images are read from the catalogue's BLOBs (through a read-only connection of its own, on demand) and
// the next checkpoint rewrites them into new files. What is still read through the mapping (the header
// and image table at open, a copy where the file keeps no descriptor) cannot kill the process either: a
// page the file no longer holds reads as zeros (mapping_faults.h), which those checks then find.
//
// Thread safety: every GeometryPart method may be called from any thread. Its two mutexes are leaves
// (nothing else is locked while one is held, except the catalogue's own inside repair_mutex_).
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <span>
#include <string>
#include <vector>

#include "index/storage/catalogue.h"
#include "index/storage/checkpoint.h"
#include "index/storage/feature_store.h"

namespace oxbow::index {

// One geometry file of a checkpoint whose images' entries view its mapping (an open loaded it, or the
// checkpointer wrote it and moved the images there: Checkpointer). Immutable but for its check state.
class GeometryPart {
 public:
  // The file `file` of folder `dir`, mapped as `mapped` (null: the images' views are plain memory).
  GeometryPart(std::string dir, CheckpointFile file, std::shared_ptr<const MappedFile> mapped = nullptr)
      : dir_(std::move(dir)), file_(std::move(file)), mapped_(std::move(mapped)) {}

  const CheckpointFile& file() const { return file_; }
  // True when the file matches its manifest entry; verifies it on the first call (logged when not).
  bool Verified() const;
  // The same, except that a check still to do gives up when `stop` returns true (asked between reads):
  // nullopt then, and a later call checks again. Concurrent callers wait for the same check.
  std::optional<bool> VerifiedUnless(const std::function<bool()>& stop) const;
  // Verified and found damaged (false while not verified yet).
  bool Damaged() const { return state_.load(std::memory_order_acquire) == kDamaged; }
  // The bytes of an image's data that `stored` (its view of this file) spans: features, then signatures.
  static size_t DataBytes(const PackedFeatures& stored) {
    return stored.bytes().size() + stored.signature_bytes().size();
  }
  // Image `number`'s data (`stored`: its view of this file; `checksum`: its checksum in the file, when
  // the file has them) copied into `buffer` (DataBytes(stored) bytes) and viewed there by *out (which
  // `owner`, possibly null, keeps alive), when the copy passes its check. False when the file is known
  // damaged, no longer holds the image's bytes or the copy fails its check (the file is then marked
  // damaged: its images are read from the catalogue from now on).
  bool CopyChecked(uint32_t number, const PackedFeatures& stored, std::optional<uint64_t> checksum,
                   std::span<uint8_t> buffer, std::shared_ptr<const void> owner, PackedFeatures* out) const;
  // CopyChecked into memory of the result's own; nullopt when it fails.
  std::optional<PackedFeatures> Copied(uint32_t number, const PackedFeatures& stored,
                                       std::optional<uint64_t> checksum) const;
  // Image `number`'s features to use: Copied(), else the image's features from the catalogue (no
  // features when they cannot be read there, logged: a search then finds no matches in it, never wrong
  // ones).
  PackedFeatures Checked(uint32_t number, const PackedFeatures& stored, std::optional<uint64_t> checksum) const;

 private:
  static constexpr int kUnverified = 0, kGood = 1, kDamaged = 2;
  // `from` (a part of this file's mapping) copied into `to` (as large); false when the file no longer
  // holds it or it cannot be read.
  bool Copy(std::span<const uint8_t> from, std::span<uint8_t> to) const;
  void MarkDamaged(const std::string& why) const;
  PackedFeatures FromCatalogue(uint32_t number) const;  // repair_mutex_ held

  const std::string dir_;
  const CheckpointFile file_;
  const std::shared_ptr<const MappedFile> mapped_;  // the file, which `stored` views; may be null
  mutable std::atomic<int> state_{kUnverified};     // kUnverified, kGood or kDamaged (damage wins)
  // verify_mutex_ guards checked_ and makes concurrent whole-file checks one check.
  mutable std::mutex verify_mutex_;
  mutable bool checked_ = false;  // the whole file was checked
  // repair_mutex_ guards the read-only catalogue connection and the images read from it, which are
  // made on first need and kept.
  mutable std::mutex repair_mutex_;
  mutable std::unique_ptr<Catalogue> catalogue_;
  mutable std::map<uint32_t, std::unique_ptr<const PackedFeatures>> repaired_;
};

// Per geometry file of a checkpoint, the numbers of the images it holds, ascending (what its image
// table says): which file holds an image, so that a checkpoint can tell how much of a file is live.
using GeometryContents = std::map<std::string, std::shared_ptr<const std::vector<uint32_t>>>;

// Compaction of the geometry files. A checkpoint keeps a geometry file of the previous one as it is,
// or drops it from its manifest and writes the file's live images into its own new files (then the
// file is deleted once the new manifest is committed). It drops a file found damaged, a file less than
// half of whose images are live (so the files on disk hold at most about twice the live images' bytes,
// plus what the last checkpoint wrote), and, when more than kMaxSmallGeometryFiles of the files it
// would keep are small (under kSmallGeometryFileBytes: a checkpoint after a few changes writes one),
// all small ones, merged into its new file. Under endless churn the geometry files (and the descriptors
// their mappings keep, MappedFile) therefore stay at most kMaxSmallGeometryFiles + 1 small ones plus
// 2 x (live bytes) / kSmallGeometryFileBytes large ones; the merge of the small files rewrites at most
// kMaxSmallGeometryFiles x kSmallGeometryFileBytes every kMaxSmallGeometryFiles checkpoints.
inline constexpr uint64_t kSmallGeometryFileBytes = kGeometryPartBytes / 4;
inline constexpr size_t kMaxSmallGeometryFiles = 8;

// The geometry files of `previous` a checkpoint keeps (see above): `contents` gives their images,
// `damaged` those found damaged, `is_live` whether an image number is live now. A file missing from
// `contents` is dropped (its live images are rewritten, which is always safe).
std::set<std::string> KeptGeometry(const CheckpointManifest& previous, const GeometryContents& contents,
                                   const std::set<std::string>& damaged, const std::function<bool(uint32_t)>& is_live);

}  // namespace oxbow::index
