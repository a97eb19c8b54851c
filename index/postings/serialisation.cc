// The checkpoint form of the inverted file (serialisation.h): its writers and its reader.
#include "index/postings/serialisation.h"

#include <algorithm>
#include <atomic>
#include <cstring>
#include <limits>
#include <type_traits>

#include "index/postings/inverted_file.h"
#include "sift/base/error.h"
#include "sift/base/parallel.h"

namespace oxbow::index {
namespace {

using postings::CollectionStatistics;
using postings::kByteOrderMark;
using postings::kFileMagic;
using postings::kFileVersion;
using postings::kHeadVersion;
using postings::kOldestReadableVersion;
using postings::kSegmentMagic;
using postings::Segment;

template <typename T>
std::span<const uint8_t> AsBytes(const T& value) {
  return {reinterpret_cast<const uint8_t*>(&value), sizeof(T)};
}

template <typename T>
std::span<const uint8_t> AsBytes(std::span<const T> values) {
  return {reinterpret_cast<const uint8_t*>(values.data()), values.size_bytes()};
}

// A CowArray as a count then the elements, chunk by chunk.
template <typename Array>
void PutCow(const Array& array, const InvertedFile::Writer& write) {
  write(AsBytes(uint64_t{array.size()}));
  for (size_t i = 0; i < array.size(); i += Array::kChunk) {
    const size_t n = std::min(array.size() - i, Array::kChunk);
    write(AsBytes(std::span(&array[i], n)));
  }
}

void PutSegmentRecord(const Segment& segment, const InvertedFile::Writer& write) {
  write(AsBytes(segment.first_image));
  write(AsBytes(segment.end_image));
  write(AsBytes(uint8_t{segment.dense ? uint8_t{1} : uint8_t{0}}));
  write(AsBytes(segment.num_postings));
  write(AsBytes(uint64_t{segment.words.size()}));
  write(AsBytes(std::span<const uint32_t>(segment.words)));
  write(AsBytes(uint64_t{segment.offsets.size()}));
  write(AsBytes(std::span<const uint64_t>(segment.offsets)));
  write(AsBytes(uint64_t{segment.size()}));
  write(std::span<const uint8_t>(segment.data(), segment.size()));
}

// Bounds-checked reads of the serialised form; a short read sets `ok` to false and yields zeros.
struct FileReader {
  std::span<const uint8_t> bytes;
  size_t at = 0;
  bool ok = true;

