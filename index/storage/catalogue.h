// The durable catalogue of an index: one SQLite database (catalogue.sqlite) in WAL mode with
// synchronous=FULL, so every committed transaction is on disk before Insert/Delete return and a crash or
// kill -9 at any moment leaves either the old or the new state (SQLite's journal rolls back a half-done
// transaction at the next open).
//
// Schema (version kSchemaVersion = 2, image_index.h):
//   meta(key TEXT PRIMARY KEY, value TEXT)      schema_version, vocabulary_fingerprint (hex),
//                                               vocabulary_size, descriptor_kind, extractor_settings,
//                                               created_unix_ms, and `checkpoint` (the manifest of the
//                                               index's checkpoint files, checkpoint.h) once one exists
//   images(number INTEGER PRIMARY KEY AUTOINCREMENT,   internal image number, never reused
//          id TEXT UNIQUE, source_path TEXT, width INTEGER, height INTEGER, num_features INTEGER,
//          metadata_json TEXT, added_unix_ms INTEGER)
//   features(number INTEGER PRIMARY KEY,               the image's row in `images`
//            blob BLOB)                                PackedFeatures::Serialize() (feature_store.h)
// The BLOBs live in their own table so that reading every record (Open from a checkpoint) reads only
// the small `images` pages. Version 1 kept the BLOB as the last column of `images`; OpenForWriting
// migrates such a catalogue to version 2 in one transaction (a crash leaves version 1, migrated again
// at the next open).
//
// Opening never writes before the catalogue is validated: Open reads through a read-only connection
// (which cannot checkpoint a WAL into the file), and only OpenForWriting, called once the caller has
// checked everything it reads, opens the read-write connection. A stray or foreign catalogue.sqlite-wal
// beside the file can then make the open fail but never changes catalogue.sqlite (SQLite checkpoints
// the WAL into the database when a read-write connection closes).
//
// Thread safety: not thread-safe; ImageIndex serialises all calls under its writer mutex (Open's
// ForEach runs before the index is shared).
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "index/image_index.h"
#include "sift/base/error.h"
#include "vocab/vocabulary.h"

namespace oxbow::index {

// The files of an index folder beside its checkpoint files (checkpoint.h).
inline constexpr const char* kCatalogueFile = "catalogue.sqlite";
inline constexpr const char* kVocabularyFile = "vocabulary.oxvoc";

struct CatalogueMeta {
  int schema_version = kSchemaVersion;
  uint64_t vocabulary_fingerprint = 0;
  uint64_t vocabulary_size = 0;
  std::string descriptor_kind;      // sift::DescriptorKindName
  std::string extractor_settings;   // sift::SiftOptions::Describe()
  int64_t created_unix_ms = 0;
  std::string checkpoint;           // the checkpoint manifest (checkpoint.h); empty when none
};

struct CatalogueRow {
  int64_t number = 0;
  ImageRecord record;
  std::vector<uint8_t> features;  // the BLOB (empty when read without features)
};

class Catalogue {
 public:
  // Creates the database file with its schema and meta rows in one transaction. kAlreadyExists if the
  // file exists, kIoError when SQLite fails.
  [[nodiscard]] static Result<std::unique_ptr<Catalogue>> Create(const std::string& path, const CatalogueMeta& meta);
  // Opens an existing catalogue read-only and reads its meta; nothing is written to the folder's files
  // but SQLite's shared-memory index (catalogue.sqlite-shm). kNotFound if missing; kCorruptData for a
  // file that is not a SQLite database or lacks the tables/meta rows; kIncompatible for another schema
  // version (1, which OpenForWriting migrates, and 2 are read); kIoError when it cannot be read
  // (permissions, I/O errors, locked by another process).
  [[nodiscard]] static Result<std::unique_ptr<Catalogue>> Open(const std::string& path);
  // Switches an opened catalogue to a read-write connection (WAL, synchronous=FULL) for Insert, Replace
  // and Delete; call it only once the content read through Open is validated. Migrates a version 1
  // catalogue to version 2 (one transaction, logged). kIoError when the file, its folder or the file
  // system is read-only (the message says so), or SQLite fails.
  [[nodiscard]] Status OpenForWriting();
  ~Catalogue();
  Catalogue(const Catalogue&) = delete;
  Catalogue& operator=(const Catalogue&) = delete;

  const CatalogueMeta& meta() const { return meta_; }
  const std::string& path() const { return path_; }

