// The checkpointer of an open index: writes checkpoints (checkpoint.h) in the background and at close,
// moves the images a checkpoint wrote from memory to its geometry files, and checks the geometry files
// an open loaded. What a checkpoint holds and why a crash at any point loses nothing: checkpoint.h and
// index/README.md ("Checkpoints").
//
// A checkpoint, like a LevelDB compaction, is prepared under the index's writer mutex, written without
// it, and committed under it again:
//   1. NextJob (writer mutex): waits until one is due (CheckpointDue: enough changes, or Open asked for
//      one, or a geometry file was found damaged) and copies what the checkpoint starts from: the
//      current snapshot, the committed manifest and its geometry contents, the changes counted;
//   2. WriteFiles (no lock; writers go on): the geometry files of the images above the previous high
//      water and of the files KeptGeometry drops, the segment files new since the previous checkpoint,
//      the postings head;
//   3. Commit (writer mutex): the manifest recorded in the catalogue (the commit point), files no
//      manifest names deleted, the geometry parts the manifest no longer names forgotten;
//   4. ReadBack (no lock): the new geometry files mapped and their image tables read;
//   5. PublishViews (writer mutex): the images still as they were at step 1 view the new files (a new
//      snapshot), so that the copies in memory that Add made are freed.
// Close stops the thread and writes the last checkpoint with the writer mutex held throughout.
//
// Threads: the checkpointer thread (Run to Close), and beside it, started by it, the verifier thread,
// which checks every geometry file an open loaded in Linux's SCHED_IDLE class, pausing while a search
// runs (SearchActivity), and wakes the checkpointer when one is damaged.
//
// Locks, in the order they are taken:
//   writer_mutex_          the index's writer mutex (ImageIndex::Impl::writer_mutex), given to the
//                          constructor. Besides the catalogue and the building of the next snapshot, it
//                          guards the state below marked "writer mutex"; due_ waits on it. Taken by
//                          NextJob, Commit, PublishViews, the verifier (to copy the parts, to wake the
//                          loop) and Close; held by the caller of Changed.
//   segment_files_mutex_   guards segment_files_ only; a leaf (taken while writing a checkpoint, with or
//                          without the writer mutex).
//   CurrentSnapshot's      a leaf (snapshot.h).
// GeometryPart's own mutexes are leaves too. No function receives a held lock.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "index/image_index.h"
#include "index/storage/catalogue.h"
#include "index/storage/checkpoint.h"
#include "index/storage/geometry_parts.h"
#include "index/storage/snapshot.h"

namespace oxbow::index {

// The searches running on an index, and when the last one ended: the background check of the geometry
// files waits while one runs and reads slowly right after one. Lock-free; any thread.
class SearchActivity {
 public:
  using Clock = std::chrono::steady_clock;
  // Counts a search as running for its lifetime.
  class Scope {
   public:
    explicit Scope(SearchActivity& activity) : activity_(activity) {
      activity_.running_.fetch_add(1, std::memory_order_relaxed);
    }
    ~Scope() {
      activity_.last_end_.store(Clock::now().time_since_epoch().count(), std::memory_order_relaxed);
      activity_.running_.fetch_sub(1, std::memory_order_relaxed);
    }
    Scope(const Scope&) = delete;
    Scope& operator=(const Scope&) = delete;

   private:
    SearchActivity& activity_;
  };
  int running() const { return running_.load(std::memory_order_relaxed); }
  Clock::time_point last_end() const {
    return Clock::time_point(Clock::duration(last_end_.load(std::memory_order_relaxed)));
  }

 private:
  std::atomic<int> running_{0};
  std::atomic<int64_t> last_end_{0};  // Clock ticks
};

class Checkpointer {
 public:
  // Where the checkpointer starts: what an open found of the committed checkpoint (LoadedCheckpoint),
  // or nothing (a new index, or an unusable checkpoint whose generation must not be reused).
  struct Start {
    CheckpointManifest manifest;                              // the committed one
    GeometryContents contents;                                // the images of its geometry files
    std::vector<std::shared_ptr<const GeometryPart>> parts;   // its geometry files, to check
    std::vector<std::pair<std::weak_ptr<const void>, CheckpointFile>> segment_files;  // its segments
    uint64_t changes = 0;   // images added + removed since it
    bool forced = false;    // checkpoint at once (Open rebuilt, re-coded or would compact)
  };
  // Checkpoints the index in `dir` whose writer mutex is `writer_mutex`, whose write connection is
  // `catalogue` (used under that mutex) and whose snapshot is `snapshot`; all outlive it.
  Checkpointer(std::string dir, const IndexOptions& options, std::mutex& writer_mutex, Catalogue& catalogue,
               CurrentSnapshot& snapshot, const SearchActivity& searches, Start start);
  ~Checkpointer();  // Close() if Run() was called and Close() was not
  Checkpointer(const Checkpointer&) = delete;
  Checkpointer& operator=(const Checkpointer&) = delete;

