#include "sift/base/binary_io.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>

#include <cerrno>
#include <filesystem>
#include <random>

namespace oxbow::io {
namespace {

constexpr uint32_t kByteOrderTag = 0x01020304u;

std::string ErrnoText() { return std::strerror(errno); }

// Writes all bytes, retrying on short writes and EINTR.
bool WriteAll(int fd, const uint8_t* data, size_t size) {
  while (size > 0) {
    const ssize_t n = ::write(fd, data, size);
    if (n < 0) {
      if (errno == EINTR) continue;
      return false;
    }
    data += n;
    size -= static_cast<size_t>(n);
  }
  return true;
}

Status WritePiecesAtomically(const std::string& path, std::span<const std::span<const uint8_t>> pieces) {
  namespace fs = std::filesystem;
  const fs::path target(path);
  const fs::path dir = target.has_parent_path() ? target.parent_path() : fs::path(".");
  std::random_device rd;
  const std::string tmp = (dir / (target.filename().string() + ".tmp." + std::to_string(::getpid()) + "." +
                                  std::to_string(rd())))
                              .string();
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0644);
  if (fd < 0) return Fail(ErrorCode::kIoError, "cannot create '" + tmp + "': " + ErrnoText());
  bool ok = true;
  for (const auto& piece : pieces) ok = ok && WriteAll(fd, piece.data(), piece.size());
  std::string failure;
  if (!ok) failure = "cannot write '" + tmp + "': " + ErrnoText();
  if (ok && ::fsync(fd) != 0) {
    ok = false;
    failure = "cannot fsync '" + tmp + "': " + ErrnoText();
  }
  if (::close(fd) != 0 && ok) {
    ok = false;
    failure = "cannot close '" + tmp + "': " + ErrnoText();
  }
  if (ok && ::rename(tmp.c_str(), path.c_str()) != 0) {
    ok = false;
    failure = "cannot rename '" + tmp + "' to '" + path + "': " + ErrnoText();
  }
  if (!ok) {
    ::unlink(tmp.c_str());
    return Fail(ErrorCode::kIoError, failure);
  }
  // Make the rename itself durable.
  const int dir_fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dir_fd >= 0) {
    ::fsync(dir_fd);
    ::close(dir_fd);
  }
  return Ok();
}

}  // namespace

// zlib's CRC-32 is the same function (IEEE polynomial, same pre- and post-inversion, so stored
// checksums keep their values) and several times faster than a byte-at-a-time table; every index open
// and feature BLOB write checksums gigabytes at scale. zlib returns 0 for a null buffer: an empty span
// leaves the running value unchanged.
uint32_t Crc32(std::span<const uint8_t> bytes, uint32_t crc) {
  if (bytes.empty()) return crc;
  return static_cast<uint32_t>(crc32_z(crc, bytes.data(), bytes.size()));
}

Status WriteFileAtomically(const std::string& path, std::span<const uint8_t> bytes) {
  const std::span<const uint8_t> pieces[] = {bytes};
  return WritePiecesAtomically(path, pieces);
}

Status WriteContainerFile(const std::string& path, std::string_view magic, uint32_t version, uint32_t flags,
                          std::span<const uint8_t> payload) {
  OXBOW_CHECK(magic.size() == 8, "container magic must be 8 characters");
  ByteWriter header;
  header.PutArray(std::span<const char>(magic.data(), 8));
  header.Put<uint32_t>(version);
  header.Put<uint32_t>(kByteOrderTag);
  header.Put<uint64_t>(payload.size());
  header.Put<uint32_t>(Crc32(payload));
  header.Put<uint32_t>(flags);
  header.Put<uint32_t>(0);
  header.Put<uint32_t>(Crc32(header.bytes()));
  OXBOW_CHECK(header.bytes().size() == kHeaderBytes);
  const std::span<const uint8_t> pieces[] = {header.bytes(), payload};
  return WritePiecesAtomically(path, pieces);
}

