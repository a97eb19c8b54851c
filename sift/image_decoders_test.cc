// The decoders of image_decoders.h against cv::imdecode(IMREAD_GRAYSCALE), pixel for pixel: every JPEG,
// PNG and PGM of OpenCV's sample data, the evaluation photos (suite ImageDecodersSharedData, a ctest of its
// own that is skipped without ../shared/data or $OXBOW_SHARED_DATA), PNG files of
// every colour type and bit depth, and EXIF orientations in JPEG APP1 segments and PNG eXIf chunks.
#include "sift/image_decoders.h"

#include <gtest/gtest.h>
#include <png.h>

#include <algorithm>
#include <array>
#include <filesystem>
#include <random>
#include <string>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "sift/base/binary_io.h"
#include "sift/image.h"
#include "tests/support/shared_data.h"

namespace oxbow::sift::internal {
namespace {

namespace fs = std::filesystem;

const fs::path kOpencvData = "/usr/share/doc/opencv-doc/examples/data";

// What image.cc's own decoders give for the file, or an empty Mat where they leave it to OpenCV.
cv::Mat Native(const std::vector<uint8_t>& bytes) {
  const auto header = ReadImageHeader(bytes);
  EXPECT_TRUE(header.has_value());
  if (!header) return {};
  switch (header->format) {
    case ImageFormat::kJpeg: {
      auto jpeg = DecodeJpeg(bytes, 100, true, true);
      EXPECT_TRUE(jpeg.has_value()) << (jpeg ? "" : jpeg.error().message);
      return jpeg ? *jpeg : cv::Mat();
    }
    case ImageFormat::kPng: return DecodePngGray(bytes, true);
    default: return {};
  }
}

// Pixel-for-pixel equality with OpenCV's grey decode; returns false when `bytes` went to OpenCV anyway.
bool ExpectSameAsOpenCv(const std::vector<uint8_t>& bytes, const std::string& what) {
  const cv::Mat ours = Native(bytes);
  const cv::Mat theirs = cv::imdecode(bytes, cv::IMREAD_GRAYSCALE);
  if (ours.empty()) return false;
  EXPECT_FALSE(theirs.empty()) << what;
  EXPECT_EQ(ours.size(), theirs.size()) << what;
  if (ours.size() == theirs.size() && !theirs.empty()) {
    EXPECT_EQ(cv::norm(ours, theirs, cv::NORM_INF), 0.0) << what;
  }
  return true;
}

std::vector<uint8_t> Read(const fs::path& path) {
  auto bytes = io::ReadWholeFile(path.string(), 256u << 20);
  EXPECT_TRUE(bytes.has_value()) << path;
  return bytes ? std::vector<uint8_t>(bytes->begin(), bytes->end()) : std::vector<uint8_t>();
}

bool IsJpegPngOrPgm(const fs::path& p) {
  std::string ext = p.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return ext == ".jpg" || ext == ".jpeg" || ext == ".png" || ext == ".pgm";
}

TEST(ImageDecoders, MatchOpenCvOnItsSampleImages) {
  ASSERT_TRUE(fs::is_directory(kOpencvData)) << "opencv-doc (scripts/install-deps.sh) is not installed";
  int compared = 0;
  for (const auto& entry : fs::directory_iterator(kOpencvData)) {
    if (!entry.is_regular_file() || !IsJpegPngOrPgm(entry.path())) continue;
    if (ExpectSameAsOpenCv(Read(entry.path()), entry.path().string())) ++compared;
  }
  EXPECT_GE(compared, 50);
}

TEST(ImageDecodersSharedData, MatchOpenCvOnTheEvaluationPhotos) {
  const fs::path data = oxbow::testing::SharedDataDir();
  if (!fs::is_directory(data)) {
    GTEST_SKIP() << "shared data not found at " << data << " (set OXBOW_SHARED_DATA; see tests/support/shared_data.h)";
  }
  std::vector<fs::path> files;
  for (const auto& entry : fs::recursive_directory_iterator(data)) {
    if (entry.is_regular_file() && IsJpegPngOrPgm(entry.path())) files.push_back(entry.path());
  }
  std::sort(files.begin(), files.end());
  // Every 8th file: about 110 of the ~850 photos (each comparison decodes the photo twice).
  int compared = 0;
  for (size_t i = 0; i < files.size(); i += 8) {
    const auto bytes = Read(files[i]);
    if (files[i].extension() == ".pgm") {
      const auto header = ReadImageHeader(bytes);
      ASSERT_TRUE(header.has_value());
      const auto decoded = DecodeImage(bytes, {.max_image_side_px = std::nullopt});
      ASSERT_TRUE(decoded.has_value()) << files[i];
      const cv::Mat theirs = cv::imdecode(bytes, cv::IMREAD_GRAYSCALE);
      ASSERT_EQ(decoded->gray.width, theirs.cols);
      for (int y = 0; y < theirs.rows; ++y)
        for (int x = 0; x < theirs.cols; ++x) ASSERT_EQ(decoded->gray.at(x, y), theirs.at<uint8_t>(y, x) * (1.0f / 255.0f)) << files[i];
      ++compared;
    } else if (ExpectSameAsOpenCv(bytes, files[i].string())) {
      ++compared;
    }
  }
  EXPECT_GE(compared, 20);
}

// ---- PNG of every kind -------------------------------------------------------------------------------

struct PngSpec {
  int colour_type = PNG_COLOR_TYPE_GRAY;
  int bit_depth = 8;
  bool interlaced = false;
  bool transparency = false;  // a tRNS chunk (palette and RGB)
  bool gamma = false;         // a gAMA chunk of 1/2.2
  std::vector<uint8_t> exif;  // an eXIf chunk when not empty
};

void AppendPng(png_structp png, png_bytep data, png_size_t size) {
  auto* out = static_cast<std::vector<uint8_t>*>(png_get_io_ptr(png));
  out->insert(out->end(), data, data + size);
}

std::vector<uint8_t> MakePng(const PngSpec& spec, int width = 37, int height = 23) {
  std::vector<uint8_t> out;
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
  png_infop info = png_create_info_struct(png);
  if (setjmp(png_jmpbuf(png)) != 0) {
    png_destroy_write_struct(&png, &info);
    ADD_FAILURE() << "libpng could not write the test file";
    return {};
  }
  png_set_write_fn(png, &out, AppendPng, nullptr);
  png_set_IHDR(png, info, static_cast<png_uint_32>(width), static_cast<png_uint_32>(height), spec.bit_depth, spec.colour_type,
               spec.interlaced ? PNG_INTERLACE_ADAM7 : PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
  std::vector<png_color> palette;
  if (spec.colour_type == PNG_COLOR_TYPE_PALETTE) {
    for (int i = 0; i < (1 << spec.bit_depth); ++i)
      palette.push_back({static_cast<png_byte>(i * 37 % 256), static_cast<png_byte>(i * 91 % 256), static_cast<png_byte>(255 - i * 13 % 256)});
    png_set_PLTE(png, info, palette.data(), static_cast<int>(palette.size()));
  }
  png_byte alphas[4] = {0, 80, 160, 255};
  png_color_16 transparent_rgb{};
  transparent_rgb.red = 120;
  transparent_rgb.green = 60;
  transparent_rgb.blue = 30;
  if (spec.transparency) {
    if (spec.colour_type == PNG_COLOR_TYPE_PALETTE) png_set_tRNS(png, info, alphas, std::min(4, 1 << spec.bit_depth), nullptr);
    else png_set_tRNS(png, info, nullptr, 0, &transparent_rgb);
  }
  if (spec.gamma) png_set_gAMA(png, info, 1 / 2.2);
  if (!spec.exif.empty()) png_set_eXIf_1(png, info, static_cast<png_uint_32>(spec.exif.size()), const_cast<png_bytep>(spec.exif.data()));
  png_write_info(png, info);
  const size_t row_bytes = png_get_rowbytes(png, info);
  std::mt19937 random(static_cast<unsigned>(spec.colour_type * 100 + spec.bit_depth));
  std::vector<std::vector<png_byte>> rows(static_cast<size_t>(height), std::vector<png_byte>(row_bytes));
  for (int y = 0; y < height; ++y)
    for (size_t b = 0; b < row_bytes; ++b)  // a ramp with noise, so that every channel and bit varies
      rows[static_cast<size_t>(y)][b] = static_cast<png_byte>((b * 7 + static_cast<size_t>(y) * 11 + random() % 64) % 256);
  std::vector<png_bytep> pointers(rows.size());
  for (size_t y = 0; y < rows.size(); ++y) pointers[y] = rows[y].data();
  png_write_image(png, pointers.data());
  png_write_end(png, info);
  png_destroy_write_struct(&png, &info);
  return out;
}

TEST(ImageDecoders, MatchOpenCvOnEveryPngColourTypeAndDepth) {
  const struct {
    int colour_type;
    std::vector<int> depths;
  } kinds[] = {{PNG_COLOR_TYPE_GRAY, {1, 2, 4, 8, 16}},
               {PNG_COLOR_TYPE_GRAY_ALPHA, {8, 16}},
               {PNG_COLOR_TYPE_RGB, {8, 16}},
               {PNG_COLOR_TYPE_RGB_ALPHA, {8, 16}},
               {PNG_COLOR_TYPE_PALETTE, {1, 2, 4, 8}}};
  for (const auto& kind : kinds) {
    for (int depth : kind.depths) {
      for (bool interlaced : {false, true}) {
        for (bool extras : {false, true}) {
          PngSpec spec{.colour_type = kind.colour_type, .bit_depth = depth, .interlaced = interlaced,
                       .transparency = extras && (kind.colour_type == PNG_COLOR_TYPE_PALETTE || kind.colour_type == PNG_COLOR_TYPE_RGB),
                       .gamma = extras, .exif = {}};
          const std::string what = "colour type " + std::to_string(kind.colour_type) + ", " + std::to_string(depth) +
                                   " bits" + (interlaced ? ", interlaced" : "") + (extras ? ", tRNS/gAMA" : "");
          EXPECT_TRUE(ExpectSameAsOpenCv(MakePng(spec), what)) << what << ": left to OpenCV";
        }
      }
    }
  }
}

TEST(ImageDecoders, TruncatedOrDamagedPngIsEmpty) {
  auto png = MakePng({.colour_type = PNG_COLOR_TYPE_RGB, .bit_depth = 8, .interlaced = false, .transparency = false, .gamma = false, .exif = {}});
  auto cut = std::vector<uint8_t>(png.begin(), png.begin() + static_cast<std::ptrdiff_t>(png.size() / 2));
  EXPECT_TRUE(DecodePngGray(cut, true).empty());
  png[png.size() / 2] ^= 0x55;  // inside the IDAT chunk: its CRC no longer matches
  EXPECT_TRUE(DecodePngGray(png, true).empty());
}

// ---- EXIF orientation ----------------------------------------------------------------------------------

// A TIFF-header EXIF block (as in an eXIf chunk, or an APP1 segment after "Exif\0\0") with the entries
// given as (tag, type, count, value-or-offset), in the byte order asked for.
std::vector<uint8_t> ExifBlock(bool little, const std::vector<std::array<uint32_t, 4>>& entries, size_t padding = 0) {
  std::vector<uint8_t> b;
  auto u16 = [&](uint32_t v) {
    if (little) { b.push_back(static_cast<uint8_t>(v)); b.push_back(static_cast<uint8_t>(v >> 8)); }
    else { b.push_back(static_cast<uint8_t>(v >> 8)); b.push_back(static_cast<uint8_t>(v)); }
  };
  auto u32 = [&](uint32_t v) {
    if (little) { u16(v & 0xFFFF); u16(v >> 16); } else { u16(v >> 16); u16(v & 0xFFFF); }
  };
  b.push_back(little ? 'I' : 'M');
  b.push_back(little ? 'I' : 'M');
  u16(42);
  u32(8);
  u16(static_cast<uint32_t>(entries.size()));
  for (const auto& e : entries) {
    u16(e[0]);
    u16(e[1]);
    u32(e[2]);
    if (e[1] == 3 && e[2] == 1) { u16(e[3]); u16(0); } else { u32(e[3]); }  // a SHORT sits in the first two bytes
  }
  u32(0);
  b.resize(b.size() + padding, 0);
  return b;
}

std::vector<uint8_t> WithApp1(const std::vector<uint8_t>& jpeg, const std::vector<uint8_t>& payload) {
  std::vector<uint8_t> out = {0xFF, 0xD8, 0xFF, 0xE1};
  const size_t length = payload.size() + 2;
  out.push_back(static_cast<uint8_t>(length >> 8));
  out.push_back(static_cast<uint8_t>(length));
  out.insert(out.end(), payload.begin(), payload.end());
  out.insert(out.end(), jpeg.begin() + 2, jpeg.end());
  return out;
}

std::vector<uint8_t> ExifApp1(const std::vector<uint8_t>& block) {
  const uint8_t identifier[] = {'E', 'x', 'i', 'f', 0, 0};
  std::vector<uint8_t> payload;
  payload.reserve(sizeof identifier + block.size());
  payload.insert(payload.end(), std::begin(identifier), std::end(identifier));
  payload.insert(payload.end(), block.begin(), block.end());
  return payload;
}

cv::Mat Card() {  // not symmetric under any flip or transpose
  cv::Mat m(30, 44, CV_8UC3);
  for (int y = 0; y < m.rows; ++y)
    for (int x = 0; x < m.cols; ++x) m.at<cv::Vec3b>(y, x) = cv::Vec3b(static_cast<uint8_t>(5 * x), static_cast<uint8_t>(7 * y), 90);
  m(cv::Rect(2, 3, 8, 6)).setTo(cv::Scalar(255, 255, 255));
  return m;
}

TEST(ImageDecoders, JpegExifOrientationAsOpenCvAppliesIt) {
  std::vector<uint8_t> jpeg;
  ASSERT_TRUE(cv::imencode(".jpg", Card(), jpeg));
  constexpr uint32_t kShort = 3, kAscii = 2, kRational = 5;
  for (bool little : {true, false}) {
    for (uint32_t orientation = 0; orientation <= 9; ++orientation) {
      const auto file = WithApp1(jpeg, ExifApp1(ExifBlock(little, {{0x0112, kShort, 1, orientation}})));
      EXPECT_TRUE(ExpectSameAsOpenCv(file, "orientation " + std::to_string(orientation)));
    }
  }
  // The fields OpenCV reads before the orientation decide whether it gets there: a string or rational
  // pointing outside the block ends its reading; one inside does not; after the orientation, nothing counts.
  const std::vector<std::vector<std::array<uint32_t, 4>>> cases = {
      {{0x010F, kAscii, 40, 1000}, {0x0112, kShort, 1, 6}},   // Make, outside: orientation not read
      {{0x010F, kAscii, 6, 26}, {0x0112, kShort, 1, 6}},      // Make, inside the padding
      {{0x010F, kAscii, 3, 0}, {0x0112, kShort, 1, 8}},       // a short string
      {{0x011A, kRational, 1, 4000}, {0x0112, kShort, 1, 5}}, // XResolution, outside
      {{0x011A, kRational, 1, 40}, {0x0112, kShort, 1, 5}},   // inside
      {{0x013F, kRational, 6, 40}, {0x0112, kShort, 1, 7}},   // PrimaryChromaticities: 48 bytes from 40
      {{0x0112, kShort, 1, 3}, {0x010F, kAscii, 40, 1000}},   // orientation first
      {{0x0112, kShort, 1, 2}, {0x0112, kShort, 1, 6}},       // the first of two wins
      {{0x9999, kShort, 1, 1}, {0x0112, kShort, 1, 6}},       // an unknown tag
  };
  for (size_t i = 0; i < cases.size(); ++i) {
    for (bool little : {true, false}) {
      const auto file = WithApp1(jpeg, ExifApp1(ExifBlock(little, cases[i], 64)));
      EXPECT_TRUE(ExpectSameAsOpenCv(file, "case " + std::to_string(i)));
    }
  }
  // Only the first APP1 segment is read: an XMP packet before the EXIF block hides it.
  const std::string xmp = "http://ns.adobe.com/xap/1.0/";
  std::vector<uint8_t> xmp_payload(xmp.begin(), xmp.end());
  xmp_payload.push_back(0);
  const auto exif_second = WithApp1(WithApp1(jpeg, ExifApp1(ExifBlock(true, {{0x0112, kShort, 1, 6}}))), xmp_payload);
  EXPECT_TRUE(ExpectSameAsOpenCv(exif_second, "XMP first"));
  EXPECT_EQ(Native(exif_second).size(), cv::Size(44, 30));
  // Not read at all when not asked.
  const auto turned = WithApp1(jpeg, ExifApp1(ExifBlock(true, {{0x0112, kShort, 1, 6}})));
  EXPECT_EQ(DecodeJpeg(turned, 100, true, false)->size(), cv::Size(44, 30));
  EXPECT_EQ(DecodeJpeg(turned, 100, true, true)->size(), cv::Size(30, 44));
}

TEST(ImageDecoders, PngExifOrientationAsOpenCvAppliesIt) {
  for (uint32_t orientation = 1; orientation <= 8; ++orientation) {
    const auto png = MakePng({.colour_type = PNG_COLOR_TYPE_RGB, .bit_depth = 8, .interlaced = false, .transparency = false, .gamma = false, .exif = ExifBlock(orientation % 2 == 0, {{0x0112, 3, 1, orientation}})});
    EXPECT_TRUE(ExpectSameAsOpenCv(png, "PNG orientation " + std::to_string(orientation)));
  }
}

TEST(ImageDecoders, ExifOrientationOfDamagedBlocksIsAsStored) {
  EXPECT_EQ(ExifOrientation({}), 1);
  const std::vector<uint8_t> header_only = {'I', 'I', 42, 0};
  EXPECT_EQ(ExifOrientation(header_only), 1);
  auto block = ExifBlock(true, {{0x0112, 3, 1, 6}});
  EXPECT_EQ(ExifOrientation(block), 6);
  block[2] = 43;  // not the TIFF mark
  EXPECT_EQ(ExifOrientation(block), 1);
  auto far = ExifBlock(false, {{0x0112, 3, 1, 6}});
  far[7] = 200;  // the first directory outside the block
  EXPECT_EQ(ExifOrientation(far), 1);
  auto cut = ExifBlock(true, {{0x0112, 3, 1, 6}});
  cut.resize(18);  // the entry cut before its value
  EXPECT_EQ(ExifOrientation(cut), 1);
}

TEST(ImageDecoders, ColourPnmIsLeftToOpenCv) {
  cv::Mat colour = Card();
  std::vector<uint8_t> ppm;
  ASSERT_TRUE(cv::imencode(".ppm", colour, ppm));
  const auto header = ReadImageHeader(ppm);
  ASSERT_TRUE(header.has_value());
  EXPECT_TRUE(DecodePgmGray(ppm, header->width, header->height, 255, 0).empty());
  // image.cc still decodes it, through OpenCV.
  const auto decoded = DecodeImage(ppm);
  ASSERT_TRUE(decoded.has_value()) << decoded.error().message;
  EXPECT_EQ(decoded->gray.width, 44);
}

}  // namespace
}  // namespace oxbow::sift::internal
