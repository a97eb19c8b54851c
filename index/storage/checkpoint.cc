#include "index/storage/checkpoint.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <unistd.h>
#include <xxhash.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <set>
#include <sstream>

#include "sift/base/system.h"

namespace oxbow::index {
namespace {

constexpr char kGeometryMagic[4] = {'O', 'X', 'G', 'E'};
constexpr uint32_t kGeometryVersion = 1;
constexpr uint32_t kSignedGeometryVersion = 2;
constexpr uint32_t kCheckedGeometryVersion = 3;
constexpr uint32_t kByteOrderMark = 0x01020304;
constexpr const char* kManifestHeader = "oxbow-checkpoint 1";

struct GeometryEntry {
  uint32_t number;
  int32_t width;
  int32_t height;
  uint32_t count;
  uint64_t offset;
};
static_assert(sizeof(GeometryEntry) == 24);
// Version 2's entry: an image's data is its features, then its signatures when `has_signatures` is 1.
struct SignedGeometryEntry {
  GeometryEntry entry;
  uint32_t has_signatures;
  uint32_t reserved;  // 0
};
static_assert(sizeof(SignedGeometryEntry) == 32);
// Version 3's entry adds the XXH3-64 of the image's data (ImageChecksum).
struct CheckedGeometryEntry {
  SignedGeometryEntry signed_entry;
  uint64_t checksum;
};
static_assert(sizeof(CheckedGeometryEntry) == 40);

bool IsCheckpointFileName(const std::string& name) {
  const bool ours = name.starts_with("postings-") || name.starts_with("segment-") || name.starts_with("geometry-");
  return ours && (name.ends_with(".oxck") || name.ends_with(".oxck.tmp"));
}

// XXH3-64 of a byte stream.
class Checksum {
 public:
  Checksum() : state_(XXH3_createState()) {
    OXBOW_CHECK(state_ != nullptr, "out of memory");
    XXH3_64bits_reset(state_);
  }
  ~Checksum() { XXH3_freeState(state_); }
  Checksum(const Checksum&) = delete;
  Checksum& operator=(const Checksum&) = delete;
  void Update(std::span<const uint8_t> bytes) { XXH3_64bits_update(state_, bytes.data(), bytes.size()); }
  uint64_t Digest() const { return XXH3_64bits_digest(state_); }