Result<std::vector<uint8_t>> ReadWholeFile(const std::string& path, uint64_t max_bytes) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    const ErrorCode code = errno == ENOENT ? ErrorCode::kNotFound : ErrorCode::kIoError;
    return Fail(code, "cannot open '" + path + "': " + ErrnoText());
  }
  struct stat st {};
  if (::fstat(fd, &st) != 0) {
    const std::string why = ErrnoText();
    ::close(fd);
    return Fail(ErrorCode::kIoError, "cannot read '" + path + "': " + why);
  }
  if (S_ISDIR(st.st_mode)) {  // a folder where a file belongs: the caller's mistake, not the disk's
    ::close(fd);
    return Fail(ErrorCode::kInvalidArgument, "'" + path + "' is a folder, not a file");
  }
  if (!S_ISREG(st.st_mode)) {
    ::close(fd);
    return Fail(ErrorCode::kInvalidArgument, "'" + path + "' is not a regular file (a device, a pipe or a socket)");
  }
  if (static_cast<uint64_t>(st.st_size) > max_bytes) {
    ::close(fd);
    return Fail(ErrorCode::kResourceExhausted,
                "'" + path + "' is " + std::to_string(st.st_size) + " bytes, over the limit of " +
                    std::to_string(max_bytes));
  }
  std::vector<uint8_t> bytes(static_cast<size_t>(st.st_size));
  size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n = ::read(fd, bytes.data() + done, bytes.size() - done);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    done += static_cast<size_t>(n);
  }
  ::close(fd);
  if (done != bytes.size()) return Fail(ErrorCode::kIoError, "short read on '" + path + "'");
  return bytes;
}

Result<Container> ReadContainerFile(const std::string& path, std::string_view magic, uint32_t min_version,
                                    uint32_t max_version) {
  OXBOW_CHECK(magic.size() == 8, "container magic must be 8 characters");
  auto bytes = ReadWholeFile(path);
  if (!bytes) return std::unexpected(bytes.error());
  const std::string name = "'" + path + "'";
  if (bytes->size() < kHeaderBytes) {
    return Fail(ErrorCode::kCorruptData, name + " is too short (" + std::to_string(bytes->size()) +
                                             " bytes) to be an oxbow " + std::string(magic) + " file");
  }
  if (std::memcmp(bytes->data(), magic.data(), 8) != 0) {
    return Fail(ErrorCode::kCorruptData,
                name + " is not an oxbow " + std::string(magic) + " file (wrong magic number)");
  }
  ByteReader reader(std::span<const uint8_t>(*bytes).subspan(8), path);
  const uint32_t version = *reader.Get<uint32_t>();
  const uint32_t byte_order = *reader.Get<uint32_t>();
  const uint64_t payload_bytes = *reader.Get<uint64_t>();
  const uint32_t payload_crc = *reader.Get<uint32_t>();
  const uint32_t flags = *reader.Get<uint32_t>();
  (void)*reader.Get<uint32_t>();
  const uint32_t header_crc = *reader.Get<uint32_t>();
  if (Crc32(std::span<const uint8_t>(bytes->data(), kHeaderBytes - 4)) != header_crc) {
    return Fail(ErrorCode::kCorruptData, name + " has a damaged header (checksum mismatch)");
  }
  if (byte_order != kByteOrderTag) {
    return Fail(ErrorCode::kIncompatible, name + " was written on a machine with another byte order");
  }
  if (version < min_version || version > max_version) {
    return Fail(ErrorCode::kIncompatible, name + " has format version " + std::to_string(version) +
                                              "; this build reads versions " + std::to_string(min_version) +
                                              " to " + std::to_string(max_version));
  }
  if (bytes->size() - kHeaderBytes != payload_bytes) {
    return Fail(ErrorCode::kCorruptData, name + " is truncated or has trailing bytes: header says " +
                                             std::to_string(payload_bytes) + " payload bytes, file has " +
                                             std::to_string(bytes->size() - kHeaderBytes));
  }
  const std::span<const uint8_t> payload(bytes->data() + kHeaderBytes, payload_bytes);
  if (Crc32(payload) != payload_crc) {
    return Fail(ErrorCode::kCorruptData, name + " is damaged (payload checksum mismatch)");
  }
  Container container;
  container.version = version;
  container.flags = flags;
  bytes->erase(bytes->begin(), bytes->begin() + kHeaderBytes);
  container.payload = std::move(*bytes);
  return container;
}

Result<std::string> ByteReader::GetString(uint32_t max_length) {
  auto length = Get<uint32_t>();
  if (!length) return std::unexpected(length.error());
  if (*length > max_length || *length > remaining()) return Truncated();
  std::string s(reinterpret_cast<const char*>(bytes_.data() + pos_), *length);
  pos_ += *length;
  return s;
}

std::unexpected<Error> ByteReader::Truncated() const {
  return Fail(ErrorCode::kCorruptData, what_ + ": record truncated at byte " + std::to_string(pos_));
}

}  // namespace oxbow::io
