// Hostile images through the real service path (api::Service Search and AddImage): decompression
// bombs, huge and empty declared sizes, a 1-pixel-high panorama, animated GIF, multi-page TIFF, CMYK
// JPEG, 16-bit PNG/TIFF, grey+alpha and palette PNG. Every input is generated in code. Each gets a
// clear error (the HTTP status follows from the error code, server/http/errors.h) or a documented bounded
// result, and a refused add leaves the index unchanged.
//
// PeakMemory measures the resident-memory high-water mark of one search per input in a fresh child
// process (this binary re-executed; /proc/self/clear_refs resets VmHWM after set-up) and checks it
// against the bound stated in server/README.md ("Limits and hostile input"):
//   peak <= 32 MiB + 4 B x declared pixels + 112 B x pixels after downscaling to max_image_side
//           (the SIFT pyramid of the 2x-upsampled first octave: 28 floats per pixel).
// `OXBOW_MEASURE_ALL=1` adds the slow rows (a real 100-megapixel photo, allowed by a raised limit);
// scripts/resource_limits.sh prints the whole table.
#include <fcntl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <gtest/gtest.h>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <random>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#ifdef OXBOW_HAVE_LIBJPEG
#include <jpeglib.h>
#endif

#include "api/service.h"
#include "server/http/errors.h"
#include "sift/base/binary_io.h"
#include "sift/image.h"
#include "tests/support/e2e.h"
#include "tests/support/hostile_images.h"
#include "tests/support/samples.h"
#include "tests/support/temp_dir.h"