 private:
  XXH3_state_t* state_;
};

uint32_t& GeometryVersion() {
  static uint32_t version = kCheckedGeometryVersion;
  return version;
}

std::function<void(std::string_view)>& StageHook() {
  static std::function<void(std::string_view)> hook;
  return hook;
}

}  // namespace

uint64_t ImageChecksum(const PackedFeatures& features) {
  Checksum checksum;
  checksum.Update(features.bytes());
  checksum.Update(features.signature_bytes());
  return checksum.Digest();
}

void SetGeometryFormatVersionForTesting(uint32_t version) {
  OXBOW_CHECK(version >= kGeometryVersion && version <= kCheckedGeometryVersion);
  GeometryVersion() = version;
}

void SetCheckpointStageHookForTesting(std::function<void(std::string_view)> hook) { StageHook() = std::move(hook); }

void CheckpointStage(std::string_view stage) {
  if (StageHook()) StageHook()(stage);
}

std::string CheckpointManifest::Format() const {
  std::ostringstream out;
  out << kManifestHeader << "\ngeneration " << generation << "\nhigh_water " << high_water << "\nsqrt_tf "
      << (sqrt_tf ? 1 : 0) << "\n";
  for (const CheckpointFile& f : files) out << "file " << f.name << " " << f.size_bytes << " " << f.checksum << "\n";
  return out.str();
}

Result<CheckpointManifest> CheckpointManifest::Parse(const std::string& text) {
  const auto bad = [] { return Fail(ErrorCode::kCorruptData, "unreadable checkpoint manifest"); };
  std::istringstream in(text);
  std::string line;
  if (!std::getline(in, line) || line != kManifestHeader) return bad();
  CheckpointManifest m;
  std::string key;
  int sqrt_tf = 0;
  if (!(in >> key >> m.generation) || key != "generation") return bad();
  if (!(in >> key >> m.high_water) || key != "high_water") return bad();
  if (!(in >> key >> sqrt_tf) || key != "sqrt_tf") return bad();
  m.sqrt_tf = sqrt_tf != 0;
  while (in >> key) {
    CheckpointFile f;
    if (key != "file" || !(in >> f.name >> f.size_bytes >> f.checksum)) return bad();
    // Names come from this code; anything else (a path) is not ours to open or delete.
    if (!IsCheckpointFileName(f.name) || f.name.find('/') != std::string::npos) return bad();
    m.files.push_back(std::move(f));
  }
  if (m.generation == 0 || m.high_water < 0) return bad();
  return m;
}

namespace {
// Reads out.size() bytes of `fd` from `offset` with pread (again after EINTR and short reads): fewer
// only at the end of the file; -1 with errno on a read error.
ssize_t ReadFully(int fd, uint64_t offset, std::span<uint8_t> out) {
  size_t done = 0;
  while (done < out.size()) {
    const ssize_t n = ::pread(fd, out.data() + done, out.size() - done, static_cast<off_t>(offset + done));
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) return -1;
    if (n == 0) break;
    done += static_cast<size_t>(n);
  }
  return static_cast<ssize_t>(done);
}

// Descriptors kept open by mapped files (MappedFile::ReadAt).
std::atomic<int> kept_descriptors{0};

// Whether one more mapped file may keep its descriptor: at most a quarter of the soft limit on open
// files (256 of the usual 1024), so that a folder of many geometry files never starves sockets.
bool KeepDescriptor() {
  static const int cap = [] {
    rlimit limit{};
    if (::getrlimit(RLIMIT_NOFILE, &limit) != 0 || limit.rlim_cur == RLIM_INFINITY) return 256;
    return static_cast<int>(std::min<rlim_t>(limit.rlim_cur / 4, 1 << 16));
  }();
  int kept = kept_descriptors.load(std::memory_order_relaxed);
  while (kept < cap) {
    if (kept_descriptors.compare_exchange_weak(kept, kept + 1, std::memory_order_relaxed)) return true;
  }
  return false;
}
}  // namespace

Result<std::shared_ptr<const MappedFile>> MappedFile::Open(const std::string& path, Use use) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return Fail(errno == ENOENT ? ErrorCode::kNotFound : ErrorCode::kIoError, path + ": " + ErrnoText());
  struct stat st {};
  if (::fstat(fd, &st) != 0) {
    const std::string message = ErrnoText();
    ::close(fd);
    return Fail(ErrorCode::kIoError, path + ": " + message);
  }
  const auto size = static_cast<size_t>(st.st_size);
  void* data = nullptr;
  if (size > 0 && use == Use::kRandom) {
    data = ::mmap(nullptr, size, PROT_READ, MAP_SHARED, fd, 0);
    if (data == MAP_FAILED) {
      const std::string message = ErrnoText();
      ::close(fd);
      return Fail(ErrorCode::kIoError, "cannot map " + path + ": " + message);
    }
    ::madvise(data, size, MADV_RANDOM);
  } else if (size > 0) {
    data = ::mmap(nullptr, size, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (data == MAP_FAILED) {
      const std::string message = ErrnoText();
      ::close(fd);
      return Fail(ErrorCode::kResourceExhausted, "cannot allocate " + std::to_string(size) + " bytes for " + path + ": " + message);
    }
    // Huge pages: 2 GB of postings would otherwise take half a million page faults to fill.
    ::madvise(data, size, MADV_HUGEPAGE);
    auto* out = static_cast<uint8_t*>(data);
    size_t done = 0;
    std::string error;
    while (done < size) {
      const ssize_t n = ::read(fd, out + done, std::min<size_t>(size - done, size_t{64} << 20));
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) {
        error = n < 0 ? ErrnoText() : "the file shrank while it was read";
        break;
      }
      done += static_cast<size_t>(n);
    }
    if (done < size || ::mprotect(data, size, PROT_READ) != 0) {
      if (error.empty()) error = ErrnoText();
      ::munmap(data, size);
      ::close(fd);
      return Fail(ErrorCode::kIoError, "cannot read " + path + ": " + error);
    }
  }
  // A mapping stays valid without its descriptor; a mapped file keeps it for ReadAt, up to a share of
  // the process's descriptor limit (past it ReadAt says no and callers read through the mapping).
  const bool keep = size > 0 && use == Use::kRandom && KeepDescriptor();
  if (!keep) ::close(fd);
  std::shared_ptr<MappedFile> file(new MappedFile(static_cast<const uint8_t*>(data), size, keep ? fd : -1,
                                                  use == Use::kRandom ? path : std::string(),
                                                  static_cast<uint64_t>(st.st_dev), static_cast<uint64_t>(st.st_ino)));
  // A page of the mapping that the file no longer holds (truncated) or the disk cannot read reads as
  // zeros instead of ending the process with SIGBUS (mapping_faults.h); readers check what they read.
  if (size > 0 && use == Use::kRandom) file->fault_guard_ = std::make_unique<MappingFaultGuard>(data, size);
  return std::shared_ptr<const MappedFile>(std::move(file));
}

