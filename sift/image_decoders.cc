#include "sift/image_decoders.h"

#include <csetjmp>
#include <cstdio>
#include <cstring>
#include <limits>
#include <string>
#include <vector>

#include <jpeglib.h>
#include <jerror.h>
#include <png.h>

namespace oxbow::sift::internal {
namespace {

std::unexpected<Error> Invalid(std::string message) { return Fail(ErrorCode::kInvalidImage, std::move(message)); }

// ---- JPEG ---------------------------------------------------------------------------------------------
//
// OpenCV's decoders carry on where libjpeg reports damage (libjpeg only warns about missing or
// undecodable entropy-coded data, then fills in grey), so every such report is an error here, as in
// libjpeg-turbo's `djpeg -strict`; the scans of a progressive file are bounded as `djpeg -maxscans` does:
// libjpeg walks every block of the frame for each scan, however few bytes the scan has.

// libjpeg's callbacks reach this through cinfo.err (the first member of JpegErrors); error_exit must not
// return, so errors jump back to the setjmp of the step that is running.
struct JpegErrors {
  jpeg_error_mgr errors;
  jpeg_progress_mgr progress;
  std::jmp_buf failed;
  int max_scans = 0;
  bool over_scan_limit = false;
  char message[JMSG_LENGTH_MAX] = {};
};

JpegErrors* ErrorsOf(j_common_ptr cinfo) { return reinterpret_cast<JpegErrors*>(cinfo->err); }

[[noreturn]] void JpegFail(j_common_ptr cinfo) {
  (*cinfo->err->format_message)(cinfo, ErrorsOf(cinfo)->message);
  std::longjmp(ErrorsOf(cinfo)->failed, 1);
}

// Warnings that image data is missing or undecodable fail. The other warnings (an unknown JFIF version,
// stray bytes between segments, a bad ICC profile) leave every pixel intact, and some cameras write such
// files; they and trace messages (level >= 0) are ignored.
void JpegMessage(j_common_ptr cinfo, int level) {
  if (level >= 0) return;
  switch (cinfo->err->msg_code) {
    case JWRN_HIT_MARKER:      // "premature end of data segment": the scan's data ran out
    case JWRN_JPEG_EOF:        // the file ran out
    case JWRN_HUFF_BAD_CODE:
    case JWRN_ARITH_BAD_CODE:
    case JWRN_MUST_RESYNC:     // restart markers out of order: data was lost
      JpegFail(cinfo);
    default:
      ++cinfo->err->num_warnings;
  }
}

// libjpeg calls this for every row of blocks it reads; input_scan_number counts the scans started.
void JpegProgress(j_common_ptr cinfo) {
  JpegErrors* errors = ErrorsOf(cinfo);
  if (reinterpret_cast<j_decompress_ptr>(cinfo)->input_scan_number > errors->max_scans) {
    errors->over_scan_limit = true;
    std::longjmp(errors->failed, 1);
  }
}

// One decompression, in steps that each set their own jump target (the C++ objects of the caller, such
// as the output Mat, live outside every step, so no destructor is skipped by a jump).
struct JpegDecompression {
  JpegErrors errors;
  jpeg_decompress_struct cinfo{};
  bool created = false;

  ~JpegDecompression() {
    if (created) jpeg_destroy_decompress(&cinfo);
  }

  // Reads the markers up to the first scan (keeping the first APP1 segment's data for the EXIF tags).
  bool ReadHeader(std::span<const uint8_t> bytes, int max_scans) {
    cinfo.err = jpeg_std_error(&errors.errors);
    errors.errors.error_exit = JpegFail;
    errors.errors.emit_message = JpegMessage;
    errors.progress.progress_monitor = JpegProgress;
    errors.max_scans = max_scans;
    if (setjmp(errors.failed) != 0) return false;
    jpeg_create_decompress(&cinfo);
    created = true;
    cinfo.progress = &errors.progress;
    jpeg_mem_src(&cinfo, bytes.data(), static_cast<unsigned long>(bytes.size()));
    jpeg_save_markers(&cinfo, JPEG_APP0 + 1, 0xffff);
    jpeg_read_header(&cinfo, TRUE);
    return true;
  }