  // Inserts one image row in its own committed transaction and returns its new number.
  // kAlreadyExists when the id is taken, kIoError otherwise.
  [[nodiscard]] Result<int64_t> Insert(const ImageRecord& record, std::span<const uint8_t> features);
  // A row for InsertMany; both must stay valid until InsertMany returns.
  struct Row {
    const ImageRecord* record = nullptr;
    std::span<const uint8_t> features;
  };
  // Inserts rows in one committed transaction and returns their numbers (ascending, in order): all
  // or none. `next` gives the rows in order: a row, std::nullopt after the last, or an error, which
  // rolls every row back and is returned. It may wait (for a row still being made, say): the rows
  // given so far are written meanwhile. kAlreadyExists when an id is taken (nothing inserted),
  // kIoError otherwise.
  [[nodiscard]] Result<std::vector<int64_t>> InsertMany(const std::function<Result<std::optional<Row>>()>& next);
  // Deletes row `old_number` and inserts the new row in one committed transaction: a crash leaves
  // either the old row or the new one. Returns the new number. kNotFound when `old_number` is absent
  // (nothing changed), kIoError otherwise (rolled back).
  [[nodiscard]] Result<int64_t> Replace(int64_t old_number, const ImageRecord& record,
                                        std::span<const uint8_t> features);
  // Deletes the row with this number in a committed transaction. kNotFound if absent.
  [[nodiscard]] Status Delete(int64_t number);
  // Calls fn for every row in number order, with its BLOB when `with_features` (else the BLOB's pages
  // are not read); stops at and returns the first error. kCorruptData for a record without BLOB.
  [[nodiscard]] Status ForEach(const std::function<Status(CatalogueRow&&)>& fn, bool with_features = true) const;
  // Calls fn(number, blob) for every image numbered above `after`, in number order (schema 2 only).
  [[nodiscard]] Status ForEachFeaturesAfter(int64_t after,
                                            const std::function<Status(int64_t, std::span<const uint8_t>)>& fn) const;
  // The BLOB of image `number` (schema 2). kNotFound when there is no such image.
  [[nodiscard]] Result<std::vector<uint8_t>> ReadFeatures(int64_t number) const;
  // Records the checkpoint manifest in one committed transaction: the commit point of a checkpoint.
  [[nodiscard]] Status SetCheckpoint(const std::string& manifest);
  // SQLite's integrity check of the `images` table and its id index (PRAGMA integrity_check(images):
  // not the `features` table, whose BLOBs FindDamagedFeatures checks): what an open reads of every
  // image. Measured 0.66 s for 1M rows (116 MB, page cache warm, 2-core VM). kCorruptData with
  // SQLite's first finding (an id changed in place gives "row N missing from index ..."), kIoError
  // when the file cannot be read.
  [[nodiscard]] Status CheckRecords() const;
  // An image whose feature BLOB fails its check (FindDamagedFeatures).
  struct DamagedImage {
    int64_t number = 0;
    std::string id;
    std::string why;  // the check's message
  };
  // Reads every image's BLOB and checks it as an open does (PackedFeatures::Deserialize: header,
  // size, CRC-32 of the body; missing BLOB): those that fail, in number order (schema 2 only).
  // O(total features). *images (when given) receives the number of image rows. An error is a
  // catalogue that cannot be read at all.
  [[nodiscard]] Result<std::vector<DamagedImage>> FindDamagedFeatures(uint64_t* images = nullptr) const;

  // The number of image rows ever inserted or deleted (a replacement is both): 2 x the highest number
  // ever given (AUTOINCREMENT numbers are never reused) - the live rows. Each Insert, Delete and each
  // row of InsertMany adds 1, Replace 2, in the same commit. Two copies of one index that applied the
  // same writes (in any order) have the same value: a cluster front compares replicas by it
  // (server/cluster/front.h). kIoError/kCorruptData when SQLite fails.
  [[nodiscard]] Result<uint64_t> WriteSequence() const;

  struct Db;  // the SQLite connection (catalogue.cc)

 private:
  Catalogue(std::unique_ptr<Db> db, std::string path, CatalogueMeta meta);
  // Runs `body` inside BEGIN IMMEDIATE ... COMMIT; rolled back when body or the commit fails.
  [[nodiscard]] Status InTransaction(const std::function<Status()>& body);
  std::unique_ptr<Db> db_;
  std::string path_;
  CatalogueMeta meta_;
};

// The feature BLOBs of the catalogue file at `path` (a copy: a backup's) checked as
// Catalogue::FindDamagedFeatures does; kCorruptData naming the first damaged image. Opens it read-write
// (it must not be an index's own catalogue while that index is open).
[[nodiscard]] Status CheckFeatureBlobs(const std::string& path);

// `oxbow index check`: the catalogue of the index at `dir` checked whole while no process has the
// index open (its FolderLock is held throughout: the folder of a running server is refused), its
// records (Catalogue::CheckRecords) and every image's feature BLOB (FindDamagedFeatures). With
// `drop_damaged`, the images whose BLOB is damaged are deleted from the catalogue, each in its own
// committed transaction (the next open removes them from its checkpoint as it does any image removed
// since); their ids can then be added again. kCorruptData when the records themselves are damaged
// (nothing is dropped then: restore a backup or rebuild).
struct IndexCheck {
  uint64_t images = 0;                           // image rows checked
  std::vector<Catalogue::DamagedImage> damaged;  // those whose BLOB fails its check, by number
  bool dropped = false;                          // drop_damaged: `damaged` were deleted
};
// The vocabulary copy is checked first (CheckVocabularyCopy): an index without a usable one does not open.
[[nodiscard]] Result<IndexCheck> CheckIndexFolder(const std::string& dir, bool drop_damaged);

// The index's vocabulary copy (`copy`, read from DIR/vocabulary.oxvoc) against its catalogue: Ok, or the
// error (unreadable, damaged, another vocabulary) with how to restore it: the copy is never rewritten,
// so the vocabulary file the index was built with, recognised by its fingerprint, can replace it.
[[nodiscard]] Status CheckVocabularyCopy(const std::string& dir, const CatalogueMeta& meta,
                                         const Result<vocab::Vocabulary>& copy);

// kNotFound ("no index at DIR (missing catalogue.sqlite)") unless `dir` holds an index's catalogue;
// touches nothing, so it runs before a FolderLock that would create its file.
[[nodiscard]] Status CheckHoldsCatalogue(const std::string& dir);

}  // namespace oxbow::index