MappedFile::~MappedFile() {
  fault_guard_.reset();  // before the range is unmapped (MappingFaultGuard's contract)
  if (size_ > 0) ::munmap(const_cast<uint8_t*>(data_), size_);
  if (fd_ >= 0) {
    ::close(fd_);
    kept_descriptors.fetch_sub(1, std::memory_order_relaxed);
  }
}

bool MappedFile::ReadAt(std::span<const uint8_t> within, std::span<uint8_t> out) const {
  if (fd_ < 0 || out.size() != within.size() || within.data() < data_ || within.size() > size_ ||
      static_cast<size_t>(within.data() - data_) > size_ - within.size()) {
    return false;
  }
  return ReadFully(fd_, static_cast<uint64_t>(within.data() - data_), out) == static_cast<ssize_t>(out.size());
}

bool MappedFile::Copy(std::span<const uint8_t> within, std::span<uint8_t> out) const {
  if (within.empty()) return out.empty();
  if (out.size() != within.size() || within.data() < data_ || within.size() > size_ ||
      static_cast<size_t>(within.data() - data_) > size_ - within.size()) {
    return false;
  }
  if (fd_ >= 0) return ReadAt(within, out);
  // Through the mapping: a page the file no longer holds reads as zeros (the fault handler), so the
  // copy is good only if the file still holds all of it once it is made.
  std::memcpy(out.data(), within.data(), within.size());
  return Holds(within);
}

bool MappedFile::Holds(std::span<const uint8_t> within) const {
  if (path_.empty() || within.empty() || within.data() < data_ || within.data() >= data_ + size_) return true;
  struct stat st {};
  if (fd_ >= 0) {
    if (::fstat(fd_, &st) != 0) return false;
  } else {
    // Gone from its path, or another file there now: nothing can truncate the mapped one by name.
    if (::stat(path_.c_str(), &st) != 0) return errno == ENOENT;
    if (static_cast<uint64_t>(st.st_dev) != device_ || static_cast<uint64_t>(st.st_ino) != inode_) return true;
  }
  const auto end = static_cast<uint64_t>(within.data() - data_) + within.size();
  return st.st_size >= 0 && static_cast<uint64_t>(st.st_size) >= end;
}