namespace oxbow {
namespace {

using Bytes = std::vector<uint8_t>;
using oxbow::testing::RandomVocabulary;
using oxbow::testing::Texture;

// ---- Generators -----------------------------------------------------------------------------------

void PutBe32(Bytes& out, uint32_t v) {
  for (int s = 24; s >= 0; s -= 8) out.push_back(static_cast<uint8_t>(v >> s));
}

void AppendPngChunk(Bytes& png, const char* type, const Bytes& data) {
  PutBe32(png, static_cast<uint32_t>(data.size()));
  const size_t type_at = png.size();
  png.insert(png.end(), type, type + 4);
  png.insert(png.end(), data.begin(), data.end());
  PutBe32(png, io::Crc32(std::span<const uint8_t>(png.data() + type_at, 4 + data.size())));
}

// A PNG written by hand (stored, i.e. uncompressed, deflate blocks), so that colour types OpenCV cannot
// write (grey+alpha, palette) can be tested. `rows` holds height scanlines of raw samples (the filter
// byte 0 is added here). `palette` is RGB triples for colour type 3.
Bytes HandMadePng(uint32_t width, uint32_t height, uint8_t bit_depth, uint8_t color_type, const Bytes& rows,
                  const Bytes& palette = {}) {
  const size_t row_bytes = rows.size() / height;
  Bytes raw;
  for (uint32_t y = 0; y < height; ++y) {
    raw.push_back(0);
    raw.insert(raw.end(), rows.begin() + static_cast<long>(y * row_bytes), rows.begin() + static_cast<long>((y + 1) * row_bytes));
  }
  Bytes zlib = {0x78, 0x01};
  for (size_t at = 0; at < raw.size() || at == 0; at += 65535) {
    const size_t n = std::min<size_t>(65535, raw.size() - at);
    zlib.push_back(at + n >= raw.size() ? 1 : 0);
    zlib.push_back(static_cast<uint8_t>(n));
    zlib.push_back(static_cast<uint8_t>(n >> 8));
    zlib.push_back(static_cast<uint8_t>(~n));
    zlib.push_back(static_cast<uint8_t>((~n) >> 8));
    zlib.insert(zlib.end(), raw.begin() + static_cast<long>(at), raw.begin() + static_cast<long>(at + n));
    if (n == 0) break;
  }
  uint32_t a = 1, b = 0;  // Adler-32 of the uncompressed data
  for (uint8_t v : raw) {
    a = (a + v) % 65521;
    b = (b + a) % 65521;
  }
  PutBe32(zlib, (b << 16) | a);
  Bytes png = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  Bytes ihdr;
  PutBe32(ihdr, width);
  PutBe32(ihdr, height);
  ihdr.insert(ihdr.end(), {bit_depth, color_type, 0, 0, 0});
  AppendPngChunk(png, "IHDR", ihdr);
  if (!palette.empty()) AppendPngChunk(png, "PLTE", palette);
  AppendPngChunk(png, "IDAT", zlib);
  AppendPngChunk(png, "IEND", {});
  return png;
}

Bytes Encode(const std::string& ext, const cv::Mat& image, const std::vector<int>& params = {}) {
  std::vector<uchar> out;
  EXPECT_TRUE(cv::imencode(ext, image, out, params)) << ext;
  return Bytes(out.begin(), out.end());
}

// Rewrites a PNG's IHDR width/height (and its CRC): the rest of the file stays as it was.
Bytes PatchPngSize(Bytes png, uint32_t width, uint32_t height) {
  for (int i = 0; i < 4; ++i) {
    png[16 + i] = static_cast<uint8_t>(width >> (24 - 8 * i));
    png[20 + i] = static_cast<uint8_t>(height >> (24 - 8 * i));
  }
  const uint32_t crc = io::Crc32(std::span<const uint8_t>(png.data() + 12, 17));
  for (int i = 0; i < 4; ++i) png[29 + i] = static_cast<uint8_t>(crc >> (24 - 8 * i));
  return png;
}

// Rewrites the first start-of-frame of a JPEG to declare width x height.
Bytes PatchJpegSize(const Bytes& jpeg, uint16_t width, uint16_t height) {
  Bytes patched = sift::testing::WithJpegFrameSize(jpeg, width, height);
  EXPECT_NE(patched, jpeg) << "no SOF marker";
  return patched;
}

// A two-frame animated GIF89a (NETSCAPE looping extension), 1x1 frames on a 64x64 screen.
Bytes AnimatedGif() {
  Bytes gif = {'G', 'I', 'F', '8', '9', 'a', 64, 0, 64, 0, 0x80, 0, 0, 0, 0, 0, 255, 255, 255};
  const Bytes loop = {0x21, 0xFF, 0x0B, 'N', 'E', 'T', 'S', 'C', 'A', 'P', 'E', '2', '.', '0', 3, 1, 0, 0, 0};
  gif.insert(gif.end(), loop.begin(), loop.end());
  for (int frame = 0; frame < 2; ++frame) {
    const Bytes f = {0x21, 0xF9, 4, 0, 10, 0, 0, 0,          // graphic control: 0.1 s delay
                     0x2C, 0, 0, 0, 0, 1, 0, 1, 0, 0,        // image descriptor 1x1
                     2, 2, 0x44, 0x01, 0};                   // LZW: clear, index 0, end
    gif.insert(gif.end(), f.begin(), f.end());
  }
  gif.push_back(0x3B);
  return gif;
}

// Two-page TIFF: a 320x240 first page, a 640x480 second page.
Bytes TwoPageTiff(const std::string& dir) {
  const std::string path = dir + "/two-pages.tiff";
  EXPECT_TRUE(cv::imwritemulti(path, std::vector<cv::Mat>{Texture(320, 240), Texture(640, 480)}));
  return testing::ReadBytes(path);
}

#ifdef OXBOW_HAVE_LIBJPEG
// A CMYK JPEG (4 components, as print workflows write them) of `grey`, stored the way Photoshop stores
// CMYK (Adobe APP14 marker, inverted samples: 255 = no ink): C = M = Y = 255, K = grey.
Bytes CmykJpeg(const cv::Mat& grey) {
  jpeg_compress_struct cinfo;
  jpeg_error_mgr jerr;
  cinfo.err = jpeg_std_error(&jerr);
  jpeg_create_compress(&cinfo);
  unsigned char* buffer = nullptr;
  unsigned long size = 0;
  jpeg_mem_dest(&cinfo, &buffer, &size);
  cinfo.image_width = static_cast<JDIMENSION>(grey.cols);
  cinfo.image_height = static_cast<JDIMENSION>(grey.rows);
  cinfo.input_components = 4;
  cinfo.in_color_space = JCS_CMYK;
  jpeg_set_defaults(&cinfo);
  jpeg_set_quality(&cinfo, 95, TRUE);
  jpeg_start_compress(&cinfo, TRUE);
  std::vector<unsigned char> row(static_cast<size_t>(grey.cols) * 4);
  while (cinfo.next_scanline < cinfo.image_height) {
    const uint8_t* in = grey.ptr<uint8_t>(static_cast<int>(cinfo.next_scanline));
    for (int x = 0; x < grey.cols; ++x) {
      row[4 * x] = row[4 * x + 1] = row[4 * x + 2] = 255;
      row[4 * x + 3] = in[x];
    }
    JSAMPROW rows[1] = {row.data()};
    jpeg_write_scanlines(&cinfo, rows, 1);
  }
  jpeg_finish_compress(&cinfo);
  Bytes out(buffer, buffer + size);
  jpeg_destroy_compress(&cinfo);
  std::free(buffer);
  return out;
}
#endif

// ---- The service under test ---------------------------------------------------------------------------

class ResourceLimitsTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new oxbow::testing::TempDir("oxbow-limits-test");
    vocab_ = dir_->path() + "/vocab.oxvoc";
    auto vocabulary = RandomVocabulary(testing::TestSiftOptions().Describe());
    ASSERT_TRUE(vocabulary->Write(vocab_));
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }

  std::unique_ptr<api::Service> OpenService(const api::ServiceOptions& options = {}) {
    auto service = api::Service::Open(dir_->path() + "/index-" + std::to_string(counter_++), vocab_, options);
    EXPECT_TRUE(service) << service.error().ToString();
    return service ? std::move(*service) : nullptr;
  }

  // Search and add `bytes`; both must fail with `code`, and the refused add must leave the index as it was.
  static void ExpectRefused(api::Service& service, const Bytes& bytes, ErrorCode code, int http_status) {
    const uint64_t before = service.Stats().index.num_images;
    auto found = service.Search(bytes, service.options().default_query);
    ASSERT_FALSE(found) << "search accepted it";
    EXPECT_EQ(found.error().code, code) << found.error().ToString();
    EXPECT_EQ(server::ToHttpError(found.error()).status, http_status);
    EXPECT_FALSE(found.error().message.empty());
    api::AddImageRequest add;
    add.id = "hostile-" + std::to_string(before);
    add.image = bytes;
    auto added = service.AddImage(add);
    ASSERT_FALSE(added) << "add accepted it";
    EXPECT_EQ(added.error().code, code) << added.error().ToString();
    EXPECT_EQ(service.Stats().index.num_images, before);
    EXPECT_FALSE(service.GetImage(add.id)) << "a refused add left a record";
  }

  // Search and add `bytes`; both must succeed; returns the added record.
  static index::ImageRecord ExpectAccepted(api::Service& service, const Bytes& bytes, const std::string& id) {
    auto found = service.Search(bytes, service.options().default_query);
    EXPECT_TRUE(found) << found.error().ToString();
    api::AddImageRequest add;
    add.id = id;
    add.image = bytes;
    auto added = service.AddImage(add);
    EXPECT_TRUE(added) << added.error().ToString();
    return added ? added->record : index::ImageRecord{};
  }

  static inline oxbow::testing::TempDir* dir_ = nullptr;
  static inline std::string vocab_;
  static inline int counter_ = 0;
};

