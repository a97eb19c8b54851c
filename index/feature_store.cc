#include "index/feature_store.h"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <numeric>

#include "sift/base/binary_io.h"

namespace oxbow::index {
namespace {

constexpr char kMagic[4] = {'O', 'X', 'F', 'T'};
constexpr uint32_t kBlobVersion = 1;
constexpr size_t kBlobHeaderBytes = 4 + 4 * 5;

inline uint16_t QuantizeCoordinate(float v, int size) {
  const double q = std::round(std::clamp(static_cast<double>(v) / size, 0.0, 1.0) * 65535.0);
  return static_cast<uint16_t>(q);
}

}  // namespace

PackedFeatures PackedFeatures::Pack(std::span<const sift::Keypoint> keypoints, std::span<const uint32_t> words,
                                    int width, int height) {
  OXBOW_CHECK(keypoints.size() == words.size());
  OXBOW_CHECK(width > 0 && height > 0);
  // By word, ties in input order: sorting (word, position) keys as integers is that stable order and
  // several times faster than a stable sort of positions through the words.
  std::vector<uint64_t> order(words.size());
  for (size_t i = 0; i < words.size(); ++i) order[i] = (static_cast<uint64_t>(words[i]) << 32) | i;
  std::sort(order.begin(), order.end());
  PackedFeatures out;
  out.width_ = width;
  out.height_ = height;
  auto storage = std::make_shared<std::vector<uint8_t>>(words.size() * kPackedFeatureBytes);
  out.bytes_ = *storage;
  out.storage_ = storage;
  uint8_t* p = storage->data();
  for (const uint64_t key : order) {
    const auto i = static_cast<uint32_t>(key);
    const uint32_t w = words[i];
    OXBOW_CHECK(w <= kMaxPackedWord, "word id does not fit 24 bits");
    const sift::Keypoint& k = keypoints[i];
    const uint16_t x = QuantizeCoordinate(k.x, width), y = QuantizeCoordinate(k.y, height);
    const double log_scale = k.scale > 0 ? std::log2(static_cast<double>(k.scale)) : -4.0;
    const int s = static_cast<int>(std::clamp(std::round((log_scale + 4.0) * 16.0), 0.0, 255.0));
    double turns = static_cast<double>(k.orientation) / (2 * std::numbers::pi);
    if (!std::isfinite(turns)) turns = 0;
    turns -= std::floor(turns);
    const int o = static_cast<int>(std::lround(turns * 256.0)) & 255;
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
  }
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
  io::ByteWriter writer;
  for (char c : kMagic) writer.Put<char>(c);
  writer.Put<uint32_t>(kBlobVersion);
  writer.Put<int32_t>(width_);
  writer.Put<int32_t>(height_);
  writer.Put<uint32_t>(static_cast<uint32_t>(size()));
  writer.Put<uint32_t>(io::Crc32(bytes_));
  writer.PutArray<uint8_t>(bytes_);
  return writer.Release();
}

Result<PackedFeatures> PackedFeatures::Deserialize(std::span<const uint8_t> blob, const std::string& what) {
  auto corrupt = [&](const std::string& why) {
    return Fail(ErrorCode::kCorruptData, "damaged features of " + what + ": " + why);
  };
  if (blob.size() < kBlobHeaderBytes) return corrupt("record shorter than its header");
  if (!std::equal(kMagic, kMagic + 4, blob.begin())) return corrupt("not an oxbow feature record (bad magic)");
  io::ByteReader reader(blob.subspan(4), what);
  const uint32_t version = *reader.Get<uint32_t>();
  if (version != kBlobVersion) {
    return Fail(ErrorCode::kIncompatible, "features of " + what + " have format version " +
                                              std::to_string(version) + "; this build reads version " +
                                              std::to_string(kBlobVersion));
  }
  PackedFeatures out;
  out.width_ = *reader.Get<int32_t>();
  out.height_ = *reader.Get<int32_t>();
  const uint32_t count = *reader.Get<uint32_t>();
  const uint32_t crc = *reader.Get<uint32_t>();
  if (out.width_ <= 0 || out.height_ <= 0) return corrupt("non-positive image size");
  if (reader.remaining() != uint64_t{count} * kPackedFeatureBytes) {
    return corrupt("length " + std::to_string(reader.remaining()) + " bytes does not match " +
                   std::to_string(count) + " features");
  }
  auto storage = std::make_shared<std::vector<uint8_t>>(reader.remaining());
  if (!reader.GetArray<uint8_t>(*storage)) return corrupt("truncated");
  if (io::Crc32(*storage) != crc) return corrupt("checksum mismatch");
  auto viewed = View(*storage, out.width_, out.height_, storage, what);
  if (!viewed) return viewed;
  for (size_t i = 1; i < viewed->size(); ++i) {
    if (viewed->word(i - 1) > viewed->word(i)) return corrupt("features not sorted by word");
  }
  return viewed;
}

Result<PackedFeatures> PackedFeatures::View(std::span<const uint8_t> bytes, int width, int height,
                                            std::shared_ptr<const void> storage, const std::string& what) {
  auto corrupt = [&](const std::string& why) {
    return Fail(ErrorCode::kCorruptData, "damaged features of " + what + ": " + why);
  };
  if (width <= 0 || height <= 0) return corrupt("non-positive image size");
  if (bytes.size() % kPackedFeatureBytes != 0) return corrupt("length is not a whole number of features");
  PackedFeatures out;
  out.width_ = width;
  out.height_ = height;
  out.bytes_ = bytes;
  out.storage_ = std::move(storage);
  return out;
}

}  // namespace oxbow::index
