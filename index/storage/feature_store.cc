#include "index/storage/feature_store.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <numbers>
#include <numeric>

#include <sys/mman.h>
#include <unistd.h>

#include "sift/base/binary_io.h"

namespace oxbow::index {
namespace {

constexpr char kMagic[4] = {'O', 'X', 'F', 'T'};
constexpr uint32_t kBlobVersion = 1;
constexpr uint32_t kSignedBlobVersion = 2;
constexpr size_t kBlobHeaderBytes = 4 + 4 * 5;

// std::round for 0 <= x < 2^52 (halves away from zero), without the libm call: x - trunc(x) is exact.
// Pack rounds four values per feature; the call was a tenth of its time.
inline int64_t RoundNonNegative(double x) {
  const auto t = static_cast<int64_t>(x);
  return t + (x - static_cast<double>(t) >= 0.5 ? 1 : 0);
}

inline uint16_t QuantizeCoordinate(float v, int size) {
  return static_cast<uint16_t>(RoundNonNegative(std::clamp(static_cast<double>(v) / size, 0.0, 1.0) * 65535.0));
}

// Writes the packed records of Pack (sorted by word, ties in input order) to `records` and, with
// signatures, theirs to `signature_out`.
void PackRecords(std::span<const sift::Keypoint> keypoints, std::span<const uint32_t> words, int width, int height,
                 std::span<const uint64_t> signatures, uint8_t* records, uint8_t* signature_out) {
  OXBOW_CHECK(keypoints.size() == words.size());
  OXBOW_CHECK(signatures.empty() || signatures.size() == words.size());
  OXBOW_CHECK(width > 0 && height > 0);
  // By word, ties in input order: a least-significant-digit radix sort of the positions, 11 bits of
  // the word per stable counting pass (two passes below 2^22 words). It is several times faster than
  // sorting (word, position) keys, and Pack runs once per added image.
  std::vector<uint32_t> order(words.size()), scratch(words.size());
  std::iota(order.begin(), order.end(), 0u);
  const uint32_t max_word = words.empty() ? 0 : *std::max_element(words.begin(), words.end());
  constexpr int kDigitBits = 11;
  constexpr uint32_t kDigits = 1u << kDigitBits;
  for (int shift = 0; shift == 0 || (shift < 32 && (max_word >> shift) != 0); shift += kDigitBits) {
    std::array<uint32_t, kDigits + 1> start{};
    for (const uint32_t w : words) ++start[((w >> shift) & (kDigits - 1)) + 1];
    for (uint32_t d = 0; d < kDigits; ++d) start[d + 1] += start[d];
    for (const uint32_t i : order) scratch[start[(words[i] >> shift) & (kDigits - 1)]++] = i;
    order.swap(scratch);
  }
  uint8_t* p = records;
  uint8_t* signature = signature_out;
  for (const uint32_t i : order) {
    const uint32_t w = words[i];
    OXBOW_CHECK(w <= kMaxPackedWord, "word id does not fit 24 bits");
    const sift::Keypoint& k = keypoints[i];
    const uint16_t x = QuantizeCoordinate(k.x, width), y = QuantizeCoordinate(k.y, height);
    const double log_scale = k.scale > 0 ? std::log2(static_cast<double>(k.scale)) : -4.0;
    const auto s = static_cast<int>(RoundNonNegative(std::clamp((log_scale + 4.0) * 16.0, 0.0, 255.0)));
    double turns = static_cast<double>(k.orientation) / (2 * std::numbers::pi);
    if (!std::isfinite(turns)) turns = 0;
    turns -= std::floor(turns);
    const int o = static_cast<int>(RoundNonNegative(turns * 256.0)) & 255;
    p[0] = static_cast<uint8_t>(w);
    p[1] = static_cast<uint8_t>(w >> 8);
    p[2] = static_cast<uint8_t>(w >> 16);
    p[3] = static_cast<uint8_t>(x);
    p[4] = static_cast<uint8_t>(x >> 8);
    p[5] = static_cast<uint8_t>(y);
    p[6] = static_cast<uint8_t>(y >> 8);
    p[7] = static_cast<uint8_t>(s);
    p[8] = static_cast<uint8_t>(o);
    p += kPackedFeatureBytes;
    if (signatures.empty()) continue;
    for (size_t b = 0; b < kSignatureBytes; ++b) *signature++ = static_cast<uint8_t>(signatures[i] >> (8 * b));
  }
}

// The BLOB header (kBlobHeaderBytes) of `count` features whose body has CRC-32 `crc`.
void WriteBlobHeader(uint8_t* out, bool with_signatures, int width, int height, size_t count, uint32_t crc) {
  // Host byte order, as the reader's io::ByteReader expects.
  const uint32_t fields[5] = {with_signatures ? kSignedBlobVersion : kBlobVersion, static_cast<uint32_t>(width),
                              static_cast<uint32_t>(height), static_cast<uint32_t>(count), crc};
  static_assert(sizeof(kMagic) + sizeof(fields) == kBlobHeaderBytes);
  std::memcpy(out, kMagic, sizeof(kMagic));
  std::memcpy(out + sizeof(kMagic), fields, sizeof(fields));
}

}  // namespace

PackedFeatures PackedFeatures::Pack(std::span<const sift::Keypoint> keypoints, std::span<const uint32_t> words,
                                    int width, int height, std::span<const uint64_t> signatures) {
  PackedFeatures out;
  out.width_ = width;
  out.height_ = height;
  const size_t feature_bytes = words.size() * kPackedFeatureBytes;
  auto storage = std::make_shared<std::vector<uint8_t>>(feature_bytes + signatures.size() * kSignatureBytes);
  PackRecords(keypoints, words, width, height, signatures, storage->data(), storage->data() + feature_bytes);
  out.bytes_ = std::span<const uint8_t>(*storage).first(feature_bytes);
  out.signature_bytes_ = std::span<const uint8_t>(*storage).subspan(feature_bytes);
  out.storage_ = storage;
  return out;
}

size_t PackedFeatures::BlobBytes(size_t count, bool with_signatures) {
  return kBlobHeaderBytes + count * (kPackedFeatureBytes + (with_signatures ? kSignatureBytes : 0));
}

PackedFeatures PackedFeatures::PackBlob(std::span<const sift::Keypoint> keypoints, std::span<const uint32_t> words,
                                        int width, int height, std::span<const uint64_t> signatures,
                                        std::span<uint8_t> blob, std::shared_ptr<const void> owner) {
  OXBOW_CHECK(blob.size() == BlobBytes(keypoints.size(), !signatures.empty()), "BLOB buffer of the wrong size");
  const size_t feature_bytes = words.size() * kPackedFeatureBytes;
  const std::span<uint8_t> body = blob.subspan(kBlobHeaderBytes);
  PackRecords(keypoints, words, width, height, signatures, body.data(), body.data() + feature_bytes);
  WriteBlobHeader(blob.data(), !signatures.empty(), width, height, words.size(), io::Crc32(body));
  PackedFeatures out;
  out.width_ = width;
  out.height_ = height;
  out.bytes_ = body.first(feature_bytes);
  out.signature_bytes_ = body.subspan(feature_bytes);
  out.storage_ = std::move(owner);
  return out;
}

sift::Keypoint PackedFeatures::keypoint(size_t i) const {
  const uint8_t* p = bytes_.data() + i * kPackedFeatureBytes;
  sift::Keypoint k;
  k.x = static_cast<float>((p[3] | (p[4] << 8)) * static_cast<double>(width_) / 65535.0);
  k.y = static_cast<float>((p[5] | (p[6] << 8)) * static_cast<double>(height_) / 65535.0);
  k.scale = static_cast<float>(std::exp2(p[7] / 16.0 - 4.0));
  k.orientation = static_cast<float>(p[8] / 256.0 * 2 * std::numbers::pi);
  return k;
}

std::vector<sift::Keypoint> PackedFeatures::Keypoints() const {
  std::vector<sift::Keypoint> out(size());
  for (size_t i = 0; i < out.size(); ++i) out[i] = keypoint(i);
  return out;
}

std::vector<uint32_t> PackedFeatures::Words() const {
  std::vector<uint32_t> out(size());
  for (size_t i = 0; i < out.size(); ++i) out[i] = word(i);
  return out;
}

BagOfWords PackedFeatures::Bag() const {
  BagOfWords bag;
  const size_t n = size();
  for (size_t i = 0; i < n;) {
    const uint32_t w = word(i);
    size_t j = i + 1;
    while (j < n && word(j) == w) ++j;
    bag.words.push_back(w);
    bag.counts.push_back(static_cast<uint32_t>(j - i));
    i = j;
  }
  return bag;
}

BagOfWords PackedFeatures::BagInside(const std::array<float, 4>& box) const {
  std::vector<uint32_t> words;
  for (size_t i = 0; i < size(); ++i) {
    const sift::Keypoint k = keypoint(i);
    if (k.x >= box[0] && k.x <= box[2] && k.y >= box[1] && k.y <= box[3]) words.push_back(word(i));
  }
  return BagOfWords::FromWords(words);
}

std::vector<uint8_t> PackedFeatures::Serialize() const {
  // Made in place at its final size: a bulk add serialises thousands of these per batch, and each
  // extra copy was another buffer of fresh pages to fault in.
  std::vector<uint8_t> out(kBlobHeaderBytes + bytes_.size() + signature_bytes_.size());
  const std::span<uint8_t> body = std::span(out).subspan(kBlobHeaderBytes);
  std::copy(bytes_.begin(), bytes_.end(), body.begin());
  std::copy(signature_bytes_.begin(), signature_bytes_.end(), body.begin() + static_cast<ptrdiff_t>(bytes_.size()));
  WriteBlobHeader(out.data(), !signature_bytes_.empty(), width_, height_, size(), io::Crc32(body));
  return out;
}

Result<PackedFeatures> PackedFeatures::Deserialize(std::span<const uint8_t> blob, const std::string& what) {
  auto corrupt = [&](const std::string& why) {
    return Fail(ErrorCode::kCorruptData, "damaged features of " + what + ": " + why);
  };
  if (blob.size() < kBlobHeaderBytes) return corrupt("record shorter than its header");
  if (!std::equal(kMagic, kMagic + 4, blob.begin())) return corrupt("not an oxbow feature record (bad magic)");
  io::ByteReader reader(blob.subspan(4), what);
  const uint32_t version = *reader.Get<uint32_t>();
  if (version != kBlobVersion && version != kSignedBlobVersion) {
    return Fail(ErrorCode::kIncompatible, "features of " + what + " have format version " +
                                              std::to_string(version) + "; this build reads versions " +
                                              std::to_string(kBlobVersion) + " and " +
                                              std::to_string(kSignedBlobVersion));
  }
  const size_t per_feature = kPackedFeatureBytes + (version == kSignedBlobVersion ? kSignatureBytes : 0);
  PackedFeatures out;
  out.width_ = *reader.Get<int32_t>();
  out.height_ = *reader.Get<int32_t>();
  const uint32_t count = *reader.Get<uint32_t>();
  const uint32_t crc = *reader.Get<uint32_t>();
  if (out.width_ <= 0 || out.height_ <= 0) return corrupt("non-positive image size");
  if (reader.remaining() != uint64_t{count} * per_feature) {
    return corrupt("length " + std::to_string(reader.remaining()) + " bytes does not match " +
                   std::to_string(count) + " features");
  }
  auto storage = std::make_shared<std::vector<uint8_t>>(reader.remaining());
  if (!reader.GetArray<uint8_t>(*storage)) return corrupt("truncated");
  if (io::Crc32(*storage) != crc) return corrupt("checksum mismatch");
  const std::span<const uint8_t> body(*storage);
  const size_t feature_bytes = size_t{count} * kPackedFeatureBytes;
  auto viewed = View(body.first(feature_bytes), body.subspan(feature_bytes), out.width_, out.height_, storage, what);
  if (!viewed) return viewed;
  for (size_t i = 1; i < viewed->size(); ++i) {
    if (viewed->word(i - 1) > viewed->word(i)) return corrupt("features not sorted by word");
  }
  return viewed;
}

namespace {
// madvise(MADV_WILLNEED) over the pages of [begin, end); a hint: errors are ignored.
void AdviseWillNeed(const uint8_t* begin, const uint8_t* end) {
  if (begin == end) return;
  static const auto page = static_cast<uintptr_t>(::sysconf(_SC_PAGESIZE));
  const uint8_t* first = begin - (reinterpret_cast<uintptr_t>(begin) & (page - 1));  // its page's start
  ::madvise(const_cast<uint8_t*>(first), static_cast<size_t>(end - first), MADV_WILLNEED);
}
}  // namespace

void PackedFeatures::WillNeed() const {
  const uint8_t* records_end = bytes_.data() + bytes_.size();
  if (!signature_bytes_.empty() && records_end == signature_bytes_.data()) {
    // A geometry file keeps an image's signatures right after its records: one call (each costs
    // several microseconds, a thousand per search).
    AdviseWillNeed(bytes_.data(), signature_bytes_.data() + signature_bytes_.size());
    return;
  }
  AdviseWillNeed(bytes_.data(), records_end);
  AdviseWillNeed(signature_bytes_.data(), signature_bytes_.data() + signature_bytes_.size());
}

Result<PackedFeatures> PackedFeatures::View(std::span<const uint8_t> bytes, std::span<const uint8_t> signature_bytes,
                                            int width, int height, std::shared_ptr<const void> storage,
                                            const std::string& what) {
  auto corrupt = [&](const std::string& why) {
    return Fail(ErrorCode::kCorruptData, "damaged features of " + what + ": " + why);
  };
  if (width <= 0 || height <= 0) return corrupt("non-positive image size");
  if (bytes.size() % kPackedFeatureBytes != 0) return corrupt("length is not a whole number of features");
  if (!signature_bytes.empty() && signature_bytes.size() != bytes.size() / kPackedFeatureBytes * kSignatureBytes) {
    return corrupt("signatures do not match the features");
  }
  PackedFeatures out;
  out.signature_bytes_ = signature_bytes;
  out.width_ = width;
  out.height_ = height;
  out.bytes_ = bytes;
  out.storage_ = std::move(storage);
  return out;
}

}  // namespace oxbow::index