Result<CheckpointFile> WriteCheckpointFile(const std::string& dir, const std::string& name,
                                           const std::function<void(const ByteSink&)>& produce) {
  const std::string path = (std::filesystem::path(dir) / name).string();
  const std::string tmp = path + ".tmp";
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) return Fail(ErrorCode::kIoError, "cannot create " + tmp + ": " + ErrnoText());
  CheckpointFile file{.name = name};
  Checksum checksum;
  std::vector<uint8_t> buffer;
  buffer.reserve(size_t{1} << 20);
  bool ok = true;
  std::string error;
  auto write_all = [&](std::span<const uint8_t> bytes) {
    size_t done = 0;
    while (ok && done < bytes.size()) {
      const ssize_t n = ::write(fd, bytes.data() + done, bytes.size() - done);
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) {
        ok = false;
        error = ErrnoText();
      } else {
        done += static_cast<size_t>(n);
      }
    }
  };
  auto flush = [&] {
    write_all(buffer);
    buffer.clear();
  };
  produce([&](std::span<const uint8_t> bytes) {
    checksum.Update(bytes);
    file.size_bytes += bytes.size();
    if (buffer.size() + bytes.size() > buffer.capacity()) flush();
    if (bytes.size() >= buffer.capacity()) {
      // Written from where it lies (a segment's postings, hundreds of MB at a million images): a copy
      // into the buffer first took a page fault per 4 KiB of it.
      write_all(bytes);
    } else {
      buffer.insert(buffer.end(), bytes.begin(), bytes.end());
    }
  });
  flush();
  file.checksum = checksum.Digest();
  CheckpointStage("file-unsynced");
  if (ok && ::fsync(fd) != 0) {
    ok = false;
    error = ErrnoText();
  }
  if (::close(fd) != 0 && ok) {
    ok = false;
    error = ErrnoText();
  }
  if (ok && ::rename(tmp.c_str(), path.c_str()) != 0) {
    ok = false;
    error = ErrnoText();
  }
  if (!ok) {
    ::unlink(tmp.c_str());
    return Fail(ErrorCode::kIoError, "cannot write " + path + ": " + error);
  }
  // The rename is durable once the folder is.
  const int dir_fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dir_fd < 0 || ::fsync(dir_fd) != 0) {
    error = ErrnoText();
    if (dir_fd >= 0) ::close(dir_fd);
    return Fail(ErrorCode::kIoError, "cannot sync the folder " + dir + ": " + error);
  }
  ::close(dir_fd);
  return file;
}

namespace {

// A file's size and checksum against its manifest entry (`what` names the file).
Status MatchesManifest(uint64_t size, uint64_t digest, const CheckpointFile& file, const std::string& what) {
  if (size != file.size_bytes) {
    return Fail(ErrorCode::kCorruptData, what + " has " + std::to_string(size) + " bytes, its manifest says " +
                                             std::to_string(file.size_bytes));
  }
  if (digest != file.checksum) return Fail(ErrorCode::kCorruptData, what + " fails its checksum");
  return Ok();
}

// Reads a file in blocks, leaving the page cache as it found it: a block's pages the cache held
// (mincore on a mapping of the file that is never touched) are read from it and stay; the others are
// read from the disk, without read-ahead, and dropped again (POSIX_FADV_DONTNEED) once read. A check of
// every file of an index (16 GB at 1M images) would otherwise push the searches' pages out of the
// cache and fill memory the kernel may have handed back to a hypervisor (free page reporting): on the
// 2-core test VM (machine C of eval/results/README.md) such a page costs about 1.7 ms per MB to touch
// again, and the first searches after a bulk ingest stall by 100-250 ms while such a check fills the cache.
class CacheNeutralReader {
 public:
  explicit CacheNeutralReader(int fd) : fd_(fd) {  // takes `fd` (closed by the destructor)
    (void)::posix_fadvise(fd, 0, 0, POSIX_FADV_RANDOM);  // no read-ahead: it would leave pages behind
    struct stat st {};
    if (::fstat(fd, &st) == 0 && st.st_size > 0) {
      void* map = ::mmap(nullptr, static_cast<size_t>(st.st_size), PROT_READ, MAP_SHARED, fd, 0);
      if (map != MAP_FAILED) {
        map_ = static_cast<uint8_t*>(map);
        map_size_ = static_cast<size_t>(st.st_size);
      }
    }
  }
  CacheNeutralReader(const CacheNeutralReader&) = delete;
  CacheNeutralReader& operator=(const CacheNeutralReader&) = delete;
  ~CacheNeutralReader() {
    if (map_ != nullptr) ::munmap(map_, map_size_);
    ::close(fd_);
  }

