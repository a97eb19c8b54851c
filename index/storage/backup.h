// Online backup of an index folder (catalogue.h, checkpoint.h) while another thread or process keeps
// reading and writing it.
//
// The backup is the committed state at one instant: the catalogue is copied with SQLite's online backup
// API inside one read transaction (a WAL reader: writers are never blocked, and the copy holds exactly the
// transactions committed before the transaction began, the checkpoint manifest included). The checkpoint
// files that manifest names are opened before anything is copied: a checkpoint committed meanwhile may
// delete them (checkpoint.h, step 3), and an open descriptor keeps a deleted file's bytes readable. A file
// already deleted when it is opened means a newer manifest was committed: the attempt is dropped and
// repeated with a new snapshot. The copied files are then verified against the manifest's sizes and
// checksums and the copied catalogue with SQLite's quick_check, so a damaged source is reported, not
// copied. Everything is written to `<out>.tmp`, fsync'ed, and renamed to `out` (the parent folder
// fsync'ed): `out` is either absent or a complete backup; a failed backup removes `<out>.tmp`.
//
// Thread safety: functions only; any number of backups may run beside the index's own writers.
#pragma once

#include <cstdint>
#include <functional>
#include <mutex>
#include <string>
#include <vector>

#include "sift/base/error.h"

namespace oxbow::index {

struct BackupOptions {
  // Further SQLite files of the folder (names relative to it) copied like the catalogue, each in a read
  // transaction begun right after the catalogue's; skipped when absent.
  std::vector<std::string> extra_databases;
  // Further plain files of the folder copied as they are, when present: files only ever replaced whole
  // (written beside and renamed), such as a cluster partition's statistics. Copied after the snapshots:
  // one replaced meanwhile is copied as it is then.
  std::vector<std::string> extra_files;
  // When set, held while the read transactions begin: a writer of this process that commits to the
  // catalogue and the extra databases under this mutex then cannot commit between them.
  std::mutex* snapshot_mutex = nullptr;
  // Test seam: called after each attempt's snapshot began, before its checkpoint files are opened.
  std::function<void(int attempt)> after_snapshot_for_testing;
};

struct BackupResult {
  int64_t images = 0;           // images in the backup
  uint64_t generation = 0;      // its checkpoint generation (0: none)
  uint64_t bytes = 0;           // bytes written
  int attempts = 0;             // snapshots taken (more than 1 when a checkpoint replaced the files)
};

// Backs up the index folder `dir` into the new folder `out` (absent or empty; its parent must exist),
// once `out` passed CheckBackupFolder. Errors: those of CheckBackupFolder, kAlreadyExists also when
// `<out>.tmp` exists (the leftover of an interrupted backup, to remove), kNotFound (no index in `dir`),
// kCorruptData (a source file fails its checks), kResourceExhausted (checkpoints replaced the files at
// every attempt), kIoError (the disk failed or filled).
[[nodiscard]] Result<BackupResult> BackupIndex(const std::string& dir, const std::string& out,
                                               const BackupOptions& options = {});

// Longest backup path accepted, bytes: room below PATH_MAX for "<out>.tmp/" and the files written in it.
inline constexpr size_t kMaxBackupPathBytes = 3968;

// Whether `out` may become a backup of the index folder `dir`; what every transport's backup checks
// (BackupIndex calls it) before anything is written. `out` names the folder as a client sent it, on this
// machine; relative to the working directory when not absolute. Refused:
//  - kInvalidArgument, the client's mistakes: an empty path, a control character (NUL, newline, any
//    byte below 0x20, 0x7f), a ".." component (name the folder without it), a name over NAME_MAX - 4
//    bytes (the backup is first written beside it as "<name>.tmp") or a path over kMaxBackupPathBytes,
//    a symbolic link as any component, dangling or not (a backup is never written through one: name
//    the real folder), a component that is not a folder, a folder the server may not inspect, and the
//    index folder `dir` itself or any folder inside it (an empty `dir`, for a caller that serves no
//    folder of its own such as a cluster front, skips that check);
//  - kNotFound: the parent folder does not exist (it is not created);
//  - kAlreadyExists: `out` exists and is not an empty folder.
// The path is checked once: a folder changed meanwhile by someone who may write the folders above it is
// not checked again while the backup runs.
[[nodiscard]] Status CheckBackupFolder(const std::string& dir, const std::string& out);

}  // namespace oxbow::index
