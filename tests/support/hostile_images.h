// Hostile image files for tests and fuzz seeds: progressive JPEGs with many scans, TIFFs with
// repeated dimension tags or a strip that does not decompress. Built byte by byte or with libjpeg, so
// that they have exactly the shape under test. Header-only; libjpeg is linked through oxbow_sift.
#pragma once

#include <jpeglib.h>

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <stdexcept>
#include <utility>
#include <vector>

namespace oxbow::sift::testing {

using Bytes = std::vector<uint8_t>;

// A valid progressive grey JPEG of `grey` (width x height samples, row-major) with exactly `scans` scans,
// 2 <= scans <= 128: the DC coefficient in two scans (first and refinement), then each AC coefficient on
// its own, first scans before refinements. Every scan is legal and carries data, so a decoder reads them
// all without a warning; only their number makes the file costly.
inline Bytes ProgressiveJpegWithScans(const Bytes& grey, int width, int height, int scans) {
  if (scans < 2 || scans > 128 || grey.size() != static_cast<size_t>(width) * static_cast<size_t>(height)) {
    throw std::invalid_argument("ProgressiveJpegWithScans: 2..128 scans of width*height samples");
  }
  std::vector<jpeg_scan_info> script;
  script.push_back({1, {0}, 0, 0, 0, 1});
  script.push_back({1, {0}, 0, 0, 1, 0});
  for (int k = 1; k <= 63; ++k) script.push_back({1, {0}, k, k, 0, 1});
  for (int k = 1; k <= 63; ++k) script.push_back({1, {0}, k, k, 1, 0});
  script.resize(static_cast<size_t>(scans));

  jpeg_compress_struct cinfo;
  jpeg_error_mgr errors;
  cinfo.err = jpeg_std_error(&errors);  // errors here are bugs of this function: libjpeg exits
  jpeg_create_compress(&cinfo);
  unsigned char* buffer = nullptr;
  unsigned long size = 0;
  jpeg_mem_dest(&cinfo, &buffer, &size);
  cinfo.image_width = static_cast<JDIMENSION>(width);
  cinfo.image_height = static_cast<JDIMENSION>(height);
  cinfo.input_components = 1;
  cinfo.in_color_space = JCS_GRAYSCALE;
  jpeg_set_defaults(&cinfo);
  jpeg_set_quality(&cinfo, 90, TRUE);
  cinfo.scan_info = script.data();
  cinfo.num_scans = scans;
  jpeg_start_compress(&cinfo, TRUE);
  while (cinfo.next_scanline < cinfo.image_height) {
    JSAMPROW row = const_cast<uint8_t*>(grey.data()) + static_cast<size_t>(cinfo.next_scanline) * static_cast<size_t>(width);
    jpeg_write_scanlines(&cinfo, &row, 1);
  }
  jpeg_finish_compress(&cinfo);
  Bytes out(buffer, buffer + size);
  jpeg_destroy_compress(&cinfo);
  std::free(buffer);
  return out;
}

// `jpeg` with its first baseline or progressive frame header rewritten to declare width x height; the
// data stays as it was. Unchanged when there is no such header.
inline Bytes WithJpegFrameSize(Bytes jpeg, uint16_t width, uint16_t height) {
  for (size_t i = 2; i + 9 < jpeg.size(); ++i) {
    if (jpeg[i] == 0xFF && (jpeg[i + 1] == 0xC0 || jpeg[i + 1] == 0xC2)) {
      jpeg[i + 5] = static_cast<uint8_t>(height >> 8);
      jpeg[i + 6] = static_cast<uint8_t>(height);
      jpeg[i + 7] = static_cast<uint8_t>(width >> 8);
      jpeg[i + 8] = static_cast<uint8_t>(width);
      break;
    }
  }
  return jpeg;
}

// A scan flood: the headers of a small progressive grey JPEG with its frame declaring
// width x height, then `scans` empty DC scans (10 bytes each: an SOS segment and no data), then EOI.
// libjpeg walks every block of the frame for each scan.
inline Bytes JpegOfEmptyScans(uint16_t width, uint16_t height, int scans) {
  Bytes jpeg = WithJpegFrameSize(ProgressiveJpegWithScans(Bytes(16 * 16, 128), 16, 16, 2), width, height);
  size_t sos = 2;
  while (sos + 4 <= jpeg.size() && !(jpeg[sos] == 0xFF && jpeg[sos + 1] == 0xDA))
    sos += 2 + ((static_cast<size_t>(jpeg[sos + 2]) << 8) | jpeg[sos + 3]);
  jpeg.resize(sos);
  // SOS, length 8, one component (id 1, DC table 0), Ss = Se = 0, Ah = Al = 0.
  static constexpr uint8_t kEmptyScan[] = {0xFF, 0xDA, 0x00, 0x08, 0x01, 0x01, 0x00, 0x00, 0x00, 0x00};
  for (int i = 0; i < scans; ++i) jpeg.insert(jpeg.end(), std::begin(kEmptyScan), std::end(kEmptyScan));
  jpeg.insert(jpeg.end(), {0xFF, 0xD9});
  return jpeg;
}

// One entry of a classic little-endian TIFF directory: tag, type (3 SHORT, 4 LONG), count 1, value.
struct TiffEntry {
  uint16_t tag;
  uint16_t type;
  uint32_t value;
};

// A little-endian TIFF of one strip: header, `strip` at offset 8, then one directory holding `entries`
// in the given order plus StripOffsets (273) and StripByteCounts (279) inserted in tag order.
inline Bytes HandMadeTiff(std::vector<TiffEntry> entries, const Bytes& strip) {
  entries.push_back({273, 4, 8});
  entries.push_back({279, 4, static_cast<uint32_t>(strip.size())});
  std::stable_sort(entries.begin(), entries.end(), [](const TiffEntry& a, const TiffEntry& b) { return a.tag < b.tag; });
  auto put16 = [](Bytes& out, uint32_t v) { out.insert(out.end(), {static_cast<uint8_t>(v), static_cast<uint8_t>(v >> 8)}); };
  auto put32 = [&](Bytes& out, uint32_t v) {
    put16(out, v & 0xFFFF);
    put16(out, v >> 16);
  };
  Bytes tiff = {'I', 'I', 42, 0};
  const uint32_t ifd = 8 + static_cast<uint32_t>((strip.size() + 1) & ~size_t{1});  // word-aligned
  put32(tiff, ifd);
  tiff.insert(tiff.end(), strip.begin(), strip.end());
  tiff.resize(ifd, 0);
  put16(tiff, static_cast<uint32_t>(entries.size()));
  for (const TiffEntry& e : entries) {
    put16(tiff, e.tag);
    put16(tiff, e.type);
    put32(tiff, 1);
    if (e.type == 3) {
      put16(tiff, e.value);
      put16(tiff, 0);
    } else {
      put32(tiff, e.value);
    }
  }
  put32(tiff, 0);  // no next directory
  return tiff;
}

// The directory entries of an 8-bit grey TIFF of one strip with `compression` (1 none, 8 deflate).
inline std::vector<TiffEntry> GreyTiffEntries(uint32_t width, uint32_t height, uint16_t compression) {
  return {{256, 4, width}, {257, 4, height}, {258, 3, 8}, {259, 3, compression}, {262, 3, 1}, {277, 3, 1}, {278, 4, height}};
}

// ImageWidth and ImageLength twice, `first` then `last` (width, height). libtiff uses
// the first entries and ignores the repeats. The strip holds the samples of the smaller of the two.
inline Bytes TiffWithRepeatedDimensions(std::pair<uint32_t, uint32_t> first, std::pair<uint32_t, uint32_t> last) {
  std::vector<TiffEntry> entries = GreyTiffEntries(first.first, first.second, 1);
  entries.push_back({256, 4, last.first});
  entries.push_back({257, 4, last.second});
  const uint64_t samples = std::min(uint64_t{first.first} * first.second, uint64_t{last.first} * last.second);
  return HandMadeTiff(entries, Bytes(static_cast<size_t>(samples), 128));
}

// A deflate-compressed grey TIFF whose strip is not deflate data.
inline Bytes TiffWithGarbageDeflateStrip(uint32_t width, uint32_t height) {
  Bytes garbage(256);
  for (size_t i = 0; i < garbage.size(); ++i) garbage[i] = static_cast<uint8_t>(i * 151 + 17);
  return HandMadeTiff(GreyTiffEntries(width, height, 8), garbage);
}

}  // namespace oxbow::sift::testing
