// Checkpoints of an index folder: what ImageIndex::Open would otherwise rebuild from every image's
// BLOB (the inverted file with its statistics, and every image's packed words + geometry), saved in
// immutable, checksummed files so that Open reads them and replays only what changed since.
//
// Files (in the index folder, never rewritten once named in a manifest):
//   postings-<generation>.oxck           InvertedFile::SerializeHead() of the checkpointed snapshot: all
//                                        but the postings, and the names of its segment files in order
//                                        (a version-2 file, what older builds wrote, holds the postings
//                                        too: InvertedFile::Serialize(); still read)
//   segment-<generation>-<k>.oxck        InvertedFile::SerializeSegment(): one immutable segment of
//                                        postings, written by the first checkpoint that has it and
//                                        named again by every later one that still has it, so that a
//                                        checkpoint writes only the segments made since the previous
//   geometry-<generation>-<part>.oxck    the packed features of the images live at that checkpoint
//                                        whose numbers lie above the previous checkpoint's high water
//                                        (parts of at most kGeometryPartBytes, verified in parallel)
// A geometry file: magic "OXGE", u32 format version, u32 byte-order mark 0x01020304, u64 image count,
// then per image {u32 number, i32 width, i32 height, u32 feature count, u64 byte offset}, then the
// packed features (PackedFeatures::bytes()) back to back. Little-endian. Version 2 adds {u32 has
// signatures (0 or 1), u32 0} to each image's entry, and an image's data is its packed features
// followed by its PackedFeatures::signature_bytes(). Version 3, the one written, adds {u64 XXH3-64 of
// the image's data (ImageChecksum)}, so that an image can be checked alone when it is first used;
// versions 1 and 2 (no per-image checksum) are still read.
//
// The manifest (CheckpointManifest::Format(), stored in catalogue meta key `checkpoint`) names the
// generation, the high water (every image number up to it is covered: the catalogue's rows up to it
// are the checkpoint's images minus those removed since; rows above it were added since) and each
// file with its size and XXH3-64 checksum. Writing a checkpoint:
//   1. each file: written as <name>.tmp, fsync'ed, renamed to <name>, the folder fsync'ed;
//   2. the manifest committed in one SQLite transaction: the commit point;
//   3. files no manifest names deleted (also at every open: the leftovers of a crash).
// A crash before 2 leaves the previous manifest, whose files are untouched (new files have a new
// generation in their names); a crash after 2 leaves the new one, whose files are complete on disk.
//
// Thread safety: functions only; distinct files may be written and read from different threads.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "index/storage/feature_store.h"
#include "index/storage/mapping_faults.h"
#include "sift/base/error.h"

namespace oxbow::index {

inline constexpr uint64_t kGeometryPartBytes = uint64_t{256} << 20;

struct CheckpointFile {
  std::string name;      // relative to the index folder
  uint64_t size_bytes = 0;
  uint64_t checksum = 0; // XXH3-64 of the whole file
  bool operator==(const CheckpointFile&) const = default;
};

struct CheckpointManifest {
  uint64_t generation = 0;  // 0: no checkpoint
  int64_t high_water = 0;   // every image number <= this is covered
  bool sqrt_tf = true;      // IndexOptions::sqrt_tf of the image sums
  std::vector<CheckpointFile> files;

  std::string Format() const;
  // kCorruptData for text Format() did not write.
  [[nodiscard]] static Result<CheckpointManifest> Parse(const std::string& text);
};

// A whole file in memory, read-only: mapped, or read into the process's own memory.
class MappedFile {
 public:
  enum class Use {
    // A few places at a time (geometry: re-ranking reads some images): the file mapped, no read-ahead,
    // only the pages in use resident.
    kRandom,
    // All of it, often (postings): read into anonymous memory (transparent huge pages where the kernel
    // allows), so that it stays resident however much else goes through the page cache; a mapping of
    // the file would lose its pages to the check of the geometry files after an open, and the first
    // searches would read them back from disk.
    kResident,
  };
  [[nodiscard]] static Result<std::shared_ptr<const MappedFile>> Open(const std::string& path, Use use = Use::kRandom);
  ~MappedFile();
  MappedFile(const MappedFile&) = delete;
  MappedFile& operator=(const MappedFile&) = delete;
  std::span<const uint8_t> bytes() const { return {data_, size_}; }
  // Copies `within` (a part of bytes()) into `out` (as large) with pread instead of through the
  // mapping: no page of it is mapped into the process (a page fault each is dear where page tables
  // are paravirtualised; a thousand images' pages per search). kRandom files only; false when not
  // one, when `within` is not inside bytes(), or on a read error (then read through bytes()).
  bool ReadAt(std::span<const uint8_t> within, std::span<uint8_t> out) const;
  // Copies `within` (a part of bytes()) into `out` (as large): ReadAt where the file keeps its
  // descriptor, else through the mapping followed by Holds(within). False when `within` is not inside
  // bytes(), when the file no longer holds all of it (truncated since it was mapped) or on a read
  // error; the bytes in `out` are then not the file's. Never raises SIGBUS. A kRandom file's mapping
  // is registered with MappingFaultGuard (mapping_faults.h): a page past the end of a file truncated
  // since it was mapped, or one the disk cannot read, reads as zeros instead of raising SIGBUS, so any
  // read of bytes() survives such damage but may see zeros: check what was read (a checksum) before
  // using it, and use the bytes checked (a copy), not a second read of the mapping. Thread-safe.
  bool Copy(std::span<const uint8_t> within, std::span<uint8_t> out) const;
  // Whether the file still holds the bytes of `within`: one fstat of the kept descriptor, else one
  // stat of the path (a file no longer at its path, deleted or replaced, cannot be truncated through
  // it: true). True for kResident files (the bytes are in this process's memory) and for bytes that
  // are not a part of bytes() (not read through this mapping). Thread-safe.
  bool Holds(std::span<const uint8_t> within) const;