  template <typename T>
  T Get() {
    T value{};
    Copy(&value, sizeof(T));
    return value;
  }
  template <typename T>
  std::vector<T> GetVector(uint64_t max_count) {
    const auto count = Get<uint64_t>();
    if (!ok || count > max_count || count > (bytes.size() - at) / sizeof(T)) {
      ok = false;
      return {};
    }
    std::vector<T> out(count);
    Copy(out.data(), count * sizeof(T));
    return out;
  }
  // The next `count` bytes in place (a view of `bytes`), after their u64 count.
  std::span<const uint8_t> View(uint64_t max_count) {
    const auto count = Get<uint64_t>();
    if (!ok || count > max_count || count > bytes.size() - at) {
      ok = false;
      return {};
    }
    const std::span<const uint8_t> out = bytes.subspan(at, count);
    at += count;
    return out;
  }
  void Copy(void* out, size_t n) {
    if (!ok || bytes.size() - at < n) {
      ok = false;
      return;
    }
    if (n == 0) return;  // an empty vector's data() may be null, which memcpy must not get
    std::memcpy(out, bytes.data() + at, n);
    at += n;
  }
  // A CowArray written by PutCow; expected_size: the only size accepted (any when max).
  template <typename Array>
  void GetCow(Array* array, uint64_t expected_size) {
    using T = std::remove_cvref_t<decltype((*array)[0])>;
    const auto size = Get<uint64_t>();
    if (!ok || (size != expected_size && expected_size != std::numeric_limits<uint64_t>::max()) ||
        size >= (uint64_t{1} << 32) || size > (bytes.size() - at) / sizeof(T)) {
      ok = false;
      return;
    }
    Array fresh;
    typename Array::Editor editor(&fresh);
    editor.Resize(size);
    for (size_t i = 0; i < size; ++i) Copy(&editor.Mutable(i), sizeof(T));
    *array = std::move(fresh);
  }
};

// One segment record (PutSegmentRecord), its structure checked; `owner` non-null: its postings viewed
// in place.
Result<std::shared_ptr<Segment>> ParseSegment(FileReader& in, size_t vocabulary_size, uint64_t num_numbers,
                                              const std::shared_ptr<const void>& owner) {
  auto segment = std::make_shared<Segment>();
  segment->first_image = in.Get<uint32_t>();
  segment->end_image = in.Get<uint32_t>();
  segment->dense = in.Get<uint8_t>() != 0;
  segment->num_postings = in.Get<uint64_t>();
  segment->words = in.GetVector<uint32_t>(vocabulary_size);
  segment->offsets = in.GetVector<uint64_t>(vocabulary_size + 1);
  if (owner) {
    segment->mapped = in.View(std::numeric_limits<uint64_t>::max());
    segment->owner = owner;
  } else {
    segment->bytes = in.GetVector<uint8_t>(std::numeric_limits<uint64_t>::max());
  }
  if (!in.ok) return Fail(ErrorCode::kCorruptData, "truncated");
  const size_t expected_offsets = segment->dense ? vocabulary_size + 1 : segment->words.size() + 1;
  if (segment->first_image > segment->end_image || segment->end_image > num_numbers ||
      segment->offsets.size() != expected_offsets || segment->offsets.back() != segment->size() ||
      (segment->dense && !segment->words.empty()) || !std::is_sorted(segment->offsets.begin(), segment->offsets.end()) ||
      std::adjacent_find(segment->words.begin(), segment->words.end(), std::greater_equal<>()) != segment->words.end() ||
      (!segment->words.empty() && segment->words.back() >= vocabulary_size)) {
    return Fail(ErrorCode::kCorruptData, "inconsistent");
  }
  return segment;
}

std::unexpected<Error> Corrupt(const std::string& why) { return Fail(ErrorCode::kCorruptData, "inconsistent inverted file: " + why); }

// The segment whose file a head names next (its name read from `in`), through `segment_source`; its
// header must match the head's.
Result<std::shared_ptr<Segment>> ReadSegmentFile(FileReader& in, size_t vocabulary_size, uint64_t num_numbers,
                                                 const InvertedFile::SegmentSource& segment_source) {
  const auto length = in.Get<uint64_t>();
  if (!in.ok || length > 4096 || length > in.bytes.size() - in.at) return Corrupt("truncated segment name");
  const std::string name(reinterpret_cast<const char*>(in.bytes.data() + in.at), length);
  in.at += length;
  auto source = segment_source(name);
  if (!source) return Fail(source.error().code, "segment file " + name + ": " + source.error().message);
  FileReader file{source->first};
  char segment_magic[4] = {};
  file.Copy(segment_magic, sizeof(segment_magic));
  const auto segment_version = file.Get<uint32_t>();
  const auto bom = file.Get<uint32_t>();
  const auto segment_vocabulary = file.Get<uint64_t>();
  if (!file.ok || !std::equal(segment_magic, segment_magic + 4, kSegmentMagic) || segment_version != kHeadVersion ||
      bom != kByteOrderMark || segment_vocabulary != vocabulary_size) {
    return Corrupt("segment file " + name + " has a bad header");
  }
  auto segment = ParseSegment(file, vocabulary_size, num_numbers, source->second);
  if (segment && file.at != file.bytes.size()) segment = Fail(ErrorCode::kCorruptData, "trailing bytes");
  if (!segment) return Corrupt("segment file " + name + ": " + segment.error().message);
  return segment;
}

// A segment read from a version-1 file, its postings re-coded from varints into 16-bit units (same
// words, layout and postings). Bounds-checked, and the posting count must match the segment's; lists in
// parallel (two passes: sizes, then contents), so that loading a large version-1 file stays fast.
Result<std::shared_ptr<Segment>> RecodeFormat1(const Segment& old) {
  const size_t lists = old.offsets.size() - 1;
  const auto decode = [&old](size_t k, auto&& fn) {
    return postings::ForEachFormat1Posting(old.data() + old.offsets[k], old.data() + old.offsets[k + 1], fn);
  };
  std::vector<uint64_t> offsets(lists + 1, 0);
  std::vector<uint64_t> counts(lists, 0);
  std::atomic<bool> ok{true};
  ParallelFor(lists, 0, 256, [&](size_t begin, size_t end, int) {
    for (size_t k = begin; k < end; ++k) {
      uint64_t size = 0, n = 0;
      if (!decode(k, [&](uint32_t gap, uint32_t tf) {
            size += postings::PostingSize(gap, tf);
            ++n;
          })) {
        ok = false;
      }
      offsets[k + 1] = size;
      counts[k] = n;
    }
  });
  uint64_t num_postings = 0;
  for (size_t k = 0; k < lists; ++k) {
    offsets[k + 1] += offsets[k];
    num_postings += counts[k];
  }
  if (!ok || num_postings != old.num_postings) return Fail(ErrorCode::kCorruptData, "malformed version-1 postings");
  auto out = std::make_shared<Segment>();
  out->first_image = old.first_image;
  out->end_image = old.end_image;
  out->dense = old.dense;
  out->words = old.words;
  out->num_postings = old.num_postings;
  out->bytes.resize(offsets.back());
  ParallelFor(lists, 0, 256, [&](size_t begin, size_t end, int) {
    for (size_t k = begin; k < end; ++k) {
      uint8_t* q = out->bytes.data() + offsets[k];
      decode(k, [&](uint32_t gap, uint32_t tf) { q = postings::PutPosting(q, gap, tf); });
    }
  });
  out->offsets = std::move(offsets);
  return out;
}

// The head's magic, version and byte order: the version, or why the file cannot be read.
Result<uint32_t> ReadVersion(FileReader& in, bool has_segment_source) {
  char magic[4] = {};
  in.Copy(magic, sizeof(magic));
  if (!in.ok || !std::equal(magic, magic + 4, kFileMagic)) return Corrupt("bad magic");
  const auto version = in.Get<uint32_t>();
  if (version < kOldestReadableVersion || version > kHeadVersion || in.Get<uint32_t>() != kByteOrderMark) {
    return Fail(ErrorCode::kIncompatible, "inverted file format version " + std::to_string(version) +
                                              " or byte order not readable by this build");
  }
  if (version == kHeadVersion && !has_segment_source) {
    return Fail(ErrorCode::kInvalidArgument, "an inverted file's head read without its segment files");
  }
  return version;
}

}  // namespace

void InvertedFile::SerializeHead(uint32_t version, const Writer& write) const {
  write(AsBytes(kFileMagic));
  write(AsBytes(version));
  write(AsBytes(kByteOrderMark));
  write(AsBytes(uint64_t{vocabulary_size_}));
  write(AsBytes(uint8_t{options_.sqrt_tf ? uint8_t{1} : uint8_t{0}}));
  for (const uint64_t v : {statistics_.num_images(), changes_since_refresh_, num_live_, num_live_features_,
                           num_postings_, num_dead_postings_}) {
    write(AsBytes(v));
  }
  PutCow(df_, write);
  PutCow(statistics_.document_frequencies(), write);
  PutCow(images_, write);
  write(AsBytes(uint64_t{segments_.size()}));
}

void InvertedFile::Serialize(const Writer& write) const {
  SerializeHead(kFileVersion, write);
  for (const auto& segment : segments_) PutSegmentRecord(*segment, write);
}

void InvertedFile::SerializeHead(std::span<const std::string> segment_names, const Writer& write) const {
  OXBOW_CHECK(segment_names.size() == segments_.size(), "one name per segment");
  SerializeHead(kHeadVersion, write);
  for (const std::string& name : segment_names) {
    write(AsBytes(uint64_t{name.size()}));
    write(std::span(reinterpret_cast<const uint8_t*>(name.data()), name.size()));
  }
}

void InvertedFile::SerializeSegment(size_t i, const Writer& write) const {
  write(AsBytes(kSegmentMagic));
  write(AsBytes(kHeadVersion));
  write(AsBytes(kByteOrderMark));
  write(AsBytes(uint64_t{vocabulary_size_}));
  PutSegmentRecord(*segments_[i], write);
}

Result<InvertedFile> InvertedFile::Deserialize(std::span<const uint8_t> bytes, size_t vocabulary_size,
                                               const TfIdfOptions& options, bool* recoded,
                                               const std::shared_ptr<const void>& owner,
                                               const SegmentSource& segment_source) {
  FileReader in{bytes};
  const Result<uint32_t> version = ReadVersion(in, segment_source != nullptr);
  if (!version) return std::unexpected(version.error());
  const auto stored_vocabulary_size = in.Get<uint64_t>();
  const bool sqrt_tf = in.Get<uint8_t>() != 0;
  if (stored_vocabulary_size != vocabulary_size || sqrt_tf != options.sqrt_tf) {
    return Fail(ErrorCode::kIncompatible, "inverted file made for another vocabulary size or sqrt_tf setting");
  }
  InvertedFile out(vocabulary_size, options);
  const auto stats_num_live = in.Get<uint64_t>();
  out.changes_since_refresh_ = in.Get<uint64_t>();
  out.num_live_ = in.Get<uint64_t>();
  out.num_live_features_ = in.Get<uint64_t>();
  out.num_postings_ = in.Get<uint64_t>();
  out.num_dead_postings_ = in.Get<uint64_t>();
  CowArray<uint32_t> stats_df = out.df_;
  in.GetCow(&out.df_, vocabulary_size);
  in.GetCow(&stats_df, vocabulary_size);
  in.GetCow(&out.images_, std::numeric_limits<uint64_t>::max());
  out.statistics_ = CollectionStatistics(options.sqrt_tf, std::move(stats_df), stats_num_live);
  const uint64_t num_numbers = out.images_.size();
  const auto num_segments = in.Get<uint64_t>();
  if (!in.ok || num_segments > num_numbers + 1) return Corrupt("truncated or bad segment count");
  uint64_t postings = 0;
  uint32_t previous_end = 0;
  for (uint64_t i = 0; i < num_segments; ++i) {
    Result<std::shared_ptr<Segment>> segment = nullptr;
    if (*version == kHeadVersion) {
      segment = ReadSegmentFile(in, vocabulary_size, num_numbers, segment_source);
      if (!segment) return std::unexpected(segment.error());
    } else {
      segment = ParseSegment(in, vocabulary_size, num_numbers, owner);
      if (!segment) return Corrupt("segment " + std::to_string(i) + " is " + segment.error().message);
    }
    if ((*segment)->first_image < previous_end) return Corrupt("segment " + std::to_string(i) + " overlaps");
    previous_end = (*segment)->end_image;
    postings += (*segment)->num_postings;
    out.segments_.push_back(std::move(*segment));
  }
  if (*version == 1) {
    for (size_t i = 0; i < out.segments_.size(); ++i) {
      auto segment = RecodeFormat1(*out.segments_[i]);
      if (!segment) return Corrupt("segment " + std::to_string(i) + ": " + segment.error().message);
      out.segments_[i] = std::move(*segment);
    }
  }
  if (recoded != nullptr) *recoded = *version == 1;
  if (in.at != bytes.size()) return Corrupt("trailing bytes");
  if (postings != out.num_postings_ || out.num_live_ > num_numbers || out.statistics_.num_images() > num_numbers) {
    return Corrupt("counts disagree");
  }
  out.RecomputeNorms();
  return out;
}

}  // namespace oxbow::index
