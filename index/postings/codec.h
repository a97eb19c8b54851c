// The posting codec: how one posting (an image number and its term frequency tf) is coded in a word's
// list, and a cursor that reads a list a posting at a time. The lists of a segment (segment.h) are
// these codes back to back; the checkpoint files (serialisation.h) store them as they are.
//
// Format 2 (written and read): a 16-bit little-endian unit (g << 1) | (tf > 1), where g is the gap
// (image - previous image in the list; the first counts from the segment's first image) when it is
// below kGapEscape, and kGapEscape otherwise, then followed by the gap in 4 little-endian bytes; then,
// when tf > 1, varint(tf - 2). Gaps in a list are below 2^15 unless the word is in fewer than about 1
// of 32768 images, so a scan reads one fixed-size unit per posting whose length does not depend on its
// value: no data-dependent branch per posting. With about one posting per feature this is about 2 bytes
// a feature.
//
// Format 1 (read only, re-coded at load): varint(gap << 1 | (tf > 1)), then varint(tf - 2) when tf > 1.
// Its 1-3 bytes per gap cost 2-3x format 2's scan time.
//
// Everything here is inline: the decoder is the innermost loop of scoring and of every pass over the
// postings. Decoding trusts its bytes (a checksummed file or this process's own) except
// ForEachFormat1Posting, which checks bounds.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <vector>

namespace oxbow::index::postings {

inline size_t VarintSize(uint64_t v) {
  size_t n = 1;
  while (v >= 128) {
    v >>= 7;
    ++n;
  }
  return n;
}

inline uint8_t* PutVarint(uint8_t* p, uint64_t v) {
  while (v >= 128) {
    *p++ = static_cast<uint8_t>(v | 128);
    v >>= 7;
  }
  *p++ = static_cast<uint8_t>(v);
  return p;
}

inline uint64_t GetVarint(const uint8_t*& p) {
  uint64_t v = *p++;
  if (v < 128) return v;
  v &= 127;
  int shift = 7;
  while (true) {
    const uint64_t b = *p++;
    v |= (b & 127) << shift;
    if (b < 128) return v;
    shift += 7;
  }
}

// The unit's gap field at this value means "the gap follows in 4 bytes".
inline constexpr uint32_t kGapEscape = 0x7FFF;

inline uint32_t Load16(const uint8_t* p) { return uint32_t{p[0]} | (uint32_t{p[1]} << 8); }
inline uint32_t Load32(const uint8_t* p) {
  return uint32_t{p[0]} | (uint32_t{p[1]} << 8) | (uint32_t{p[2]} << 16) | (uint32_t{p[3]} << 24);
}

// Bytes of the posting (gap, tf), tf >= 1.
inline size_t PostingSize(uint32_t gap, uint32_t tf) {
  return 2 + (gap >= kGapEscape ? 4 : 0) + (tf > 1 ? VarintSize(tf - 2) : 0);
}

// Codes the posting (gap, tf) at p (PostingSize bytes of room) and returns the end of its code.
inline uint8_t* PutPosting(uint8_t* p, uint32_t gap, uint32_t tf) {
  const uint32_t g = std::min(gap, kGapEscape);
  const uint32_t unit = (g << 1) | (tf > 1 ? 1 : 0);
  *p++ = static_cast<uint8_t>(unit);
  *p++ = static_cast<uint8_t>(unit >> 8);
  if (g == kGapEscape) {
    for (int k = 0; k < 4; ++k) *p++ = static_cast<uint8_t>(gap >> (8 * k));
  }
  if (tf > 1) p = PutVarint(p, tf - 2);
  return p;
}

// Appends the code of the posting (gap, tf) to *out.
inline void PutPosting(std::vector<uint8_t>* out, uint32_t gap, uint32_t tf) {
  const size_t at = out->size();
  out->resize(at + PostingSize(gap, tf));
  PutPosting(out->data() + at, gap, tf);
}

// Decodes the posting at p (trusted bytes) and moves past it.
inline void GetPosting(const uint8_t*& p, uint32_t* gap, uint32_t* tf) {
  const uint32_t unit = Load16(p);
  p += 2;
  *gap = unit >> 1;
  if (*gap == kGapEscape) [[unlikely]] {
    *gap = Load32(p);
    p += 4;
  }
  *tf = 1;
  if ((unit & 1) != 0) [[unlikely]] *tf = static_cast<uint32_t>(GetVarint(p)) + 2;
}

// One word's list in one segment, read a posting at a time, for the scans that go through a segment a
// block of image numbers at a time with a cursor per list (the statistics' refresh, scoring). Start it
// at the segment's first image, then Advance() decodes the first posting: `image` and `tf` are those of
// the posting decoded last, and `image` is UINT32_MAX once the list is done.
struct PostingCursor {
  const uint8_t* p = nullptr;
  const uint8_t* end = nullptr;
  uint32_t image = 0;
  uint32_t tf = 1;

  void Advance() {
    if (p >= end) {
      image = std::numeric_limits<uint32_t>::max();
      return;
    }
    uint32_t gap = 0;
    GetPosting(p, &gap, &tf);
    image += gap;
  }
};

// Calls fn(gap, tf) for every posting of the format-1 list [p, end), checking bounds: false (after the
// postings before it) at a varint that runs past `end` or a value that does not fit 32 bits.
template <typename Fn>
bool ForEachFormat1Posting(const uint8_t* p, const uint8_t* end, Fn&& fn) {
  const auto varint = [&](uint64_t* v) {
    *v = 0;
    for (int shift = 0; shift < 64 && p < end; shift += 7) {
      const uint8_t b = *p++;
      *v |= uint64_t{b & 127u} << shift;
      if (b < 128) return true;
    }
    return false;
  };
  while (p < end) {
    uint64_t v = 0, extra = 0;
    if (!varint(&v) || (v >> 1) > std::numeric_limits<uint32_t>::max()) return false;
    if ((v & 1) != 0 && (!varint(&extra) || extra > std::numeric_limits<uint32_t>::max() - 2)) return false;
    fn(static_cast<uint32_t>(v >> 1), (v & 1) != 0 ? static_cast<uint32_t>(extra) + 2 : 1u);
  }
  return true;
}

}  // namespace oxbow::index::postings
