// Loading an index folder into its first snapshot, for ImageIndex::Open: from the checkpoint the
// catalogue's manifest names (its files read and checked, then the catalogue's changes since replayed),
// or, without a usable checkpoint, from every catalogue BLOB. What Open refuses and why a damaged file
// costs a rebuild, never a wrong answer: index/README.md ("Open", "Why a crash cannot lose or falsify
// anything").
//
// Thread safety: functions only, called by Open before the index is shared; they run their work on
// IndexOptions::num_threads threads.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "index/image_index.h"
#include "index/postings/inverted_file.h"
#include "index/storage/catalogue.h"
#include "index/storage/checkpoint.h"
#include "index/storage/geometry_parts.h"
#include "index/storage/snapshot.h"

namespace oxbow::index {

// The inverted file's options of an index's options.
TfIdfOptions ToTfIdf(const IndexOptions& options);

// An image whose catalogue BLOB an open found damaged: it is left out of the index and its row deleted
// (Open), so that the damage costs that image only.
struct DamagedBlob {
  int64_t number = 0;
  std::string why;
};

// Open without a checkpoint: every row and BLOB read and validated, the inverted file built in one
// pass; an image whose BLOB fails its check is left out and added to *damaged. An error is a catalogue
// failure.
[[nodiscard]] Result<std::shared_ptr<Snapshot>> BuildFromCatalogue(const Catalogue& catalogue, size_t vocab_size,
                                                                   const IndexOptions& options,
                                                                   std::vector<DamagedBlob>* damaged);

struct LoadedCheckpoint {
  std::shared_ptr<Snapshot> snapshot;  // null: the checkpoint is unusable (logged), rebuild from the catalogue
  CheckpointManifest manifest;   // generation 0 when unreadable
  uint64_t changes = 0;          // images added + removed since the checkpoint (replayed)
  std::vector<std::shared_ptr<const GeometryPart>> parts;  // its geometry files, not verified yet
  GeometryContents contents;     // the images of its geometry files
  bool compact = false;          // a checkpoint would drop some of its geometry files (KeptGeometry)
  bool recoded = false;          // the postings file was of an older format (re-coded in memory)
  std::vector<DamagedBlob> damaged;  // images added since whose BLOB is damaged (left out)
  // Its segment files, each with the segment loaded from it (what the checkpointer names again).
  std::vector<std::pair<std::weak_ptr<const void>, CheckpointFile>> segment_files;
};

// Open from the checkpoint the catalogue names, replaying the changes since. A damaged, missing or
// inconsistent checkpoint file gives a null snapshot (and a log line); an error is a catalogue failure.
// The postings files (the head and its segment files) are verified against their checksums; a geometry
// file's size and image table are checked, its data on use (GeometryPart).
[[nodiscard]] Result<LoadedCheckpoint> LoadCheckpoint(const std::string& dir, const Catalogue& catalogue,
                                                      size_t vocab_size, const IndexOptions& options);

}  // namespace oxbow::index
