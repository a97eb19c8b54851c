// Versioned binary container files, shared by every on-disk format oxbow writes (feature files,
// vocabularies, index snapshots).
//
// Layout (little-endian, 40-byte header, then the payload):
//   offset  0  char[8]  magic           identifies the format, e.g. "OXBWFEAT"
//   offset  8  u32      version         format version; readers refuse versions they do not know
//   offset 12  u32      byte_order      0x01020304 as written by the producer; refused if it reads differently
//   offset 16  u64      payload_bytes   exact payload length; a truncated file is refused
//   offset 24  u32      payload_crc32   CRC-32 (IEEE) of the payload; a damaged file is refused
//   offset 28  u32      flags           format-specific
//   offset 32  u32      reserved        0
//   offset 36  u32      header_crc32    CRC-32 of bytes 0..35
// Writes go to a temporary file in the same folder, are fsync'ed, renamed over the target and the
// folder is fsync'ed, so a reader sees either the old file or the new one, never half of one.
#pragma once

#include <cstdint>
#include <cstring>
#include <span>
#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

#include "sift/base/error.h"

namespace oxbow::io {

inline constexpr size_t kHeaderBytes = 40;

// CRC-32 (IEEE 802.3 polynomial, as zlib's crc32); `crc` chains calls over consecutive pieces.
uint32_t Crc32(std::span<const uint8_t> bytes, uint32_t crc = 0);

struct Container {
  uint32_t version = 0;
  uint32_t flags = 0;
  std::vector<uint8_t> payload;
};

// Writes magic/version/flags + payload atomically (temp file, fsync, rename, fsync folder).
// `magic` must be exactly 8 characters.
[[nodiscard]] Status WriteContainerFile(const std::string& path, std::string_view magic, uint32_t version,
                                        uint32_t flags, std::span<const uint8_t> payload);

// Reads and validates a container: kNotFound if missing, kCorruptData for a foreign magic, a damaged
// header, a wrong length or checksum (the message names the file and what is wrong), kIncompatible for
// a version outside [min_version, max_version] or another byte order.
[[nodiscard]] Result<Container> ReadContainerFile(const std::string& path, std::string_view magic,
                                                  uint32_t min_version, uint32_t max_version);

// Writes `bytes` to `path` atomically (same protocol as WriteContainerFile, no header).
[[nodiscard]] Status WriteFileAtomically(const std::string& path, std::span<const uint8_t> bytes);

// Reads a whole file; kNotFound / kIoError on failure. Refuses files larger than max_bytes.
[[nodiscard]] Result<std::vector<uint8_t>> ReadWholeFile(const std::string& path,
                                                        uint64_t max_bytes = uint64_t{1} << 36);

// Appends trivially copyable values to a byte buffer (host byte order, which the header records).
class ByteWriter {
 public:
  template <typename T>
  void Put(const T& value) {
    static_assert(std::is_trivially_copyable_v<T>);
    const auto* p = reinterpret_cast<const uint8_t*>(&value);
    bytes_.insert(bytes_.end(), p, p + sizeof(T));
  }
  template <typename T>
  void PutArray(std::span<const T> values) {
    static_assert(std::is_trivially_copyable_v<T>);
    const auto* p = reinterpret_cast<const uint8_t*>(values.data());
    bytes_.insert(bytes_.end(), p, p + values.size_bytes());
  }
  void PutString(std::string_view s) {  // u32 length + bytes
    Put<uint32_t>(static_cast<uint32_t>(s.size()));
    bytes_.insert(bytes_.end(), s.begin(), s.end());
  }
  std::vector<uint8_t>& bytes() { return bytes_; }
  std::vector<uint8_t> Release() { return std::move(bytes_); }

 private:
  std::vector<uint8_t> bytes_;
};

// Reads values back with bounds checks; every failure is kCorruptData naming `what`.
class ByteReader {
 public:
  ByteReader(std::span<const uint8_t> bytes, std::string what) : bytes_(bytes), what_(std::move(what)) {}

  template <typename T>
  [[nodiscard]] Result<T> Get() {
    static_assert(std::is_trivially_copyable_v<T>);
    if (remaining() < sizeof(T)) return Truncated();
    T value;
    std::memcpy(&value, bytes_.data() + pos_, sizeof(T));
    pos_ += sizeof(T);
    return value;
  }
  template <typename T>
  [[nodiscard]] Status GetArray(std::span<T> out) {
    static_assert(std::is_trivially_copyable_v<T>);
    if (remaining() < out.size_bytes()) return Truncated();
    if (out.empty()) return Ok();  // an empty span may have no data pointer (memcpy from/to null is UB)
    std::memcpy(out.data(), bytes_.data() + pos_, out.size_bytes());
    pos_ += out.size_bytes();
    return Ok();
  }
  [[nodiscard]] Result<std::string> GetString(uint32_t max_length = 1u << 20);

  size_t remaining() const { return bytes_.size() - pos_; }
  size_t position() const { return pos_; }

 private:
  std::unexpected<Error> Truncated() const;
  std::span<const uint8_t> bytes_;
  size_t pos_ = 0;
  std::string what_;
};

}  // namespace oxbow::io