  // Full size, 8-bit grey, libjpeg's defaults otherwise (what OpenCV asks for), into `out`.
  bool ReadGray(cv::Mat& out) {
    if (setjmp(errors.failed) != 0) return false;
    cinfo.out_color_space = JCS_GRAYSCALE;
    jpeg_start_decompress(&cinfo);
    if (static_cast<int>(cinfo.output_width) != out.cols || static_cast<int>(cinfo.output_height) != out.rows ||
        cinfo.output_components != 1) {
      std::snprintf(errors.message, sizeof errors.message, "decoded size differs from the frame header");
      return false;
    }
    while (cinfo.output_scanline < cinfo.output_height) {
      JSAMPROW row = out.ptr<uint8_t>(static_cast<int>(cinfo.output_scanline));
      jpeg_read_scanlines(&cinfo, &row, 1);
    }
    jpeg_finish_decompress(&cinfo);  // reads on to the end marker: damage after the last row shows too
    return true;
  }

  // Every scan and block entropy-decoded at 1/8 scale, the pixels thrown away.
  bool Check() {
    if (setjmp(errors.failed) != 0) return false;
    cinfo.scale_num = 1;
    cinfo.scale_denom = 8;
    cinfo.dct_method = JDCT_IFAST;
    cinfo.do_fancy_upsampling = FALSE;
    if (cinfo.jpeg_color_space == JCS_YCbCr || cinfo.jpeg_color_space == JCS_GRAYSCALE) cinfo.out_color_space = JCS_GRAYSCALE;
    jpeg_start_decompress(&cinfo);
    JSAMPARRAY row = (*cinfo.mem->alloc_sarray)(reinterpret_cast<j_common_ptr>(&cinfo), JPOOL_IMAGE,
                                                cinfo.output_width * static_cast<JDIMENSION>(cinfo.output_components), 1);
    while (cinfo.output_scanline < cinfo.output_height) jpeg_read_scanlines(&cinfo, row, 1);
    jpeg_finish_decompress(&cinfo);
    return true;
  }

  Error Failure(int max_scans) const {
    if (errors.over_scan_limit) {
      return Error{ErrorCode::kInvalidImage,
                   "progressive JPEG has more than " + std::to_string(max_scans) +
                       " scans (the limit; ordinary files have at most ~10): refused, as each scan costs a pass over the whole image"};
    }
    return Error{ErrorCode::kInvalidImage, std::string("JPEG data is corrupt or truncated (libjpeg: ") + errors.message + ")"};
  }

  // The EXIF block of the first APP1 segment (what follows its 6-byte "Exif\0\0" identifier), as OpenCV
  // reads it; empty when there is none. Valid until the decompression finishes.
  std::span<const uint8_t> Exif() const {
    for (jpeg_saved_marker_ptr m = cinfo.marker_list; m != nullptr; m = m->next) {
      if (m->marker != JPEG_APP0 + 1) continue;
      if (m->data_length <= 6) return {};
      return {m->data + 6, m->data_length - 6};
    }
    return {};
  }
};

// ---- PNG ----------------------------------------------------------------------------------------------

struct PngInput {
  std::span<const uint8_t> bytes;
  size_t position = 0;
};

void PngRead(png_structp png, png_bytep out, png_size_t size) {
  auto* input = static_cast<PngInput*>(png_get_io_ptr(png));
  if (size > input->bytes.size() - input->position) png_error(png, "the data ends early");
  std::memcpy(out, input->bytes.data() + input->position, size);
  input->position += size;
}

void PngWarning(png_structp, png_const_charp) {}  // libpng would print to stderr; the pixels are intact

[[noreturn]] void PngError(png_structp png, png_const_charp) { png_longjmp(png, 1); }

// libpng's read and info structures, destroyed on every way out.
struct PngDecompression {
  png_structp png = nullptr;
  png_infop info = nullptr;
  png_infop end = nullptr;
  PngInput input;
  std::vector<png_bytep> rows;  // the output's rows, set before ReadGray (nothing is allocated after its setjmp)

  ~PngDecompression() { png_destroy_read_struct(&png, &info, &end); }