  // Up to out.size() bytes at `offset` (fewer only at the end of the file); -1 with errno on a read error.
  ssize_t Read(uint64_t offset, std::span<uint8_t> out) {
    static const auto page = static_cast<uint64_t>(::sysconf(_SC_PAGESIZE));
    const uint64_t first = offset / page;
    const uint64_t mapped = offset < map_size_ ? std::min<uint64_t>(out.size(), map_size_ - offset) : 0;
    held_.assign((offset + mapped + page - 1) / page - first, 0);  // 0: not held (or unknown): dropped after
    if (!held_.empty() && ::mincore(map_ + first * page, held_.size() * page, held_.data()) != 0) {
      std::fill(held_.begin(), held_.end(), 0);
    }
    const ssize_t got = ReadFully(fd_, offset, out);
    if (got < 0) return -1;
    const auto done = static_cast<uint64_t>(got);
    // Drop each run of the pages read that the cache did not hold (clean pages no process maps).
    const uint64_t end = (offset + done + page - 1) / page;
    for (uint64_t p = first; p < end;) {
      const auto held = [&](uint64_t q) { return q - first < held_.size() && (held_[q - first] & 1) != 0; };
      if (held(p)) {
        ++p;
        continue;
      }
      uint64_t q = p;
      while (q < end && !held(q)) ++q;
      (void)::posix_fadvise(fd_, static_cast<off_t>(p * page), static_cast<off_t>((q - p) * page), POSIX_FADV_DONTNEED);
      p = q;
    }
    return got;
  }

 private:
  int fd_;
  uint8_t* map_ = nullptr;  // never touched: only mincore looks at it
  size_t map_size_ = 0;
  std::vector<unsigned char> held_;
};

}  // namespace

Status VerifyCheckpointFile(const std::string& dir, const CheckpointFile& file) {
  std::optional<Status> status = VerifyCheckpointFileUnless(dir, file, [] { return false; });
  return status.has_value() ? std::move(*status) : Fail(ErrorCode::kInternal, "the check of " + file.name + " stopped");
}

std::optional<Status> VerifyCheckpointFileUnless(const std::string& dir, const CheckpointFile& file,
                                                 const std::function<bool()>& stop) {
  const std::string path = (std::filesystem::path(dir) / file.name).string();
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    return Fail(errno == ENOENT ? ErrorCode::kNotFound : ErrorCode::kIoError, "checkpoint file " + path + ": " + ErrnoText());
  }
  CacheNeutralReader reader(fd);
  std::vector<uint8_t> buffer(size_t{4} << 20);
  uint64_t size = 0;
  Checksum checksum;
  while (true) {
    if (stop()) return std::nullopt;
    const ssize_t n = reader.Read(size, buffer);
    if (n < 0) {
      std::string message = "cannot read checkpoint file " + path;
      message += ": ";
      message += ErrnoText();
      return Fail(ErrorCode::kIoError, message);
    }
    if (n == 0) break;
    checksum.Update(std::span(buffer.data(), static_cast<size_t>(n)));
    size += static_cast<uint64_t>(n);
  }
  return MatchesManifest(size, checksum.Digest(), file, "checkpoint file " + path);
}

Status VerifyCheckpointBytes(std::span<const uint8_t> bytes, const CheckpointFile& file, const std::string& what) {
  Checksum checksum;
  checksum.Update(bytes);
  return MatchesManifest(bytes.size(), checksum.Digest(), file, what);
}

void WriteGeometry(std::span<const GeometryImage> images, const ByteSink& sink) {
  const auto put = [&](const auto& value) {
    sink(std::span(reinterpret_cast<const uint8_t*>(&value), sizeof(value)));
  };
  const uint32_t version = GeometryVersion();
  sink(std::span(reinterpret_cast<const uint8_t*>(kGeometryMagic), sizeof(kGeometryMagic)));
  put(version);
  put(kByteOrderMark);
  put(uint64_t{images.size()});
  uint64_t offset = 0;
  for (const GeometryImage& image : images) {
    const GeometryEntry entry{image.number, image.features.width(), image.features.height(),
                              static_cast<uint32_t>(image.features.size()), offset};
    const bool has_signatures = !image.features.signature_bytes().empty();
    const SignedGeometryEntry signed_entry{entry, has_signatures ? 1u : 0u, 0};
    if (version == kCheckedGeometryVersion) {
      put(CheckedGeometryEntry{signed_entry, ImageChecksum(image.features)});
    } else if (version == kSignedGeometryVersion) {
      put(signed_entry);
    } else {
      OXBOW_CHECK(!has_signatures, "geometry format version 1 has no signatures");
      put(entry);
    }
    offset += image.features.bytes().size() + image.features.signature_bytes().size();
  }
  for (const GeometryImage& image : images) {
    sink(image.features.bytes());
    if (!image.features.signature_bytes().empty()) sink(image.features.signature_bytes());
  }
}

