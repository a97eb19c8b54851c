// The search source over one index's snapshot (source.h): what ImageIndex::Query and QuerySimilar run
// the search pipeline over, and what a cluster partition answers its front's calls with. Refs are image
// numbers (part 0). It reads the snapshot's inverted file (scoring, idf, norms, the ranking among the
// results), its entries (records and features, through Entry: a geometry file's data checked on use)
// and its id map, and keeps what one stage read for the next: the Hamming shortlist's features (copied
// once with pread), the allow-bitmap of a filter, transitive verification's ranking.
//
// Thread safety: as every Source, one search on one thread at a time; it runs its batches on
// `num_threads` threads of the shared pool. The snapshot is immutable and kept alive by the source.
#pragma once

#include <memory>

#include "index/search/source.h"
#include "index/storage/snapshot.h"

namespace oxbow::index::search {

std::unique_ptr<Source> OpenSnapshotSearch(std::shared_ptr<const Snapshot> snapshot, int num_threads);

}  // namespace oxbow::index::search
