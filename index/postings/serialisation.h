// The checkpoint form of an inverted file, field by field. Written by InvertedFile::Serialize,
// SerializeHead and SerializeSegment, read by InvertedFile::Deserialize (inverted_file.h), all in
// serialisation.cc. Checksums are the caller's: each file's XXH3-64 is in the checkpoint manifest
// (storage/checkpoint.h). All integers little-endian.
//
// Postings file (postings-<generation>.oxck), magic "OXIF":
//   char[4] "OXIF", u32 version, u32 byte-order mark 0x01020304, u64 vocabulary size, u8 sqrt_tf;
//   u64 N of the last refresh, u64 changes since it, u64 live images, u64 live features, u64 stored
//   postings, u64 postings of removed images not yet merged away;
//   u64 n + u32[n] document frequency per word now; u64 n + u32[n] at the last refresh;
//   u64 n + ImageState[n] per image number (double a, b, c; u32 live, features: 32 bytes);
//   u64 number of segments, then per segment
//     version 1 and 2: a segment record;
//     version 3 (a head): u64 length + the name of the segment's own file (< 4 KB).
// Segment record: u32 first image, u32 end image, u8 dense, u64 postings, u64 n + u32[n] words (sparse
//   layout), u64 n + u64[n] list offsets, u64 n + u8[n] the coded postings (codec.h).
// Segment file (segment-<generation>-<k>.oxck), magic "OXIS": char[4] "OXIS", u32 version 3, u32
//   byte-order mark, u64 vocabulary size, one segment record.
//
// Versions: 1, postings coded as varints (codec.h, format 1), re-coded at load; 2, postings in 16-bit
// units, every segment inside the file (Serialize writes it); 3, a head naming a file per segment
// (SerializeHead), so that a checkpoint writes only the segments new since the last one.
#pragma once

#include <cstdint>

namespace oxbow::index::postings {

inline constexpr char kFileMagic[4] = {'O', 'X', 'I', 'F'};
inline constexpr char kSegmentMagic[4] = {'O', 'X', 'I', 'S'};
inline constexpr uint32_t kFileVersion = 2;  // the whole form (Serialize)
inline constexpr uint32_t kHeadVersion = 3;  // a head and segment files (SerializeHead, SerializeSegment)
inline constexpr uint32_t kOldestReadableVersion = 1;
inline constexpr uint32_t kByteOrderMark = 0x01020304;

}  // namespace oxbow::index::postings