  // Starts the checkpointer thread.
  void Run();
  // After a committed write of `images` added + removed, with the writer mutex held: counts them and
  // wakes the checkpointer when a checkpoint is due.
  void Changed(uint64_t images);
  // Stops the threads, then, with the writer mutex held, checkpoints what is pending; a failure is
  // logged (the next open replays the changes from the catalogue). Without the writer mutex held.
  void Close();

 private:
  struct Job {
    std::shared_ptr<const Snapshot> snapshot;
    CheckpointManifest previous;
    GeometryContents contents;
    uint64_t changes = 0;
  };
  // A new geometry file of a committed checkpoint, read back (ReadBack), with the entries of its
  // images that should view it.
  struct Viewing {
    std::shared_ptr<const GeometryPart> part;
    std::vector<std::pair<uint32_t, std::shared_ptr<const Entry>>> entries;  // by number
  };
  // What ReadBack reads: the new geometry files of the committed manifest, and every file it names.
  struct Written {
    std::vector<CheckpointFile> new_geometry;
    std::vector<CheckpointFile> named;
  };

  void Loop();                                   // the checkpointer thread
  std::optional<Job> NextJob();                  // takes the writer mutex; nullopt when closing
  // Steps 2 and 3 of the file comment; Commit takes the writer mutex and gives the files to read
  // back (nullopt when the checkpoint failed: logged, retried after as many changes).
  Result<CheckpointManifest> WriteFiles(const Snapshot& snap, const CheckpointManifest& previous,
                                        const GeometryContents& contents, GeometryContents* next_contents) const;
  std::optional<Written> Commit(const Job& job, Result<CheckpointManifest> next, GeometryContents next_contents);
  // Steps 4 and 5. ReadBack reads only its arguments and dir_; PublishViews takes the writer mutex.
  std::vector<Viewing> ReadBack(const Snapshot& written, const Written& files) const;
  void PublishViews(const Snapshot& written, std::vector<Viewing> viewing);

  // With the writer mutex held: records `next` as the committed checkpoint, deletes what no manifest
  // names. The checkpoint covers `changes` of changes_.
  Status CommitManifest(CheckpointManifest next, GeometryContents next_contents, uint64_t changes);
  // The file of segment i of `snap` for checkpoint `generation`: the one `previous` names for it, else
  // a new one written now (`written` counts them). Uses segment_files_.
  Result<CheckpointFile> FileOfSegment(const Snapshot& snap, size_t i, const CheckpointManifest& previous,
                                       const std::string& generation, int* written) const;
  bool CheckpointDue() const;  // writer mutex held
  // The geometry files `manifest` names that were found damaged; writer mutex held.
  std::set<std::string> DamagedGeometry(const CheckpointManifest& manifest) const;
  // The verifier thread: checks every part loaded by the open not checked yet (gives up when closing),
  // then wakes the checkpointer if one was damaged.
  void VerifyParts();

  const std::string dir_;
  const bool sqrt_tf_;
  const uint64_t checkpoint_changes_;
  std::mutex& writer_mutex_;
  Catalogue& catalogue_;          // the index's write connection; writer mutex
  CurrentSnapshot& snapshot_;
  const SearchActivity& searches_;

  // --- Guarded by the writer mutex. loaded_parts_ and written_parts_ are changed only on the
  // checkpointer thread (under the mutex), which may therefore read them without it (WriteFiles).
  CheckpointManifest manifest_;          // the last committed checkpoint
  GeometryContents contents_;            // the images of its geometry files
  uint64_t changes_ = 0;                 // images added + removed since it
  bool forced_ = false;                  // checkpoint now (Start::forced)
  bool closing_ = false;                 // Close was called: the loop ends
  uint64_t pending_after_failure_ = 0;   // changes of failed background checkpoints (for Close)
  // The geometry files of the checkpoint Open loaded that the committed manifest still names (those
  // a checkpoint drops are forgotten at its commit); the verifier copies the list once at its start.
  std::vector<std::shared_ptr<const GeometryPart>> loaded_parts_;
  // The geometry files later checkpoints wrote and their images now view (PublishViews).
  std::vector<std::shared_ptr<const GeometryPart>> written_parts_;
  std::condition_variable due_;          // waited on with the writer mutex: wakes the checkpointer

  // The segment files of checkpoints, each with the segment it holds (weak: one merged away is
  // forgotten), so that a checkpoint writes only the segments new since the previous one. A file is
  // named again only if the previous manifest names it (one written by a checkpoint that failed is not).
  struct SegmentFile {
    std::weak_ptr<const void> segment;
    CheckpointFile file;
  };
  mutable std::mutex segment_files_mutex_;
  mutable std::vector<SegmentFile> segment_files_;  // guarded by segment_files_mutex_

  std::atomic<bool> stop_verifying_{false};  // set by Close: the verifier gives up before its next read
  std::thread thread_;                       // runs Loop, from Run to Close
  bool closed_ = false;                      // Close ran (owner's thread only)
};

}  // namespace oxbow::index