Result<std::vector<GeometryImage>> ReadGeometry(const std::shared_ptr<const MappedFile>& file, const std::string& what) {
  const std::span<const uint8_t> bytes = file->bytes();
  const auto corrupt = [&](const std::string& why) { return Fail(ErrorCode::kCorruptData, what + ": " + why); };
  constexpr size_t kHeader = 4 + 4 + 4 + 8;
  if (bytes.size() < kHeader || !std::equal(kGeometryMagic, kGeometryMagic + 4, bytes.begin())) {
    return corrupt("not a geometry file");
  }
  uint32_t version = 0, mark = 0;
  uint64_t count = 0;
  std::memcpy(&version, bytes.data() + 4, 4);
  std::memcpy(&mark, bytes.data() + 8, 4);
  std::memcpy(&count, bytes.data() + 12, 8);
  if (version < kGeometryVersion || version > kCheckedGeometryVersion || mark != kByteOrderMark) {
    return corrupt("format version or byte order not readable");
  }
  const size_t entry_bytes = version == kCheckedGeometryVersion ? sizeof(CheckedGeometryEntry)
                             : version == kSignedGeometryVersion ? sizeof(SignedGeometryEntry)
                                                                 : sizeof(GeometryEntry);
  if (count > (bytes.size() - kHeader) / entry_bytes) return corrupt("truncated image table");
  const size_t data_start = kHeader + count * entry_bytes;
  // The image table in one pread: read through the mapping (MADV_RANDOM, no read-ahead), a cold file
  // took a page fault and a synchronous 4 KiB disk read per page of it, about a hundred per file. What
  // is checked below is the copy, so a file truncated meanwhile cannot change it after its check.
  std::vector<uint8_t> table_copy(count * entry_bytes);
  if (!file->Copy(bytes.subspan(kHeader, table_copy.size()), table_copy)) return corrupt("image table unreadable (truncated?)");
  const std::span<const uint8_t> table = table_copy;
  std::vector<GeometryImage> out;
  out.reserve(count);
  uint64_t expected_offset = 0;
  for (uint64_t i = 0; i < count; ++i) {
    CheckedGeometryEntry checked_entry{};
    std::memcpy(&checked_entry, table.data() + i * entry_bytes, entry_bytes);
    const SignedGeometryEntry& signed_entry = checked_entry.signed_entry;
    const GeometryEntry& e = signed_entry.entry;
    if (signed_entry.has_signatures > 1 || signed_entry.reserved != 0) return corrupt("inconsistent image table");
    const uint64_t feature_length = uint64_t{e.count} * kPackedFeatureBytes;
    const uint64_t length = feature_length + (signed_entry.has_signatures != 0 ? uint64_t{e.count} * kSignatureBytes : 0);
    if (e.offset != expected_offset || length > bytes.size() - data_start - e.offset ||
        (!out.empty() && e.number <= out.back().number)) {
      return corrupt("inconsistent image table");
    }
    expected_offset += length;
    const std::span<const uint8_t> data = bytes.subspan(data_start + e.offset, length);
    auto features = PackedFeatures::View(data.first(feature_length), data.subspan(feature_length), e.width, e.height, file,
                                         "image number " + std::to_string(e.number) + " in " + what);
    if (!features) return std::unexpected(features.error());
    out.push_back({e.number, std::move(*features),
                   version == kCheckedGeometryVersion ? std::optional<uint64_t>(checked_entry.checksum) : std::nullopt});
  }
  if (data_start + expected_offset != bytes.size()) return corrupt("trailing bytes");
  return out;
}

void RemoveUnreferencedCheckpointFiles(const std::string& dir, const CheckpointManifest& manifest) {
  std::set<std::string> keep;
  for (const CheckpointFile& f : manifest.files) keep.insert(f.name);
  std::error_code ec;
  for (const auto& item : std::filesystem::directory_iterator(dir, ec)) {
    const std::string name = item.path().filename().string();
    if (IsCheckpointFileName(name) && !keep.count(name)) std::filesystem::remove(item.path(), ec);
  }
}

}  // namespace oxbow::index
