// Compact storage of an indexed image's features: visual word + keypoint geometry, 9 bytes per
// feature, sorted by word (so the image's bag of words and its word -> features lookup are one scan,
// and matching against a query sorted the same way is a merge join).
//
// Per feature (little-endian):
//   word         24 bits   visual word id (vocabularies up to 2^24 = 16.7M words)
//   x, y         16 bits   position quantised to the image size: q = round(x / width * 65535), so the
//                          error is at most width / 131070 px (0.008 px for a 1000 px image)
//   log-scale     8 bits   q = round((log2(scale) + 4) * 16), clamped to [0, 255]: sigma in
//                          [1/16, ~3800] px in steps of 2^(1/16) (4.4%)
//   orientation   8 bits   q = round(theta / (2 pi) * 256) mod 256: steps of 1.4 degrees
// The quantisation errors are far below the tolerances of the Hough verifier (30 degree, factor 2 bins,
// 12 px residual), so re-ranking with dequantised keypoints matches re-ranking with the originals.
//
// Optionally, per feature, its 64-bit Hamming-embedding signature (vocab::Vocabulary::Signatures),
// kept apart from the 9-byte records (in the same word order) so that code reading geometry only
// touches the same bytes as without them.
//
// Serialised form (the catalogue BLOB): magic "OXFT", u32 version, i32 width, i32 height, u32 count,
// u32 CRC-32 of everything after the header, then count * 9 bytes; version 2 (features with
// signatures) then count * 8 bytes of little-endian signatures. Features without signatures are
// written as version 1, readable by older builds. A BLOB whose magic, version, length or checksum is
// wrong is refused (kCorruptData / kIncompatible) with a message.
//
// Thread safety: immutable after construction; const members are safe from any number of threads.
#pragma once

#include <array>
#include <bit>
#include <cstdint>
#include <cstring>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "index/postings/inverted_file.h"
#include "sift/base/error.h"
#include "sift/types.h"

namespace oxbow::index {

inline constexpr size_t kPackedFeatureBytes = 9;
inline constexpr size_t kSignatureBytes = 8;
inline constexpr uint32_t kMaxPackedWord = (1u << 24) - 1;

class PackedFeatures {
 public:
  PackedFeatures() = default;

  // Packs keypoints[i] with words[i] and signatures[i] (same length, or no signatures; every word <=
  // kMaxPackedWord; OXBOW_CHECK) for an image of width x height pixels (> 0). Features are reordered
  // by (word, original order).
  static PackedFeatures Pack(std::span<const sift::Keypoint> keypoints, std::span<const uint32_t> words,
                             int width, int height, std::span<const uint64_t> signatures = {});

  // The size of Serialize()'s BLOB for `count` features, with or without signatures.
  static size_t BlobBytes(size_t count, bool with_signatures);
  // Pack(...) made directly in its serialised form: `blob` (BlobBytes(keypoints.size(),
  // !signatures.empty()) bytes; OXBOW_CHECK) receives exactly what Serialize() of Pack(...) gives, every
  // byte written, and the features returned view its body, kept alive by `owner` (what holds `blob`).
  // One buffer per image instead of two: a bulk add packs thousands per batch, and each buffer is
  // fresh pages to fault in.
  static PackedFeatures PackBlob(std::span<const sift::Keypoint> keypoints, std::span<const uint32_t> words,
                                 int width, int height, std::span<const uint64_t> signatures,
                                 std::span<uint8_t> blob, std::shared_ptr<const void> owner);

  size_t size() const { return bytes_.size() / kPackedFeatureBytes; }
  int width() const { return width_; }
  int height() const { return height_; }
  uint32_t word(size_t i) const {
    const uint8_t* p = bytes_.data() + i * kPackedFeatureBytes;
    return uint32_t{p[0]} | (uint32_t{p[1]} << 8) | (uint32_t{p[2]} << 16);
  }
  bool has_signatures() const { return !signature_bytes_.empty() || bytes_.empty(); }
  // The Hamming-embedding signature of feature i (has_signatures()).
  // Stored little-endian; one load (scoring and verification read it per pair of features).
  uint64_t signature(size_t i) const {
    static_assert(kSignatureBytes == sizeof(uint64_t));
    uint64_t v = 0;
    std::memcpy(&v, signature_bytes_.data() + i * kSignatureBytes, sizeof v);
    if constexpr (std::endian::native == std::endian::big) v = __builtin_bswap64(v);
    return v;
  }
  // The dequantised keypoint of feature i (response 0, octave 0).
  sift::Keypoint keypoint(size_t i) const;
  std::vector<sift::Keypoint> Keypoints() const;
  std::vector<uint32_t> Words() const;
  BagOfWords Bag() const;
  // Bag of the features whose dequantised position lies in the box x1,y1,x2,y2 (inclusive).
  BagOfWords BagInside(const std::array<float, 4>& box) const;

  // Tells the kernel these features will be read soon: for a view of a memory-mapped checkpoint file
  // whose pages are not in memory, their reads start now in the background, so that many images
  // asked for together are read with the disk's queue full instead of one page fault at a time (a
  // cold 1M-image index spent two seconds per search in such faults). A hint: nothing is read here
  // and errors are ignored; cheap (a system call per span) when the pages are already in memory.
  void WillNeed() const;

  // Bytes of the packed features (in memory, or in a mapped checkpoint file) + this object.
  size_t MemoryBytes() const { return bytes_.size() + signature_bytes_.size() + sizeof(*this); }

  // The packed features, count * kPackedFeatureBytes bytes (checkpoint files store them as they are).
  std::span<const uint8_t> bytes() const { return bytes_; }
  // The signatures, count * kSignatureBytes bytes, or none.
  std::span<const uint8_t> signature_bytes() const { return signature_bytes_; }
  // Features over `bytes` and `signature_bytes` (as bytes() and signature_bytes() gave them; the
  // latter may be empty) without copying; `storage` keeps them alive (e.g. a memory-mapped checkpoint
  // file). kCorruptData when the size or a length is wrong; the bytes are not read (a mapped file's
  // pages stay on disk until used), so their source must vouch for them.
  [[nodiscard]] static Result<PackedFeatures> View(std::span<const uint8_t> bytes,
                                                   std::span<const uint8_t> signature_bytes, int width, int height,
                                                   std::shared_ptr<const void> storage, const std::string& what);

  std::vector<uint8_t> Serialize() const;
  // `what` names the source in error messages (e.g. "image 'foo' in /idx/catalogue.sqlite").
  [[nodiscard]] static Result<PackedFeatures> Deserialize(std::span<const uint8_t> blob, const std::string& what);

 private:
  int width_ = 0;
  int height_ = 0;
  std::shared_ptr<const void> storage_;  // owns what bytes_ views (a vector or a mapped file)
  std::span<const uint8_t> bytes_;
  std::span<const uint8_t> signature_bytes_;
};

}  // namespace oxbow::index
