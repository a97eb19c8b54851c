// FolderLock: one process at a time in an index folder.
//
// An open ImageIndex writes checkpoint files in the background and, when it opens, deletes the files
// its manifest does not name (checkpoint.h). Two opens of one folder would each delete the other's
// files not committed yet, so ImageIndex::Create and ::Open take this lock first and hold it until
// closed: a second open, by another process or the same one, is refused with a clear error.
//
// The lock is flock(2) on DIR/LOCK (exclusive, not waiting). A read-only open
// (ImageIndex::OpenReadOnly), which writes nothing, takes it shared: several read-only opens (the ranks
// of `index duplicates --mpi`) share the folder, and no writer opens it meanwhile. The kernel drops it when its holder's
// file is closed, including when the process dies (kill -9, a crash): a restart never meets a stale
// lock. The file keeps the holder's pid, for the refusal's message only; the file itself stays. On a
// file system without locks (flock fails with ENOLCK or EOPNOTSUPP) the folder opens unlocked, with a
// warning in the log.
#pragma once

#include <string>

#include "sift/base/error.h"

namespace oxbow::index {

inline constexpr const char* kLockFile = "LOCK";

class FolderLock {
 public:
  // Takes the lock of the existing folder `dir`, exclusive or `shared`. kIoError when a holder refuses it
  // (the message names the exclusive holder's pid when known) or the file cannot be opened.
  [[nodiscard]] static Result<FolderLock> Acquire(const std::string& dir, bool shared = false);

  FolderLock() = default;
  FolderLock(FolderLock&& other) noexcept;
  FolderLock& operator=(FolderLock&& other) noexcept;
  FolderLock(const FolderLock&) = delete;
  FolderLock& operator=(const FolderLock&) = delete;
  ~FolderLock();

 private:
  explicit FolderLock(int fd) : fd_(fd) {}
  int fd_ = -1;
};

}  // namespace oxbow::index