TEST_F(ResourceLimitsTest, DecompressionBombsAreRefusedFromTheHeader) {
  auto service = OpenService();
  ASSERT_TRUE(service);
  // A 16x16 PNG whose header says 60000 x 60000 (3.6 gigapixels): refused before any pixel is allocated.
  const Bytes png = PatchPngSize(Encode(".png", Texture(16, 16)), 60000, 60000);
  ASSERT_LT(png.size(), 2000u);
  ExpectRefused(*service, png, ErrorCode::kImageTooLarge, 413);
  // The same for JPEG (the largest size a JPEG frame can declare) and a 100-megapixel JPEG header.
  const Bytes jpeg = Encode(".jpg", Texture(64, 48));
  ExpectRefused(*service, PatchJpegSize(jpeg, 65535, 65535), ErrorCode::kImageTooLarge, 413);
  ExpectRefused(*service, PatchJpegSize(jpeg, 12000, 8400), ErrorCode::kImageTooLarge, 413);
  // A real deflate bomb inside the pixel limit: 6000 x 6000 flat grey compresses ~1000:1. It decodes
  // (36 MB, within --max-megapixels 40), is downscaled to 1600 px and has no features: a bounded result.
  const Bytes flat = Encode(".png", cv::Mat(6000, 6000, CV_8UC1, cv::Scalar(90)));
  ASSERT_LT(flat.size(), 100'000u);
  auto found = service->Search(flat, service->options().default_query);
  ASSERT_TRUE(found) << found.error().ToString();
  EXPECT_EQ(found->query_width, 6000);
  EXPECT_EQ(found->extracted_features, 0u);
  EXPECT_TRUE(found->index.results.empty());
  // With a lower limit the same file is refused from its header.
  api::ServiceOptions strict;
  strict.max_pixels = 20'000'000;
  auto strict_service = OpenService(strict);
  ASSERT_TRUE(strict_service);
  ExpectRefused(*strict_service, flat, ErrorCode::kImageTooLarge, 413);
}

TEST_F(ResourceLimitsTest, EmptyAndDegenerateSizes) {
  auto service = OpenService();
  ASSERT_TRUE(service);
  const Bytes png = Encode(".png", Texture(16, 16));
  ExpectRefused(*service, PatchPngSize(png, 0, 0), ErrorCode::kInvalidImage, 400);
  ExpectRefused(*service, PatchPngSize(png, 16, 0), ErrorCode::kInvalidImage, 400);
  ExpectRefused(*service, PatchJpegSize(Encode(".jpg", Texture(16, 16)), 16, 0), ErrorCode::kInvalidImage, 400);
  // A size the header does not match: 16x16 data under a 32x32 header is corrupt, not a crash.
  ExpectRefused(*service, PatchPngSize(png, 32, 32), ErrorCode::kInvalidImage, 400);

  // A 1-pixel-high panorama (8000 x 1) decodes, is downscaled to 1600 x 1 and has no features: it can be
  // added (a record with 0 features, found by nothing) and searched (no results).
  const Bytes panorama = Encode(".png", Texture(8000, 1));
  const index::ImageRecord record = ExpectAccepted(*service, panorama, "panorama");
  EXPECT_EQ(record.width, 8000u);
  EXPECT_EQ(record.height, 1u);
  EXPECT_EQ(record.num_features, 0u);
  // Tall and thin, and a single pixel, behave the same way.
  ExpectAccepted(*service, Encode(".png", Texture(1, 5000)), "tower");
  ExpectAccepted(*service, Encode(".png", Texture(1, 1)), "dot");
  EXPECT_EQ(service->Stats().index.num_images, 3u);
}

TEST_F(ResourceLimitsTest, AnimatedAndMultiPageFiles) {
  auto service = OpenService();
  ASSERT_TRUE(service);
  // GIF (animated or not) is a known image format OpenCV 4.6 cannot decode: 415, not "not an image".
  ExpectRefused(*service, AnimatedGif(), ErrorCode::kUnsupportedFormat, 415);

  // A multi-page TIFF: the first page is used (documented); the second, larger page is never decoded.
  const Bytes tiff = TwoPageTiff(dir_->path());
  if (!cv::haveImageReader(dir_->path() + "/two-pages.tiff")) GTEST_SKIP() << "this OpenCV cannot read TIFF";
  const index::ImageRecord record = ExpectAccepted(*service, tiff, "two-pages");
  EXPECT_EQ(record.width, 320u);
  EXPECT_EQ(record.height, 240u);
  EXPECT_GT(record.num_features, 20u);
}

TEST_F(ResourceLimitsTest, ColourModelsAndBitDepthsDecodeToTheSameGrey) {
  const cv::Mat grey = Texture(200, 160);
  auto decode = [](const Bytes& bytes) { return sift::DecodeImage(bytes); };
  auto expect_grey = [&](const Bytes& bytes, int tolerance, const char* what) {
    auto decoded = decode(bytes);
    ASSERT_TRUE(decoded) << what << ": " << decoded.error().ToString();
    ASSERT_EQ(decoded->gray.width, 200) << what;
    ASSERT_EQ(decoded->gray.height, 160) << what;
    int worst = 0;
    for (int y = 0; y < 160; ++y)
      for (int x = 0; x < 200; ++x)
        worst = std::max(worst, std::abs(static_cast<int>(std::lround(decoded->gray.at(x, y) * 255)) - grey.at<uint8_t>(y, x)));
    EXPECT_LE(worst, tolerance) << what;
  };
  // 16-bit PNG and TIFF: the high byte is the 8-bit value.
  cv::Mat grey16;
  grey.convertTo(grey16, CV_16U, 257.0);
  expect_grey(Encode(".png", grey16), 0, "16-bit PNG");
  if (cv::haveImageWriter(".tiff")) expect_grey(Encode(".tiff", grey16), 1, "16-bit TIFF");
  // Grey + alpha (colour type 4) and an 8-bit palette (type 3) PNG, written by hand.
  Bytes grey_alpha, indices, palette;
  for (int y = 0; y < 160; ++y) {
    for (int x = 0; x < 200; ++x) {
      const uint8_t v = grey.at<uint8_t>(y, x);
      grey_alpha.insert(grey_alpha.end(), {v, static_cast<uint8_t>(x)});
      indices.push_back(v);
    }
  }
  for (int v = 0; v < 256; ++v) palette.insert(palette.end(), {static_cast<uint8_t>(v), static_cast<uint8_t>(v), static_cast<uint8_t>(v)});
  expect_grey(HandMadePng(200, 160, 8, 4, grey_alpha), 0, "grey+alpha PNG");
  expect_grey(HandMadePng(200, 160, 8, 3, indices, palette), 1, "palette PNG");
  // A 16-bit grey+alpha PNG: 4 bytes per pixel, big-endian samples.
  Bytes grey_alpha16;
  for (int y = 0; y < 160; ++y)
    for (int x = 0; x < 200; ++x) grey_alpha16.insert(grey_alpha16.end(), {grey.at<uint8_t>(y, x), grey.at<uint8_t>(y, x), 255, 255});
  expect_grey(HandMadePng(200, 160, 16, 4, grey_alpha16), 0, "16-bit grey+alpha PNG");
#ifdef OXBOW_HAVE_LIBJPEG
  // CMYK JPEG (Adobe-inverted, no ink but black): decoded to the same grey within JPEG loss.
  expect_grey(CmykJpeg(grey), 12, "CMYK JPEG");
#endif
  // Colour with alpha (RGBA PNG): the grey of the colour part.
  cv::Mat rgba;
  cv::cvtColor(grey, rgba, cv::COLOR_GRAY2BGRA);
  expect_grey(Encode(".png", rgba), 1, "RGBA PNG");
}

TEST_F(ResourceLimitsTest, SixteenBitAndCmykImagesAreIndexedAndFound) {
  auto service = OpenService();
  ASSERT_TRUE(service);
  const cv::Mat grey = Texture(400, 320);
  cv::Mat grey16;
  grey.convertTo(grey16, CV_16U, 257.0);
  const index::ImageRecord eight = ExpectAccepted(*service, Encode(".png", grey), "eight-bit");
  const index::ImageRecord sixteen = ExpectAccepted(*service, Encode(".png", grey16), "sixteen-bit");
  EXPECT_GT(eight.num_features, 50u);
  EXPECT_EQ(sixteen.num_features, eight.num_features);
#ifdef OXBOW_HAVE_LIBJPEG
  const index::ImageRecord cmyk = ExpectAccepted(*service, CmykJpeg(grey), "cmyk");
  EXPECT_GT(cmyk.num_features, eight.num_features / 2);
#endif
  EXPECT_GE(service->Stats().index.num_images, 2u);
}

// ---- Peak memory per request ------------------------------------------------------------------------

// A VmRSS / VmHWM line of /proc/<process>/status ("self" or a pid), bytes.
uint64_t StatusBytes(const std::string& process, const char* field) {
  std::ifstream status("/proc/" + process + "/status");
  std::string line;
  while (std::getline(status, line)) {
    if (line.rfind(field, 0) == 0) return std::stoull(line.substr(std::strlen(field) + 1)) * 1024;
  }
  return 0;
}

// One hostile or large input for the memory table.
struct MemoryCase {
  std::string name;
  std::function<Bytes()> make;
  uint64_t declared_width = 0, declared_height = 0;
  double max_megapixels = 40;  // the serve --max-megapixels the case runs under
  bool slow = false;           // only with OXBOW_MEASURE_ALL=1
};

// The stated bound (server/README.md, "Limits and hostile input"): a fixed 32 MiB (decoder state, allocator slack, the SIFT work of
// small images) + 4 B per declared pixel (the 8-bit grey decode, 16-bit samples, the resize source) +
// 112 B per pixel of the image after downscaling to --max-image-side (the SIFT pyramid of the
// 2x-upsampled first octave, sift.h: 28 floats per pixel). Images refused from the header: 32 MiB.
uint64_t PeakBound(uint64_t width, uint64_t height, double max_megapixels, int max_side) {
  const uint64_t declared = width * height;
  if (declared > static_cast<uint64_t>(max_megapixels * 1e6)) return 32ull << 20;
  const double scale = std::min(1.0, static_cast<double>(max_side) / static_cast<double>(std::max(width, height)));
  const uint64_t extracted = static_cast<uint64_t>(std::ceil(width * scale) * std::ceil(height * scale));
  return (32ull << 20) + 4 * declared + 112 * extracted;
}

std::vector<MemoryCase> MemoryCases(const std::string& dir) {
  auto jpeg = [](int w, int h, bool progressive) {
    return Encode(".jpg", Texture(w, h), {cv::IMWRITE_JPEG_QUALITY, 90, cv::IMWRITE_JPEG_PROGRESSIVE, progressive ? 1 : 0});
  };
  std::vector<MemoryCase> cases = {
      {"PNG header 60000x60000 (bomb)", [] { return PatchPngSize(Encode(".png", Texture(16, 16)), 60000, 60000); }, 60000, 60000},
      {"JPEG header 65535x65535 (bomb)", [] { return PatchJpegSize(Encode(".jpg", Texture(64, 48)), 65535, 65535); }, 65535, 65535},
      {"JPEG header 12000x8400 (100 MP)", [] { return PatchJpegSize(Encode(".jpg", Texture(64, 48)), 12000, 8400); }, 12000, 8400},
      {"PNG 0x0", [] { return PatchPngSize(Encode(".png", Texture(16, 16)), 0, 0); }, 0, 0},
      {"animated GIF", [] { return AnimatedGif(); }, 64, 64},
      {"flat PNG 6000x6000 (deflate bomb)", [] { return Encode(".png", cv::Mat(6000, 6000, CV_8UC1, cv::Scalar(90))); }, 6000, 6000},
      {"PNG 8000x1 panorama", [] { return Encode(".png", Texture(8000, 1)); }, 8000, 1},
      {"JPEG 1024x768 (typical photo)", [=] { return jpeg(1024, 768, false); }, 1024, 768},
      {"JPEG 4000x3000 progressive", [=] { return jpeg(4000, 3000, true); }, 4000, 3000},
      {"16-bit PNG 2000x1600", [] {
         cv::Mat grey16;
         Texture(2000, 1600).convertTo(grey16, CV_16U, 257.0);
         return Encode(".png", grey16);
       }, 2000, 1600},
      {"two-page TIFF 320x240 + 640x480", [=] { return TwoPageTiff(dir); }, 320, 240},
#ifdef OXBOW_HAVE_LIBJPEG
      {"CMYK JPEG 2000x1600", [] { return CmykJpeg(Texture(2000, 1600)); }, 2000, 1600},
#endif
      {"JPEG 7300x5470 baseline (40 MP)", [=] { return jpeg(7300, 5470, false); }, 7300, 5470, 40, true},
      {"JPEG 7300x5470 progressive (40 MP)", [=] { return jpeg(7300, 5470, true); }, 7300, 5470, 40, true},
      {"JPEG 12000x8400 (100 MP, --max-megapixels 120)", [=] { return jpeg(12000, 8400, false); }, 12000, 8400, 120, true},
  };
  return cases;
}

// The child side: one search of the file $OXBOW_MEASURE_INPUT on a fresh index, production SIFT
// settings; prints "OXBOW_MEASURE status=<http status> peak=<bytes over the pre-request RSS>".
// Disabled: only PeakMemoryPerSearchStaysUnderTheBound runs it, in a child process.
TEST(ResourceLimitsMeasure, DISABLED_OneSearch) {
  const char* input = std::getenv("OXBOW_MEASURE_INPUT");
  ASSERT_NE(input, nullptr) << "run by PeakMemoryPerSearchStaysUnderTheBound in a child process";
  api::ServiceOptions options;
  // This measures memory: a loaded machine must not turn a slow extraction into a 503 at the deadline.
  options.processing_timeout_ms = 3'600'000;
  // The parent sets every variable; a missing one reads as "" (std::stoull throws: a test error, not a crash).
  const auto env = [](const char* name) {
    const char* value = std::getenv(name);
    return std::string(value != nullptr ? value : "");
  };
  options.max_pixels = std::stoull(env("OXBOW_MEASURE_MAX_PIXELS"));
  options.threads_per_request = 1;
  options.add_nice = 0;
  auto service = api::Service::Open(env("OXBOW_MEASURE_INDEX"), env("OXBOW_MEASURE_VOCAB"), options);
  ASSERT_TRUE(service) << service.error().ToString();
  const Bytes bytes = testing::ReadBytes(input);
  {
    std::ofstream clear("/proc/self/clear_refs");
    clear << "5";  // resets VmHWM to the current RSS (Linux >= 4.0)
  }
  const uint64_t before = StatusBytes("self", "VmRSS:");
  auto found = (*service)->Search(bytes, (*service)->options().default_query);
  const uint64_t peak = StatusBytes("self", "VmHWM:");
  const int status = found ? 200 : server::ToHttpError(found.error()).status;
  std::printf("OXBOW_MEASURE status=%d peak=%llu code=%s\n", status, static_cast<unsigned long long>(peak - std::min(peak, before)),
              found ? "ok" : std::string(ErrorCodeName(found.error().code)).c_str());
  std::fflush(stdout);
}

TEST_F(ResourceLimitsTest, PeakMemoryPerSearchStaysUnderTheBound) {
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
  GTEST_SKIP() << "sanitizer builds add shadow memory: the bound is for release builds";
#endif
  {
    std::ofstream clear("/proc/self/clear_refs");
    clear << "5";
    if (!clear) GTEST_SKIP() << "/proc/self/clear_refs is not writable here: cannot measure peak memory";
  }
  const bool all = std::getenv("OXBOW_MEASURE_ALL") != nullptr;
  const std::string vocab = dir_->path() + "/vocab-default-sift.oxvoc";
  sift::SiftOptions production;  // the server's extractor: `oxbow vocab train` defaults (RootSIFT, 2x first octave)
  production.descriptor = sift::DescriptorKind::kRootSift;
  ASSERT_TRUE(RandomVocabulary(production.Describe())->Write(vocab));
  // NOLINTNEXTLINE(bugprone-unchecked-optional-access): the default is set (value() would throw otherwise)
  const int max_side = api::ServiceOptions{}.max_image_side_px.value();
  std::printf("| input | declared size | file bytes | --max-megapixels | result | peak memory (MiB) | bound (MiB) |\n"
              "|---|---|---:|---:|---|---:|---:|\n");
  int n = 0;
  for (const MemoryCase& c : MemoryCases(dir_->path())) {
    if (c.slow && !all) continue;
    const Bytes bytes = c.make();
    const std::string input = dir_->path() + "/input-" + std::to_string(n++);
    std::ofstream(input, std::ios::binary).write(reinterpret_cast<const char*>(bytes.data()), static_cast<long>(bytes.size()));
    int out[2];
    ASSERT_EQ(pipe(out), 0);
    const pid_t pid = fork();
    if (pid == 0) {
      dup2(out[1], STDOUT_FILENO);
      close(out[0]);
      setenv("OXBOW_MEASURE_INPUT", input.c_str(), 1);
      setenv("OXBOW_MEASURE_MAX_PIXELS", std::to_string(static_cast<uint64_t>(c.max_megapixels * 1e6)).c_str(), 1);
      setenv("OXBOW_MEASURE_INDEX", (input + "-index").c_str(), 1);
      setenv("OXBOW_MEASURE_VOCAB", vocab.c_str(), 1);
      execl("/proc/self/exe", "resource_limits_test", "--gtest_filter=ResourceLimitsMeasure.DISABLED_OneSearch",
            "--gtest_also_run_disabled_tests", nullptr);
      _exit(127);
    }
    close(out[1]);
    std::string text;
    char buf[4096];
    for (ssize_t r; (r = read(out[0], buf, sizeof buf)) > 0;) text.append(buf, static_cast<size_t>(r));
    close(out[0]);
    int wstatus = 0;
    waitpid(pid, &wstatus, 0);
    ASSERT_TRUE(WIFEXITED(wstatus) && WEXITSTATUS(wstatus) == 0) << c.name << ": the child crashed or failed\n" << text;
    const size_t at = text.find("OXBOW_MEASURE ");
    ASSERT_NE(at, std::string::npos) << text;
    int status = 0;
    unsigned long long peak = 0;
    char code[64] = {};
    ASSERT_EQ(std::sscanf(text.c_str() + at, "OXBOW_MEASURE status=%d peak=%llu code=%63s", &status, &peak, code), 3);
    const uint64_t bound = PeakBound(c.declared_width, c.declared_height, c.max_megapixels, max_side);
    std::printf("| %s | %llux%llu | %zu | %g | %d %s | %.1f | %.1f |\n", c.name.c_str(),
                static_cast<unsigned long long>(c.declared_width), static_cast<unsigned long long>(c.declared_height),
                bytes.size(), c.max_megapixels, status, code, peak / 1048576.0, bound / 1048576.0);
    std::fflush(stdout);
    EXPECT_TRUE(status == 200 || status == 400 || status == 413 || status == 415) << c.name << ": " << status << " " << code;
    EXPECT_LE(peak, bound) << c.name;
  }
}

// The server's memory grows with --extractions, not with --threads: SIFT keeps pyramid buffers per thread
// that extracts, so extractions run on service-owned threads (on the HTTP workers' own threads, 32
// concurrent searches with 32 workers and 2 extraction slots would peak at 7 GiB). Compared with one search alone, eight at once (eight HTTP
// workers, one extraction slot) may only add their request bodies.
TEST_F(ResourceLimitsTest, ConcurrentSearchesCostWhatTheExtractionSlotsAllow) {
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
  GTEST_SKIP() << "sanitizer builds add shadow memory";
#endif
  oxbow::testing::ServerProcess server({"serve", "--index", dir_->path() + "/concurrent", "--vocab", vocab_, "--port", "0",
                                        "--http-workers", "8", "--extractions", "1", "--extraction-wait-ms", "120000"},
                                       dir_->path() + "/concurrent.log");
  ASSERT_TRUE(server.port() > 0 && server.WaitReady()) << server.Log();
  auto reset_peak = [&] {
    std::ofstream clear("/proc/" + std::to_string(server.pid()) + "/clear_refs");
    clear << "5";
    return static_cast<bool>(clear);
  };
  if (!reset_peak()) GTEST_SKIP() << "cannot reset the server's VmHWM here";
  const Bytes jpeg = Encode(".jpg", Texture(1600, 1200), {cv::IMWRITE_JPEG_QUALITY, 90});
  const std::string body(jpeg.begin(), jpeg.end());
  auto search = [&] {
    auto res = server.Client().Post("/v1/search", body, "image/jpeg");
    return res ? res->status : -1;
  };
  const uint64_t before_one = StatusBytes(std::to_string(server.pid()), "VmRSS:");
  ASSERT_EQ(search(), 200);
  const uint64_t one = StatusBytes(std::to_string(server.pid()), "VmHWM:") - before_one;
  ASSERT_TRUE(reset_peak());
  const uint64_t before_many = StatusBytes(std::to_string(server.pid()), "VmRSS:");
  std::vector<int> statuses(8, 0);
  std::vector<std::thread> clients;
  for (size_t i = 0; i < statuses.size(); ++i) clients.emplace_back([&, i] { statuses[i] = search(); });
  for (auto& t : clients) t.join();
  const uint64_t many = StatusBytes(std::to_string(server.pid()), "VmHWM:") - before_many;
  for (int status : statuses) EXPECT_EQ(status, 200);
  std::printf("one search: +%.1f MiB; eight at once with one extraction slot: +%.1f MiB\n", one / 1048576.0, many / 1048576.0);
  EXPECT_GT(one, 16u << 20) << "the first extraction should allocate its pyramid";
  EXPECT_LE(many, one / 2 + 8 * body.size() * 3) << "concurrent searches allocated pyramids beyond the extraction slots";
}

}  // namespace
}  // namespace oxbow