  bool ReadHeader(std::span<const uint8_t> bytes, png_uint_32& width, png_uint_32& height) {
    png = png_create_read_struct(PNG_LIBPNG_VER_STRING, nullptr, PngError, PngWarning);
    if (png == nullptr) return false;
    info = png_create_info_struct(png);
    end = png_create_info_struct(png);
    if (info == nullptr || end == nullptr) return false;
    if (setjmp(png_jmpbuf(png)) != 0) return false;
    input.bytes = bytes;
    png_set_read_fn(png, &input, PngRead);
    png_read_info(png, info);
    width = png_get_image_width(png, info);
    height = png_get_image_height(png, info);
    return true;
  }

  // OpenCV's transforms for a grey 8-bit result, then every row into `rows` and the chunks after them.
  bool ReadGray(size_t row_bytes) {
    if (setjmp(png_jmpbuf(png)) != 0) return false;
    const int depth = png_get_bit_depth(png, info);
    const int colour = png_get_color_type(png, info);
    if (depth == 16) png_set_strip_16(png);
    png_set_strip_alpha(png);
    if (colour == PNG_COLOR_TYPE_PALETTE) png_set_palette_to_rgb(png);
    if ((colour & PNG_COLOR_MASK_COLOR) == 0 && depth < 8) png_set_expand_gray_1_2_4_to_8(png);
    png_set_rgb_to_gray(png, 1, 0.299, 0.587);
    png_set_interlace_handling(png);
    png_read_update_info(png, info);
    if (png_get_rowbytes(png, info) != row_bytes) return false;
    png_read_image(png, rows.data());
    png_read_end(png, end);
    return true;
  }