 private:
  MappedFile(const uint8_t* data, size_t size, int fd, std::string path, uint64_t device, uint64_t inode)
      : data_(data), size_(size), fd_(fd), path_(std::move(path)), device_(device), inode_(inode) {}
  std::unique_ptr<MappingFaultGuard> fault_guard_;  // kRandom: the mapping's registration; reset before munmap
  const uint8_t* data_;
  size_t size_;
  int fd_;  // kRandom: the file, open for ReadAt; else -1
  std::string path_;  // kRandom: where it was opened (Holds); else empty
  uint64_t device_;   // st_dev and st_ino of the file mapped (Holds)
  uint64_t inode_;
};

using ByteSink = std::function<void(std::span<const uint8_t>)>;

// Writes dir/name durably and atomically (step 1 above) with the bytes `produce` gives its sink, and
// returns its manifest entry. kIoError on any failure (the temporary file is removed).
[[nodiscard]] Result<CheckpointFile> WriteCheckpointFile(const std::string& dir, const std::string& name,
                                                         const std::function<void(const ByteSink&)>& produce);
// Size and checksum of dir/file.name against the manifest, read with pread in 4 MiB blocks that leave
// the page cache as they found it (pages it held stay; pages read from the disk are dropped again) and
// nothing in this process's resident memory. kNotFound if missing, kCorruptData if different.
[[nodiscard]] Status VerifyCheckpointFile(const std::string& dir, const CheckpointFile& file);
// The same check, given up when `stop` returns true (asked before each 4 MiB read): nullopt then.
[[nodiscard]] std::optional<Status> VerifyCheckpointFileUnless(const std::string& dir, const CheckpointFile& file,
                                                               const std::function<bool()>& stop);
// The same check of a file already mapped (`what` names it in errors): kCorruptData if different.
[[nodiscard]] Status VerifyCheckpointBytes(std::span<const uint8_t> bytes, const CheckpointFile& file,
                                           const std::string& what);

// One image of a geometry file.
struct GeometryImage {
  uint32_t number = 0;
  PackedFeatures features;            // views the mapping
  std::optional<uint64_t> checksum;   // ImageChecksum of `features` (read: versions >= 3 only)
};
// XXH3-64 of an image's data in a geometry file: its packed features, then its signatures.
uint64_t ImageChecksum(const PackedFeatures& features);
// Writes the geometry file format for `images` (numbers ascending).
void WriteGeometry(std::span<const GeometryImage> images, const ByteSink& sink);
// The images of a mapped geometry file (each keeps the mapping alive). kCorruptData when inconsistent.
[[nodiscard]] Result<std::vector<GeometryImage>> ReadGeometry(const std::shared_ptr<const MappedFile>& file,
                                                              const std::string& what);

// Deletes the checkpoint files (and temporaries) in `dir` that `manifest` does not name. Best effort:
// a file that cannot be deleted now is deleted at a later call.
void RemoveUnreferencedCheckpointFiles(const std::string& dir, const CheckpointManifest& manifest);

// Test seam: the geometry format version WriteGeometry writes (default and only otherwise written: 3;
// 1 and 2, what older builds wrote, for tests of reading them). Not thread-safe.
void SetGeometryFormatVersionForTesting(uint32_t version);

// Test seam: called at each step of writing a checkpoint ("file-unsynced": a file's bytes written to
// its temporary, before fsync and rename; "segment-written": a postings segment's file complete, before
// the head; "files-written", "manifest-committed", "cleaned"), e.g. to
// kill the process there, and when the checkpointer starts verifying the geometry files an open
// loaded ("verifying-geometry"), e.g. to hold it back, and when it has checked them all
// ("geometry-verified"). Not thread-safe; set it before the index is used.
void SetCheckpointStageHookForTesting(std::function<void(std::string_view stage)> hook);
void CheckpointStage(std::string_view stage);

}  // namespace oxbow::index
