#include "sift/image.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdarg>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <functional>
#include <memory>
#include <set>
#include <string_view>
#include <utility>

#include <sys/stat.h>

#include <tiffio.h>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>  // the IMREAD_ flags only; the library is loaded by opencv_codecs.cc
#include <opencv2/imgproc.hpp>

#include "sift/base/binary_io.h"
#include "sift/image_decoders.h"
#include "sift/opencv_codecs.h"

namespace oxbow::sift {
namespace {

// ---- Small readers over the header bytes (all bounds-checked by the callers). ----------------------

uint32_t Be16(const uint8_t* p) { return (uint32_t{p[0]} << 8) | p[1]; }
uint32_t Be32(const uint8_t* p) { return (uint32_t{p[0]} << 24) | (uint32_t{p[1]} << 16) | (uint32_t{p[2]} << 8) | p[3]; }
uint32_t Le16(const uint8_t* p) { return (uint32_t{p[1]} << 8) | p[0]; }
uint32_t Le24(const uint8_t* p) { return (uint32_t{p[2]} << 16) | (uint32_t{p[1]} << 8) | p[0]; }
uint32_t Le32(const uint8_t* p) { return (uint32_t{p[3]} << 24) | (uint32_t{p[2]} << 16) | (uint32_t{p[1]} << 8) | p[0]; }

bool StartsWith(std::span<const uint8_t> bytes, std::string_view prefix) {
  return bytes.size() >= prefix.size() && std::memcmp(bytes.data(), prefix.data(), prefix.size()) == 0;
}

std::unexpected<Error> Invalid(std::string message) { return Fail(ErrorCode::kInvalidImage, std::move(message)); }

ImageFormat SniffFormat(std::span<const uint8_t> b) {
  if (b.size() >= 3 && b[0] == 0xFF && b[1] == 0xD8 && b[2] == 0xFF) return ImageFormat::kJpeg;
  if (StartsWith(b, "\x89PNG\r\n\x1a\n")) return ImageFormat::kPng;
  if (b.size() >= 2 && b[0] == 'P' && b[1] >= '1' && b[1] <= '6') return ImageFormat::kPnm;
  if (b.size() >= 12 && StartsWith(b, "RIFF") && std::memcmp(b.data() + 8, "WEBP", 4) == 0) return ImageFormat::kWebp;
  if (StartsWith(b, std::string_view("II*\0", 4)) || StartsWith(b, std::string_view("MM\0*", 4))) return ImageFormat::kTiff;
  if (StartsWith(b, "BM")) return ImageFormat::kBmp;
  return ImageFormat::kUnknown;
}

// JPEG: walk the marker segments from SOI up to the first start-of-frame, which holds the size.
// Also reports where the scan data starts, for the truncation check.
Result<ImageHeaderInfo> JpegHeader(std::span<const uint8_t> b, size_t* scan_start) {
  size_t pos = 2;
  while (true) {
    while (pos < b.size() && b[pos] != 0xFF) ++pos;  // tolerate garbage between segments as libjpeg does
    while (pos < b.size() && b[pos] == 0xFF) ++pos;  // fill bytes
    if (pos >= b.size()) return Invalid("JPEG ends before its frame header (truncated or not a JPEG)");
    const uint8_t marker = b[pos++];
    if (marker == 0xD8 || (marker >= 0xD0 && marker <= 0xD7) || marker == 0x01) continue;  // no length
    if (marker == 0xD9) return Invalid("JPEG has no frame header before its end marker");
    if (pos + 2 > b.size()) return Invalid("JPEG segment header is truncated");
    const uint32_t length = Be16(b.data() + pos);
    if (length < 2 || pos + length > b.size()) return Invalid("JPEG segment runs past the end of the data (truncated)");
    const bool is_sof = marker >= 0xC0 && marker <= 0xCF && marker != 0xC4 && marker != 0xC8 && marker != 0xCC;
    if (is_sof) {
      if (length < 8) return Invalid("JPEG frame header is too short");
      ImageHeaderInfo info;
      info.format = ImageFormat::kJpeg;
      info.height = Be16(b.data() + pos + 3);
      info.width = Be16(b.data() + pos + 5);
      // The scan follows later; find SOS for the truncation check.
      size_t p = pos + length;
      *scan_start = b.size();
      while (p + 4 <= b.size()) {
        if (b[p] != 0xFF) {
          ++p;
          continue;
        }
        const uint8_t m = b[p + 1];
        if (m == 0xFF) {
          ++p;
          continue;
        }
        if (m == 0xDA) {
          *scan_start = p;
          break;
        }
        if (m == 0xD8 || (m >= 0xD0 && m <= 0xD7) || m == 0x01) {
          p += 2;
          continue;
        }
        p += 2 + Be16(b.data() + p + 2);
      }
      return info;
    }
    pos += length;
  }
}

Result<ImageHeaderInfo> PngHeader(std::span<const uint8_t> b) {
  if (b.size() < 33) return Invalid("PNG is shorter than its signature and header chunk (truncated)");
  if (Be32(b.data() + 8) != 13 || std::memcmp(b.data() + 12, "IHDR", 4) != 0)
    return Invalid("PNG does not start with an IHDR chunk (corrupt)");
  ImageHeaderInfo info;
  info.format = ImageFormat::kPng;
  info.width = Be32(b.data() + 16);
  info.height = Be32(b.data() + 20);
  const uint32_t crc = io::Crc32(b.subspan(12, 17));
  if (crc != Be32(b.data() + 29)) return Invalid("PNG header chunk fails its CRC (corrupt)");
  return info;
}

// PNM header: magic, then width, height (and maxval except for P1/P4), separated by whitespace and
// '#' comments. `data_start` receives the offset of the pixel data.
Result<ImageHeaderInfo> PnmHeader(std::span<const uint8_t> b, uint32_t* maxval, size_t* data_start) {
  size_t pos = 2;
  const int kind = b[1] - '0';
  const int fields = (kind == 1 || kind == 4) ? 2 : 3;
  uint64_t values[3] = {0, 0, 1};
  for (int f = 0; f < fields; ++f) {
    while (pos < b.size()) {
      if (b[pos] == '#') {
        while (pos < b.size() && b[pos] != '\n' && b[pos] != '\r') ++pos;
      } else if (std::isspace(b[pos])) {
        ++pos;
      } else {
        break;
      }
    }
    if (pos >= b.size() || !std::isdigit(b[pos])) return Invalid("PNM header is truncated or malformed");
    uint64_t v = 0;
    while (pos < b.size() && std::isdigit(b[pos])) {
      v = v * 10 + static_cast<uint64_t>(b[pos++] - '0');
      if (v > (uint64_t{1} << 40)) return Invalid("PNM header declares an absurd size");
    }
    values[f] = v;
  }
  if (pos >= b.size() || !std::isspace(b[pos])) return Invalid("PNM header is truncated or malformed");
  *data_start = pos + 1;
  *maxval = static_cast<uint32_t>(std::min<uint64_t>(values[2], 0xFFFFFFFFu));
  if (fields == 3 && (values[2] == 0 || values[2] > 65535)) return Invalid("PNM maxval must be in [1, 65535]");
  ImageHeaderInfo info;
  info.format = ImageFormat::kPnm;
  info.width = values[0];
  info.height = values[1];
  return info;
}

Result<ImageHeaderInfo> WebpHeader(std::span<const uint8_t> b) {
  if (b.size() < 30) return Invalid("WebP is shorter than its header (truncated)");
  ImageHeaderInfo info;
  info.format = ImageFormat::kWebp;
  const uint8_t* chunk = b.data() + 12;
  if (std::memcmp(chunk, "VP8X", 4) == 0) {
    info.width = uint64_t{Le24(b.data() + 24)} + 1;
    info.height = uint64_t{Le24(b.data() + 27)} + 1;
  } else if (std::memcmp(chunk, "VP8L", 4) == 0) {
    if (b[20] != 0x2F) return Invalid("WebP lossless header has a wrong signature (corrupt)");
    const uint32_t bits = Le32(b.data() + 21);
    info.width = (bits & 0x3FFF) + 1;
    info.height = ((bits >> 14) & 0x3FFF) + 1;
  } else if (std::memcmp(chunk, "VP8 ", 4) == 0) {
    if (b[23] != 0x9D || b[24] != 0x01 || b[25] != 0x2A) return Invalid("WebP lossy header has a wrong start code (corrupt)");
    info.width = Le16(b.data() + 26) & 0x3FFF;
    info.height = Le16(b.data() + 28) & 0x3FFF;
  } else {
    return Invalid("WebP has an unknown first chunk (corrupt)");
  }
  return info;
}

Result<ImageHeaderInfo> TiffHeader(std::span<const uint8_t> b) {
  const bool le = b[0] == 'I';
  auto u16 = [&](size_t at) { return le ? Le16(b.data() + at) : Be16(b.data() + at); };
  auto u32 = [&](size_t at) { return le ? Le32(b.data() + at) : Be32(b.data() + at); };
  if (b.size() < 8) return Invalid("TIFF is shorter than its header (truncated)");
  const uint64_t ifd = u32(4);
  if (ifd + 2 > b.size()) return Invalid("TIFF directory offset points past the end (truncated)");
  const uint32_t entries = u16(ifd);
  if (ifd + 2 + uint64_t{entries} * 12 > b.size()) return Invalid("TIFF directory runs past the end (truncated)");
  ImageHeaderInfo info;
  info.format = ImageFormat::kTiff;
  // libtiff ignores every repeat of a tag after its first entry, and it is libtiff that decodes: a file
  // with ImageWidth 32000 then ImageWidth 1 is a 32000-pixel-wide image, so the first entry counts here too.
  bool seen_width = false, seen_height = false;
  for (uint32_t e = 0; e < entries; ++e) {
    const size_t at = ifd + 2 + e * 12;
    const uint32_t tag = u16(at), type = u16(at + 2);
    const uint64_t value = type == 3 ? u16(at + 8) : type == 4 ? u32(at + 8) : 0;
    if (tag == 256 && !seen_width) {
      info.width = value;
      seen_width = true;
    }
    if (tag == 257 && !seen_height) {
      info.height = value;
      seen_height = true;
    }
  }
  if (info.width == 0 || info.height == 0) return Invalid("TIFF directory has no image width/length (corrupt)");
  return info;
}

Result<ImageHeaderInfo> BmpHeader(std::span<const uint8_t> b) {
  if (b.size() < 26) return Invalid("BMP is shorter than its header (truncated)");
  const uint32_t dib = Le32(b.data() + 14);
  ImageHeaderInfo info;
  info.format = ImageFormat::kBmp;
  if (dib == 12) {
    info.width = Le16(b.data() + 18);
    info.height = Le16(b.data() + 20);
  } else if (dib >= 40) {
    info.width = static_cast<uint64_t>(std::abs(static_cast<int64_t>(static_cast<int32_t>(Le32(b.data() + 18)))));
    info.height = static_cast<uint64_t>(std::abs(static_cast<int64_t>(static_cast<int32_t>(Le32(b.data() + 22)))));
  } else {
    return Invalid("BMP has an unknown header size (corrupt)");
  }
  return info;
}

// Checks that the encoded data is complete (cheap, format-specific; see image.h).
Status CheckComplete(std::span<const uint8_t> b, const ImageHeaderInfo& info, size_t jpeg_scan_start, uint32_t pnm_maxval,
                     size_t pnm_data_start) {
  switch (info.format) {
    case ImageFormat::kJpeg: {
      if (jpeg_scan_start >= b.size()) return Invalid("JPEG has no scan data (truncated)");
      // In entropy-coded data 0xFF is always stuffed (FF 00) or a restart marker, so FF D9 after the
      // start of scan is the end-of-image marker; trailing bytes after it are allowed.
      for (size_t i = b.size() - 1; i > jpeg_scan_start; --i)
        if (b[i] == 0xD9 && b[i - 1] == 0xFF) return Ok();
      return Invalid("JPEG has no end-of-image marker (truncated)");
    }
    case ImageFormat::kPng: {
      // The IEND chunk: length 0, "IEND", its CRC; trailing bytes after it are allowed.
      static constexpr uint8_t kIend[12] = {0, 0, 0, 0, 'I', 'E', 'N', 'D', 0xAE, 0x42, 0x60, 0x82};
      if (b.size() < 12 || std::search(b.begin() + 33, b.end(), std::begin(kIend), std::end(kIend)) == b.end())
        return Invalid("PNG has no IEND chunk (truncated)");
      return Ok();
    }
    case ImageFormat::kPnm: {
      const int kind = b[1] - '0';
      if (kind < 4) return Ok();  // ASCII variants: the decoder reports missing samples itself
      const uint64_t channels = kind == 6 ? 3 : 1;
      const uint64_t bytes_per_sample = pnm_maxval > 255 ? 2 : 1;
      const uint64_t need = kind == 4 ? (info.width + 7) / 8 * info.height
                                      : info.width * info.height * channels * bytes_per_sample;
      if (b.size() - pnm_data_start < need) return Invalid("PNM pixel data is shorter than its header declares (truncated)");
      return Ok();
    }
    case ImageFormat::kWebp: {
      const uint64_t riff = Le32(b.data() + 4);
      if (b.size() < riff + 8) return Invalid("WebP is shorter than its RIFF header declares (truncated)");
      return Ok();
    }
    default:
      return Ok();
  }
}

// Over the pixel limit: refused before any pixel is allocated.
Status CheckPixelLimit(ImageFormat format, uint64_t width, uint64_t height, const DecodeOptions& options) {
  // The decoders' own limits on a side: libpng's 1,000,000 pixels (in the decoder here and in OpenCV's,
  // which also makes thumbnails) and OpenCV's 2^20 (CV_IO_MAX_IMAGE_WIDTH / HEIGHT, an assertion inside
  // it). A strip within the pixel limit but longer is refused as too large, not reported as corrupt data.
  const uint64_t max_side = format == ImageFormat::kPng ? 1000000 : uint64_t{1} << 20;
  if (std::max(width, height) > max_side) {
    return Fail(ErrorCode::kImageTooLarge, std::string(ImageFormatName(format)) + " header declares " +
                                               std::to_string(width) + "x" + std::to_string(height) + " pixels: a side over " +
                                               std::to_string(max_side) + " pixels, the most its decoder reads");
  }
  if (width <= (uint64_t{1} << 31) && height <= (uint64_t{1} << 31) && width * height <= options.max_pixels) return Ok();
  return Fail(ErrorCode::kImageTooLarge, std::string(ImageFormatName(format)) + " header declares " + std::to_string(width) +
                                             "x" + std::to_string(height) + " pixels, over the limit of " +
                                             std::to_string(options.max_pixels));
}

// ---- TIFF data as libtiff sees it ------------------------------------------------------------------
//
// OpenCV's TIFF reader ignores what libtiff's RGBA interface reports, so TIFF data first goes through
// libtiff itself with its reports as errors, and OpenCV decodes only what passed (JPEG: image_decoders.h).

// libtiff reads the bytes from memory through these callbacks; `error` keeps its first error message.
struct TiffInput {
  std::span<const uint8_t> bytes;
  uint64_t position = 0;
  std::optional<std::string> error;
};

tmsize_t TiffRead(thandle_t handle, void* buffer, tmsize_t size) {
  auto* in = static_cast<TiffInput*>(handle);
  if (size <= 0 || in->position >= in->bytes.size()) return 0;
  const uint64_t n = std::min<uint64_t>(static_cast<uint64_t>(size), in->bytes.size() - in->position);
  std::memcpy(buffer, in->bytes.data() + in->position, n);
  in->position += n;
  return static_cast<tmsize_t>(n);
}
tmsize_t TiffWrite(thandle_t, void*, tmsize_t) { return -1; }
toff_t TiffSeek(thandle_t handle, toff_t offset, int whence) {
  auto* in = static_cast<TiffInput*>(handle);
  const uint64_t base = whence == SEEK_CUR ? in->position : whence == SEEK_END ? in->bytes.size() : 0;
  in->position = std::min<uint64_t>(base + offset, in->bytes.size());  // unsigned wrap-around: negative offsets
  return in->position;
}
int TiffClose(thandle_t) { return 0; }
toff_t TiffSize(thandle_t handle) { return static_cast<TiffInput*>(handle)->bytes.size(); }
int TiffMap(thandle_t handle, void** base, toff_t* size) {
  auto* in = static_cast<TiffInput*>(handle);
  *base = const_cast<uint8_t*>(in->bytes.data());
  *size = in->bytes.size();
  return 1;
}
void TiffUnmap(thandle_t, void*, toff_t) {}

// Handlers of this TIFF handle only (libtiff >= 4.5): returning 1 keeps the message from the process-wide
// handlers (OpenCV installs its own there).
int TiffError(TIFF*, void* user_data, const char* module, const char* format, va_list args) {
  auto* in = static_cast<TiffInput*>(user_data);
  if (!in->error) {
    char text[512];
    std::vsnprintf(text, sizeof text, format, args);
    in->error = (module != nullptr ? std::string(module) + ": " : std::string()) + text;
  }
  return 1;
}
int TiffWarning(TIFF*, void*, const char*, const char*, va_list) { return 1; }

// Opens the first directory (the page OpenCV decodes) with libtiff, checks the dimensions libtiff itself
// will decode against the pixel limit, then decodes every strip or tile of it. `header` holds the
// dimensions already checked from the header bytes (so libtiff opens nothing over the limit).
Status CheckTiffData(std::span<const uint8_t> b, const ImageHeaderInfo& header, const DecodeOptions& options) {
  // Largest strip, tile or other single allocation: the whole image at 4 samples of 16 bits (at least
  // one 256x256 tile, which small images may use).
  const uint64_t max_alloc = 8 * std::max<uint64_t>(header.width * header.height, uint64_t{1} << 16);
  TiffInput input{b, 0, std::nullopt};
  const std::unique_ptr<TIFFOpenOptions, decltype(&TIFFOpenOptionsFree)> open_options(TIFFOpenOptionsAlloc(), TIFFOpenOptionsFree);
  TIFFOpenOptionsSetErrorHandlerExtR(open_options.get(), TiffError, &input);
  TIFFOpenOptionsSetWarningHandlerExtR(open_options.get(), TiffWarning, nullptr);
  TIFFOpenOptionsSetMaxSingleMemAlloc(open_options.get(), static_cast<tmsize_t>(max_alloc));
  const std::unique_ptr<TIFF, decltype(&TIFFClose)> tif(
      TIFFClientOpenExt("image", "r", &input, TiffRead, TiffWrite, TiffSeek, TiffClose, TiffSize, TiffMap, TiffUnmap,
                        open_options.get()),
      TIFFClose);
  auto corrupt = [&] { return Invalid("TIFF data is corrupt (libtiff: " + input.error.value_or("unreadable directory") + ")"); };
  if (!tif) return corrupt();
  uint32_t width = 0, height = 0;
  if (TIFFGetField(tif.get(), TIFFTAG_IMAGEWIDTH, &width) != 1 || TIFFGetField(tif.get(), TIFFTAG_IMAGELENGTH, &height) != 1)
    return corrupt();
  if (auto limit = CheckPixelLimit(ImageFormat::kTiff, width, height, options); !limit) return limit;
  const bool tiled = TIFFIsTiled(tif.get()) != 0;
  const uint64_t piece_bytes = tiled ? TIFFTileSize64(tif.get()) : TIFFStripSize64(tif.get());
  const uint32_t pieces = tiled ? TIFFNumberOfTiles(tif.get()) : TIFFNumberOfStrips(tif.get());
  if (input.error || piece_bytes == 0 || piece_bytes > max_alloc) return corrupt();
  std::vector<uint8_t> buffer(piece_bytes);
  const auto size = static_cast<tmsize_t>(piece_bytes);
  for (uint32_t i = 0; i < pieces && !input.error; ++i) {
    const tmsize_t n = tiled ? TIFFReadEncodedTile(tif.get(), i, buffer.data(), size) : TIFFReadEncodedStrip(tif.get(), i, buffer.data(), size);
    if (n < 0) return corrupt();
  }
  if (input.error) return corrupt();
  return Ok();
}

// Whether this OpenCV build decodes `format` (WebP and TIFF support are build options): it must read back
// an image it wrote itself. Asked only after a decode failed, to tell 415 from a corrupt file.
bool OpenCvDecodes(ImageFormat format) {
  auto round_trip = [](const char* ext) {
    std::vector<uint8_t> bytes;
    const auto encoded = opencv_codecs::Encode(ext, cv::Mat(8, 8, CV_8UC1, cv::Scalar(128)), bytes);
    if (!encoded || !*encoded) return false;
    const auto decoded = opencv_codecs::Decode(bytes, cv::IMREAD_GRAYSCALE);
    return decoded && !decoded->empty();
  };
  static const bool webp = round_trip(".webp");
  static const bool tiff = round_trip(".tiff");
  return format == ImageFormat::kWebp ? webp : format == ImageFormat::kTiff ? tiff : true;
}

GrayImage ToGray(const cv::Mat& mat) {
  GrayImage image;
  image.width = mat.cols;
  image.height = mat.rows;
  image.pixels.resize(static_cast<size_t>(mat.cols) * static_cast<size_t>(mat.rows));
  for (int y = 0; y < mat.rows; ++y) {
    float* out = image.pixels.data() + static_cast<size_t>(y) * static_cast<size_t>(mat.cols);
    if (mat.depth() == CV_8U) {
      const uint8_t* in = mat.ptr<uint8_t>(y);
      for (int x = 0; x < mat.cols; ++x) out[x] = in[x] * (1.0f / 255.0f);
    } else {
      const float* in = mat.ptr<float>(y);
      for (int x = 0; x < mat.cols; ++x) out[x] = std::clamp(in[x], 0.0f, 1.0f);
    }
  }
  return image;
}

}  // namespace

std::optional<std::string> DecodeOptions::Check() const {
  if (max_pixels < 1) return "max_pixels must be >= 1";
  if (max_jpeg_scans < 1 || max_jpeg_scans > 10000) return "max_jpeg_scans must be in [1, 10000], got " + std::to_string(max_jpeg_scans);
  if (max_bytes < 1) return "max_bytes must be >= 1";
  if (max_image_side_px && *max_image_side_px < 16)
    return "max_image_side_px must be >= 16 when set, got " + std::to_string(*max_image_side_px);
  return std::nullopt;
}

bool IsImageFile(const std::string& path) {
  std::string ext = std::filesystem::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  for (const char* e : {".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".pnm", ".bmp", ".tif", ".tiff", ".webp"}) {
    if (ext == e) return true;
  }
  return false;
}

Result<std::vector<std::string>> ListImageFiles(const std::string& folder) { return ListFiles(folder, IsImageFile); }

Result<std::vector<std::string>> ListFiles(const std::string& folder, const std::function<bool(const std::string&)>& keep) {
  namespace fs = std::filesystem;
  std::error_code ec;
  if (!fs::is_directory(folder, ec)) {
    return Fail(ErrorCode::kNotFound, "'" + folder + (fs::exists(folder, ec) ? "' is not a folder" : "' does not exist"));
  }
  // Links to folders are followed, each folder once: a link back to an ancestor (or a second link to
  // one folder) is not entered again, so a loop ends and no file is listed twice through it. Folders
  // are walked in name order, so which of two links to one folder lists it does not depend on the
  // file system's order.
  auto folder_id = [](const fs::path& path) -> std::pair<dev_t, ino_t> {
    struct stat st {};
    return ::stat(path.c_str(), &st) == 0 ? std::pair(st.st_dev, st.st_ino) : std::pair<dev_t, ino_t>(0, 0);
  };
  std::set<std::pair<dev_t, ino_t>> entered;
  std::vector<std::string> files;
  std::function<void(const fs::path&)> walk = [&](const fs::path& dir) {
    if (ec || !entered.insert(folder_id(dir)).second) return;
    // Entries keep the type the folder listing gave: only links cost a stat.
    std::vector<fs::directory_entry> entries;
    for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) entries.push_back(*it);
    if (ec) return;
    std::sort(entries.begin(), entries.end());
    for (const fs::directory_entry& entry : entries) {
      std::error_code entry_ec;  // a dangling link or a file removed meanwhile is skipped
      if (entry.is_directory(entry_ec)) {
        walk(entry.path());
      } else if (entry.is_regular_file(entry_ec) && keep(entry.path().string())) {
        files.push_back(entry.path().string());
      }
    }
  };
  walk(folder);
  if (ec) return Fail(ErrorCode::kIoError, "cannot list '" + folder + "': " + ec.message());
  std::sort(files.begin(), files.end());
  return files;
}

const char* ImageFormatName(ImageFormat format) {
  switch (format) {
    case ImageFormat::kUnknown: return "unknown";
    case ImageFormat::kJpeg: return "jpeg";
    case ImageFormat::kPng: return "png";
    case ImageFormat::kPnm: return "pnm";
    case ImageFormat::kWebp: return "webp";
    case ImageFormat::kTiff: return "tiff";
    case ImageFormat::kBmp: return "bmp";
  }
  return "unknown";
}

Result<ImageHeaderInfo> ReadImageHeader(std::span<const uint8_t> bytes) {
  size_t scan_start = 0, data_start = 0;
  uint32_t maxval = 0;
  Result<ImageHeaderInfo> info = Invalid("");
  switch (SniffFormat(bytes)) {
    case ImageFormat::kJpeg: info = JpegHeader(bytes, &scan_start); break;
    case ImageFormat::kPng: info = PngHeader(bytes); break;
    case ImageFormat::kPnm: info = PnmHeader(bytes, &maxval, &data_start); break;
    case ImageFormat::kWebp: info = WebpHeader(bytes); break;
    case ImageFormat::kTiff: info = TiffHeader(bytes); break;
    case ImageFormat::kBmp: info = BmpHeader(bytes); break;
    case ImageFormat::kUnknown:
      if (bytes.empty()) return Invalid("image data is empty");
      if (StartsWith(bytes, "GIF87a") || StartsWith(bytes, "GIF89a"))
        return Fail(ErrorCode::kUnsupportedFormat, "GIF images are not supported (OpenCV 4.6 cannot decode them); "
                                                   "convert to PNG or JPEG (an animation: its first frame)");
      return Invalid("not an image: the data starts with no known image signature (JPEG, PNG, PPM/PGM, WebP, TIFF, BMP)");
  }
  if (info && (info->width == 0 || info->height == 0)) return Invalid("image header declares a zero width or height");
  return info;
}

Result<DecodedImage> DecodeImage(std::span<const uint8_t> bytes, const DecodeOptions& options) {
  if (auto message = options.Check()) return Fail(ErrorCode::kInvalidArgument, "invalid decode options: " + *message);
  if (bytes.empty()) return Invalid("image data is empty");
  if (bytes.size() > options.max_bytes)
    return Fail(ErrorCode::kImageTooLarge, "image data is " + std::to_string(bytes.size()) + " bytes, over the limit of " +
                                               std::to_string(options.max_bytes));
  const ImageFormat format = SniffFormat(bytes);
  size_t scan_start = 0, data_start = 0;
  uint32_t maxval = 0;
  Result<ImageHeaderInfo> info = Invalid("");
  switch (format) {
    case ImageFormat::kJpeg: info = JpegHeader(bytes, &scan_start); break;
    case ImageFormat::kPnm: info = PnmHeader(bytes, &maxval, &data_start); break;
    default: info = ReadImageHeader(bytes); break;
  }
  if (!info) return std::unexpected(info.error());
  if (info->width == 0 || info->height == 0) return Invalid("image header declares a zero width or height");
  if (auto limit = CheckPixelLimit(info->format, info->width, info->height, options); !limit) return std::unexpected(limit.error());
  const uint64_t declared = info->width * info->height;
  if (auto complete = CheckComplete(bytes, *info, scan_start, maxval, data_start); !complete)
    return std::unexpected(complete.error());
  // JPEG, PNG and 8-bit PGM are decoded here (image_decoders.h); what those decoders leave (CMYK JPEG,
  // other PNM) and the other formats go to OpenCV's decoders. A PNG that libpng refuses is not: OpenCV
  // reads it with the same libpng, which would refuse it again and print its error to stderr.
  cv::Mat mat;
  switch (info->format) {
    case ImageFormat::kJpeg: {
      auto jpeg = internal::DecodeJpeg(bytes, options.max_jpeg_scans, true, options.apply_exif_orientation);
      if (!jpeg) return std::unexpected(jpeg.error());
      mat = std::move(*jpeg);
      break;
    }
    case ImageFormat::kPng:
      mat = internal::DecodePngGray(bytes, options.apply_exif_orientation);
      if (mat.empty()) return Invalid("png data could not be decoded (corrupt or truncated)");
      break;
    case ImageFormat::kPnm: mat = internal::DecodePgmGray(bytes, info->width, info->height, maxval, data_start); break;
    case ImageFormat::kTiff:
      if (auto intact = CheckTiffData(bytes, *info, options); !intact) return std::unexpected(intact.error());
      break;
    default: break;
  }
  if (mat.empty()) {
    int flags = cv::IMREAD_GRAYSCALE;
    if (!options.apply_exif_orientation) flags |= cv::IMREAD_IGNORE_ORIENTATION;
    auto decoded = opencv_codecs::Decode(bytes, flags);
    if (!decoded) {
      Error error = decoded.error();
      if (error.code == ErrorCode::kInvalidImage)
        error.message = std::string(ImageFormatName(info->format)) + " data could not be decoded: " + error.message;
      return std::unexpected(error);
    }
    mat = std::move(*decoded);
  }
  if (mat.empty()) {
    if (!OpenCvDecodes(info->format))
      return Fail(ErrorCode::kUnsupportedFormat, std::string("this OpenCV build cannot decode ") + ImageFormatName(info->format));
    return Invalid(std::string(ImageFormatName(info->format)) + " data could not be decoded (corrupt or truncated)");
  }
  if (static_cast<uint64_t>(mat.cols) * static_cast<uint64_t>(mat.rows) != declared)
    return Invalid("decoded size differs from the size the header declares (corrupt)");
  if (mat.depth() != CV_8U) mat.convertTo(mat, CV_32F, mat.depth() == CV_16U ? 1.0 / 65535.0 : 1.0);

  DecodedImage out;
  out.original_width = mat.cols;
  out.original_height = mat.rows;
  const int longest = std::max(mat.cols, mat.rows);
  if (options.max_image_side_px && longest > *options.max_image_side_px) {
    const double scale = static_cast<double>(longest) / *options.max_image_side_px;
    const int w = std::max(1, static_cast<int>(std::lround(mat.cols / scale)));
    const int h = std::max(1, static_cast<int>(std::lround(mat.rows / scale)));
    cv::Mat small;
    cv::resize(mat, small, cv::Size(w, h), 0, 0, cv::INTER_AREA);
    mat = small;
    out.scale_to_original = scale;
  }
  out.gray = ToGray(mat);
  return out;
}

Result<DecodedImage> ReadImage(const std::string& path, const DecodeOptions& options) {
  auto bytes = io::ReadWholeFile(path, options.max_bytes);
  if (!bytes) {
    Error error = bytes.error();
    if (error.code == ErrorCode::kResourceExhausted) error.code = ErrorCode::kImageTooLarge;  // over max_bytes
    return std::unexpected(error);
  }
  auto decoded = DecodeImage(*bytes, options);
  if (!decoded) {
    Error error = decoded.error();
    error.message = "'" + path + "': " + error.message;
    return std::unexpected(error);
  }
  return decoded;
}

GrayImage GrayFromBytes(const uint8_t* data, int width, int height, size_t stride) {
  GrayImage image;
  image.width = width;
  image.height = height;
  image.pixels.resize(static_cast<size_t>(width) * static_cast<size_t>(height));
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x)
      image.pixels[static_cast<size_t>(y) * static_cast<size_t>(width) + static_cast<size_t>(x)] =
          data[static_cast<size_t>(y) * stride + static_cast<size_t>(x)] * (1.0f / 255.0f);
  return image;
}

}  // namespace oxbow::sift
