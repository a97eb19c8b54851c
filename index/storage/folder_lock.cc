#include "index/storage/folder_lock.h"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <utility>

#include "sift/base/log.h"

namespace oxbow::index {

namespace {

// The pid the holder wrote into its lock file ("" when there is none).
std::string HolderOf(int fd) {
  char text[32] = {};
  const ssize_t n = ::pread(fd, text, sizeof(text) - 1, 0);
  if (n <= 0) return "";
  std::string pid(text, static_cast<size_t>(n));
  while (!pid.empty() && (pid.back() == '\n' || pid.back() == ' ')) pid.pop_back();
  return pid.find_first_not_of("0123456789") == std::string::npos ? pid : "";
}

}  // namespace

Result<FolderLock> FolderLock::Acquire(const std::string& dir, bool shared) {
  const std::string path = (std::filesystem::path(dir) / kLockFile).string();
  const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (fd < 0) {
    const int error = errno;
    const bool refused = error == EACCES || error == EPERM || error == EROFS;
    return Fail(ErrorCode::kIoError, "cannot open the lock file " + path + " (" + std::strerror(error) + ")" +
                                         (refused ? ": oxbow needs to write in the index folder; check its "
                                                    "permissions and that its file system is not mounted read-only"
                                                  : ""));
  }
  int rc = 0;
  do {
    rc = ::flock(fd, (shared ? LOCK_SH : LOCK_EX) | LOCK_NB);
  } while (rc != 0 && errno == EINTR);
  if (rc != 0) {
    const int error = errno;
    if (error == ENOLCK || error == EOPNOTSUPP || error == ENOSYS) {
      // A file system without locks (some network and FUSE ones) must not make every index on it
      // unusable: the folder opens unlocked, and the log says what that leaves to the user.
      OXBOW_LOG(kWarning) << "cannot lock " << path << " (" << std::strerror(error)
                          << "): its file system offers no locks; make sure that one process at a time opens "
                          << dir;
      return FolderLock(fd);
    }
    const std::string holder = error == EWOULDBLOCK ? HolderOf(fd) : "";
    ::close(fd);
    if (error != EWOULDBLOCK) {
      return Fail(ErrorCode::kIoError, "cannot lock " + path + ": " + std::strerror(error));
    }
    return Fail(ErrorCode::kIoError,
                "the index " + dir + " is open in another process" + (holder.empty() ? "" : " (pid " + holder + ")") +
                    " or elsewhere in this one: one process at a time may open an index folder for writing, or "
                    "several only to read it (it holds " + path +
                    "). Stop that process first, or send the work to the server that holds it over HTTP");
  }
  if (shared) {  // the pid names a writer only: no stale one in a refusal's message while readers hold it
    (void)::ftruncate(fd, 0);
    return FolderLock(fd);
  }
  // Best effort: the pid is for the message of a refused open only.
  const std::string pid = std::to_string(::getpid()) + "\n";
  if (::ftruncate(fd, 0) == 0) (void)::pwrite(fd, pid.data(), pid.size(), 0);
  return FolderLock(fd);
}

FolderLock::FolderLock(FolderLock&& other) noexcept : fd_(std::exchange(other.fd_, -1)) {}

FolderLock& FolderLock::operator=(FolderLock&& other) noexcept {
  if (this != &other) {
    if (fd_ >= 0) ::close(fd_);
    fd_ = std::exchange(other.fd_, -1);
  }
  return *this;
}

FolderLock::~FolderLock() {
  if (fd_ >= 0) ::close(fd_);
}

}  // namespace oxbow::index