  std::span<const uint8_t> Exif() const {
    png_uint_32 size = 0;
    png_bytep data = nullptr;
    if (png_get_valid(png, info, PNG_INFO_eXIf)) {
      png_get_eXIf_1(png, info, &size, &data);
    } else if (png_get_valid(png, end, PNG_INFO_eXIf)) {
      png_get_eXIf_1(png, end, &size, &data);
    }
    if (data == nullptr) return {};
    return {data, size};
  }
};

}  // namespace

Result<cv::Mat> DecodeJpeg(std::span<const uint8_t> bytes, int max_scans, bool want_gray, bool apply_exif_orientation) {
  JpegDecompression jpeg;
  if (!jpeg.ReadHeader(bytes, max_scans)) return std::unexpected(jpeg.Failure(max_scans));
  // Read now: the saved segments are freed when the decompression finishes.
  const int orientation = want_gray && apply_exif_orientation ? ExifOrientation(jpeg.Exif()) : 1;
  if (!want_gray || jpeg.cinfo.num_components == 4) {
    if (!jpeg.Check()) return std::unexpected(jpeg.Failure(max_scans));
    return cv::Mat();
  }
  if (jpeg.cinfo.image_width > static_cast<JDIMENSION>(std::numeric_limits<int>::max()) ||
      jpeg.cinfo.image_height > static_cast<JDIMENSION>(std::numeric_limits<int>::max())) {
    return Invalid("JPEG frame is too large");
  }
  cv::Mat gray(static_cast<int>(jpeg.cinfo.image_height), static_cast<int>(jpeg.cinfo.image_width), CV_8U);
  if (!jpeg.ReadGray(gray)) return std::unexpected(jpeg.Failure(max_scans));
  ApplyExifOrientation(orientation, gray);
  return gray;
}

cv::Mat DecodePngGray(std::span<const uint8_t> bytes, bool apply_exif_orientation) {
  PngDecompression png;
  png_uint_32 width = 0, height = 0;
  if (!png.ReadHeader(bytes, width, height)) return {};
  if (width == 0 || height == 0 || width > static_cast<png_uint_32>(std::numeric_limits<int>::max()) ||
      height > static_cast<png_uint_32>(std::numeric_limits<int>::max())) {
    return {};
  }
  cv::Mat gray(static_cast<int>(height), static_cast<int>(width), CV_8U);
  png.rows.resize(height);
  for (int y = 0; y < gray.rows; ++y) png.rows[static_cast<size_t>(y)] = gray.ptr<uint8_t>(y);
  if (!png.ReadGray(width)) return {};
  if (apply_exif_orientation) ApplyExifOrientation(ExifOrientation(png.Exif()), gray);
  return gray;
}

cv::Mat DecodePgmGray(std::span<const uint8_t> bytes, uint64_t width, uint64_t height, uint32_t maxval, size_t data_start) {
  if (bytes.size() < 2 || bytes[0] != 'P' || bytes[1] != '5' || maxval != 255) return {};
  if (data_start > bytes.size() || width * height > bytes.size() - data_start) return {};
  cv::Mat gray(static_cast<int>(height), static_cast<int>(width), CV_8U);
  for (int y = 0; y < gray.rows; ++y) {
    std::memcpy(gray.ptr<uint8_t>(y), bytes.data() + data_start + static_cast<size_t>(y) * width, width);
  }
  return gray;
}

int ExifOrientation(std::span<const uint8_t> exif) {
  // OpenCV's reading: "II" is little-endian, anything else big-endian; the 0x002A mark must follow; each
  // 12-byte entry of the first directory is read in order, and a field it knows that points outside the
  // block ends the reading (the entries before it count; the first orientation entry wins).
  const size_t size = exif.size();
  const bool little = size >= 2 && exif[0] == 'I' && exif[1] == 'I';
  auto fits = [&](uint64_t offset, uint64_t length) { return offset + length <= size; };
  auto u16 = [&](uint64_t o) -> uint32_t {
    return little ? exif[o] | (uint32_t{exif[o + 1]} << 8) : (uint32_t{exif[o]} << 8) | exif[o + 1];
  };
  auto u32 = [&](uint64_t o) -> uint64_t {
    return little ? u16(o) | (uint64_t{u16(o + 2)} << 16) : (uint64_t{u16(o)} << 16) | u16(o + 2);
  };
  if (!fits(2, 2) || u16(2) != 0x2A || !fits(4, 4)) return 1;
  uint64_t offset = u32(4);
  if (!fits(offset, 2)) return 1;
  const uint32_t entries = u16(offset);
  offset += 2;
  for (uint32_t e = 0; e < entries; ++e, offset += 12) {
    if (!fits(offset, 2)) return 1;
    switch (u16(offset)) {
      case 0x0112:  // Orientation (SHORT)
        if (!fits(offset + 8, 2)) return 1;
        return static_cast<int>(u16(offset + 8));
      case 0x0128:  // ResolutionUnit, YCbCrPositioning (SHORT)
      case 0x0213:
        if (!fits(offset + 8, 2)) return 1;
        break;
      case 0x010E:  // ImageDescription, Make, Model, Software, DateTime, Copyright (strings)
      case 0x010F:
      case 0x0110:
      case 0x0131:
      case 0x0132:
      case 0x8298: {
        if (!fits(offset + 4, 4)) return 1;
        const uint64_t length = u32(offset + 4);
        uint64_t at = 8;  // as OpenCV reads a string of up to 4 bytes: from the block's byte 8
        if (length > 4) {
          if (!fits(offset + 8, 4)) return 1;
          at = u32(offset + 8);
        }
        if (at > size || !fits(at, length)) return 1;
        break;
      }
      case 0x011A:  // XResolution, YResolution: one RATIONAL; WhitePoint 2; YCbCrCoefficients 3;
      case 0x011B:  // PrimaryChromaticities and ReferenceBlackWhite 6
      case 0x013E:
      case 0x0211:
      case 0x013F:
      case 0x0214: {
        const uint16_t tag = static_cast<uint16_t>(u16(offset));
        const uint64_t count = tag == 0x013E ? 2 : tag == 0x0211 ? 3 : (tag == 0x013F || tag == 0x0214) ? 6 : 1;
        if (!fits(offset + 8, 4)) return 1;
        if (!fits(u32(offset + 8), 8 * count)) return 1;
        break;
      }
      default:
        break;
    }
  }
  return 1;
}

void ApplyExifOrientation(int orientation, cv::Mat& image) {
  switch (orientation) {
    case 2: cv::flip(image, image, 1); break;
    case 3: cv::flip(image, image, -1); break;
    case 4: cv::flip(image, image, 0); break;
    case 5: cv::transpose(image, image); break;
    case 6: cv::transpose(image, image); cv::flip(image, image, 1); break;
    case 7: cv::transpose(image, image); cv::flip(image, image, -1); break;
    case 8: cv::transpose(image, image); cv::flip(image, image, 0); break;
    default: break;
  }
}

}  // namespace oxbow::sift::internal
