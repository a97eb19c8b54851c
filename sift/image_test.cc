#include "sift/image.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <fcntl.h>
#include <unistd.h>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "sift/base/binary_io.h"
#include "tests/support/hostile_images.h"
#include "tests/support/temp_dir.h"

namespace oxbow::sift {
namespace {

const std::string kOpencvData = "/usr/share/doc/opencv-doc/examples/data/";

// A 64x48 test card: horizontal ramp plus a bright square in the top-left corner (so orientation
// changes are visible).
cv::Mat TestCard() {
  cv::Mat m(48, 64, CV_8U);
  for (int y = 0; y < m.rows; ++y)
    for (int x = 0; x < m.cols; ++x) m.at<uint8_t>(y, x) = static_cast<uint8_t>(40 + 2 * x);
  m(cv::Rect(2, 2, 10, 10)).setTo(250);
  return m;
}

std::vector<uint8_t> Encode(const cv::Mat& m, const std::string& ext) {
  std::vector<uint8_t> bytes;
  EXPECT_TRUE(cv::imencode(ext, m, bytes)) << ext;
  return bytes;
}

double MeanAbsDiff(const GrayImage& g, const cv::Mat& m) {
  double sum = 0;
  for (int y = 0; y < m.rows; ++y)
    for (int x = 0; x < m.cols; ++x) sum += std::abs(g.at(x, y) - m.at<uint8_t>(y, x) / 255.0);
  return sum / (m.rows * m.cols);
}

void PutBe32(std::vector<uint8_t>* v, uint32_t x) {
  for (int s = 24; s >= 0; s -= 8) v->push_back(static_cast<uint8_t>(x >> s));
}

// A PNG whose IHDR declares width x height (valid CRC) followed by IEND: no pixel data at all.
std::vector<uint8_t> PngHeaderOnly(uint32_t width, uint32_t height) {
  std::vector<uint8_t> v = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  PutBe32(&v, 13);
  const size_t chunk = v.size();
  for (char c : std::string("IHDR")) v.push_back(static_cast<uint8_t>(c));
  PutBe32(&v, width);
  PutBe32(&v, height);
  for (int b : {8, 0, 0, 0, 0}) v.push_back(static_cast<uint8_t>(b));  // 8-bit grey
  PutBe32(&v, io::Crc32(std::span<const uint8_t>(v).subspan(chunk, 17)));
  for (int b : {0, 0, 0, 0, int{'I'}, int{'E'}, int{'N'}, int{'D'}, 0xAE, 0x42, 0x60, 0x82}) v.push_back(static_cast<uint8_t>(b));
  return v;
}

// Inserts an EXIF APP1 segment with the given Orientation tag right after the JPEG SOI marker.
std::vector<uint8_t> WithExifOrientation(const std::vector<uint8_t>& jpeg, uint16_t orientation) {
  std::vector<uint8_t> app1 = {'E', 'x', 'i', 'f', 0, 0,                   // EXIF identifier
                               'M', 'M', 0, 42, 0, 0, 0, 8,                // big-endian TIFF header, IFD0 at 8
                               0, 1,                                       // one entry
                               0x01, 0x12, 0, 3, 0, 0, 0, 1,               // Orientation, SHORT, count 1
                               static_cast<uint8_t>(orientation >> 8), static_cast<uint8_t>(orientation), 0, 0,
                               0, 0, 0, 0};                                // no next IFD
  std::vector<uint8_t> out;
  out.reserve(jpeg.size() + app1.size() + 4);
  for (int b : {0xFF, 0xD8, 0xFF, 0xE1}) out.push_back(static_cast<uint8_t>(b));
  const size_t length = app1.size() + 2;
  out.push_back(static_cast<uint8_t>(length >> 8));
  out.push_back(static_cast<uint8_t>(length));
  out.insert(out.end(), app1.begin(), app1.end());
  out.insert(out.end(), jpeg.begin() + 2, jpeg.end());
  return out;
}

TEST(DecodeImage, DecodesEveryFormatIntoUnitRangeGrey) {
  const cv::Mat card = TestCard();
  for (const std::string ext : {".png", ".pgm", ".ppm", ".bmp", ".tiff", ".webp", ".jpg"}) {
    if (!cv::haveImageWriter("x" + ext)) continue;
    cv::Mat input = card;
    if (ext == ".ppm") cv::merge(std::vector<cv::Mat>{card, card, card}, input);
    auto decoded = DecodeImage(Encode(input, ext));
    ASSERT_TRUE(decoded) << ext << ": " << decoded.error().ToString();
    EXPECT_EQ(decoded->gray.width, 64) << ext;
    EXPECT_EQ(decoded->gray.height, 48) << ext;
    EXPECT_EQ(decoded->original_width, 64);
    EXPECT_EQ(decoded->scale_to_original, 1.0);
    const double tolerance = ext == ".jpg" || ext == ".webp" ? 0.02 : 0.003;
    EXPECT_LT(MeanAbsDiff(decoded->gray, card), tolerance) << ext;
    for (float v : decoded->gray.pixels) ASSERT_TRUE(v >= 0 && v <= 1) << ext;
  }
}

TEST(DecodeImage, ReadsHeaderDimensionsWithoutDecoding) {
  const cv::Mat card = TestCard();
  for (const std::string ext : {".png", ".pgm", ".bmp", ".tiff", ".webp", ".jpg"}) {
    if (!cv::haveImageWriter("x" + ext)) continue;
    auto info = ReadImageHeader(Encode(card, ext));
    ASSERT_TRUE(info) << ext << ": " << info.error().ToString();
    EXPECT_EQ(info->width, 64u) << ext;
    EXPECT_EQ(info->height, 48u) << ext;
  }
}

TEST(DecodeImage, ReadsARealPhotoFile) {
  auto decoded = ReadImage(kOpencvData + "graf1.png");
  ASSERT_TRUE(decoded) << decoded.error().ToString();
  EXPECT_EQ(decoded->gray.width, 800);
  EXPECT_EQ(decoded->gray.height, 640);
}

TEST(DecodeImage, DownscalesToTheLongestSideLimit) {
  DecodeOptions options;
  options.max_image_side_px = 400;
  auto decoded = ReadImage(kOpencvData + "graf1.png", options);
  ASSERT_TRUE(decoded) << decoded.error().ToString();
  EXPECT_EQ(decoded->gray.width, 400);
  EXPECT_EQ(decoded->gray.height, 320);
  EXPECT_EQ(decoded->original_width, 800);
  EXPECT_EQ(decoded->original_height, 640);
  EXPECT_DOUBLE_EQ(decoded->scale_to_original, 2.0);
  EXPECT_DOUBLE_EQ(GrayToOriginal(0.0, 2.0), 0.5);  // the first small pixel covers big pixels 0 and 1
  // Never upscales.
  options.max_image_side_px = 5000;
  decoded = ReadImage(kOpencvData + "graf1.png", options);
  ASSERT_TRUE(decoded);
  EXPECT_EQ(decoded->gray.width, 800);
}

TEST(DecodeImage, HonoursExifOrientation) {
  const cv::Mat card = TestCard();  // 64 wide, 48 high, bright square top-left
  const auto jpeg = WithExifOrientation(Encode(card, ".jpg"), 6);  // 6: display rotated 90 degrees clockwise
  auto upright = DecodeImage(jpeg);
  ASSERT_TRUE(upright) << upright.error().ToString();
  EXPECT_EQ(upright->gray.width, 48);
  EXPECT_EQ(upright->gray.height, 64);
  EXPECT_EQ(upright->original_width, 48);
  // Rotating clockwise moves the top-left square to the top-right.
  EXPECT_GT(upright->gray.at(40, 6), 0.9f);
  EXPECT_LT(upright->gray.at(6, 6), 0.8f);

  DecodeOptions raw;
  raw.apply_exif_orientation = false;
  auto stored = DecodeImage(jpeg, raw);
  ASSERT_TRUE(stored);
  EXPECT_EQ(stored->gray.width, 64);
  EXPECT_GT(stored->gray.at(6, 6), 0.9f);
}

TEST(DecodeImage, RefusesEmptyNonImageAndCorruptData) {
  auto empty = DecodeImage(std::span<const uint8_t>());
  ASSERT_FALSE(empty);
  EXPECT_EQ(empty.error().code, ErrorCode::kInvalidImage);
  EXPECT_NE(empty.error().message.find("empty"), std::string::npos);

  const std::string text = "hello, this is a text file and not an image at all\n";
  auto not_image = DecodeImage(std::span(reinterpret_cast<const uint8_t*>(text.data()), text.size()));
  ASSERT_FALSE(not_image);
  EXPECT_EQ(not_image.error().code, ErrorCode::kInvalidImage);
  EXPECT_NE(not_image.error().message.find("not an image"), std::string::npos);

  // A PNG signature followed by garbage, and a PNG whose header CRC is wrong.
  std::vector<uint8_t> garbage_png = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  for (int i = 0; i < 100; ++i) garbage_png.push_back(static_cast<uint8_t>(i * 37));
  auto corrupt = DecodeImage(garbage_png);
  ASSERT_FALSE(corrupt);
  EXPECT_EQ(corrupt.error().code, ErrorCode::kInvalidImage);
  auto png = Encode(TestCard(), ".png");
  png[20] ^= 0x01;  // flips a bit of the declared width
  auto bad_crc = DecodeImage(png);
  ASSERT_FALSE(bad_crc);
  EXPECT_EQ(bad_crc.error().code, ErrorCode::kInvalidImage);

  // A JPEG whose compressed data is overwritten with garbage after the headers.
  auto jpeg = Encode(TestCard(), ".jpg");
  std::vector<uint8_t> garbage_jpeg(jpeg.begin(), jpeg.begin() + 4);
  for (int i = 0; i < 200; ++i) garbage_jpeg.push_back(static_cast<uint8_t>(i * 13 + 1));
  auto corrupt_jpeg = DecodeImage(garbage_jpeg);
  ASSERT_FALSE(corrupt_jpeg);
  EXPECT_EQ(corrupt_jpeg.error().code, ErrorCode::kInvalidImage);
}

TEST(DecodeImage, RefusesTruncatedFiles) {
  cv::Mat photo = cv::imread(kOpencvData + "box.png", cv::IMREAD_GRAYSCALE);
  ASSERT_FALSE(photo.empty());
  for (const std::string ext : {".jpg", ".png", ".pgm", ".webp"}) {
    if (!cv::haveImageWriter("x" + ext)) continue;
    auto bytes = Encode(photo, ext);
    for (double keep : {0.3, 0.9}) {
      std::vector<uint8_t> truncated(bytes.begin(), bytes.begin() + static_cast<long>(bytes.size() * keep));
      auto decoded = DecodeImage(truncated);
      ASSERT_FALSE(decoded) << ext << " truncated to " << keep;
      EXPECT_EQ(decoded.error().code, ErrorCode::kInvalidImage) << ext;
      EXPECT_NE(decoded.error().message.find("truncated"), std::string::npos) << decoded.error().message;
    }
  }
}

TEST(DecodeImage, RefusesDeclaredOversizeBeforeAllocating) {
  const auto bomb = PngHeaderOnly(100000, 100000);  // 10^10 pixels declared in 45 bytes
  auto info = ReadImageHeader(bomb);
  ASSERT_TRUE(info) << info.error().ToString();
  EXPECT_EQ(info->width, 100000u);
  auto decoded = DecodeImage(bomb);
  ASSERT_FALSE(decoded);
  EXPECT_EQ(decoded.error().code, ErrorCode::kImageTooLarge);
  EXPECT_NE(decoded.error().message.find("100000x100000"), std::string::npos) << decoded.error().message;

  // The limit is configurable, and applies to real images too.
  DecodeOptions small;
  small.max_pixels = 1000;
  auto limited = DecodeImage(Encode(TestCard(), ".jpg"), small);
  ASSERT_FALSE(limited);
  EXPECT_EQ(limited.error().code, ErrorCode::kImageTooLarge);

  // A PNG strip within the pixel limit but taller than libpng reads is too large, not corrupt.
  auto strip = DecodeImage(PngHeaderOnly(2, 1000001));
  ASSERT_FALSE(strip);
  EXPECT_EQ(strip.error().code, ErrorCode::kImageTooLarge) << strip.error().ToString();
  EXPECT_NE(strip.error().message.find("2x1000001"), std::string::npos) << strip.error().message;
  // The same for a side over OpenCV's 2^20 (a BMP, which OpenCV decodes): an assertion inside it otherwise.
  std::vector<uint8_t> bmp = {'B', 'M'};
  const uint32_t rows = 1100000, row_bytes = 4;  // 1 x 1,100,000, 24 bits, rows padded to 4 bytes
  auto put32 = [&](uint32_t x) { for (int i = 0; i < 4; ++i) bmp.push_back(static_cast<uint8_t>(x >> (8 * i))); };
  auto put16 = [&](uint16_t x) { for (int i = 0; i < 2; ++i) bmp.push_back(static_cast<uint8_t>(x >> (8 * i))); };
  put32(54 + rows * row_bytes), put32(0), put32(54);
  put32(40), put32(1), put32(rows), put16(1), put16(24), put32(0), put32(rows * row_bytes), put32(2835), put32(2835), put32(0), put32(0);
  bmp.resize(54 + size_t{rows} * row_bytes, 0);
  auto long_bmp = DecodeImage(bmp);
  ASSERT_FALSE(long_bmp);
  EXPECT_EQ(long_bmp.error().code, ErrorCode::kImageTooLarge) << long_bmp.error().ToString();
  EXPECT_NE(long_bmp.error().message.find("1x1100000"), std::string::npos) << long_bmp.error().message;

  DecodeOptions few_bytes;
  few_bytes.max_bytes = 100;
  auto too_many_bytes = DecodeImage(Encode(TestCard(), ".png"), few_bytes);
  ASSERT_FALSE(too_many_bytes);
  EXPECT_EQ(too_many_bytes.error().code, ErrorCode::kImageTooLarge);
}

// libjpeg walks every block of the frame for each scan of a progressive JPEG, however
// few bytes the scan has. Scans past DecodeOptions::max_jpeg_scans are refused, even when each is valid.
TEST(DecodeImage, RefusesProgressiveJpegsWithTooManyScans) {
  cv::Mat card;
  cv::resize(TestCard(), card, cv::Size(128, 96));
  const testing::Bytes grey(card.datastart, card.dataend);
  const auto many = testing::ProgressiveJpegWithScans(grey, 128, 96, 128);
  auto decoded = DecodeImage(many);
  ASSERT_FALSE(decoded) << "128 scans accepted";
  EXPECT_EQ(decoded.error().code, ErrorCode::kInvalidImage);
  EXPECT_NE(decoded.error().message.find("more than 100 scans"), std::string::npos) << decoded.error().message;
  // Every scan is legal: under a higher limit the same file decodes, and at the limit too.
  DecodeOptions lenient;
  lenient.max_jpeg_scans = 128;
  auto allowed = DecodeImage(many, lenient);
  ASSERT_TRUE(allowed) << allowed.error().ToString();
  EXPECT_LT(MeanAbsDiff(allowed->gray, card), 0.02);
  EXPECT_TRUE(DecodeImage(testing::ProgressiveJpegWithScans(grey, 128, 96, 100)));
  // What encoders write (libjpeg's default progression, through OpenCV) is far below the limit.
  std::vector<uint8_t> progressive;
  ASSERT_TRUE(cv::imencode(".jpg", card, progressive, {cv::IMWRITE_JPEG_PROGRESSIVE, 1}));
  EXPECT_TRUE(DecodeImage(progressive));
  lenient.max_jpeg_scans = 0;
  EXPECT_TRUE(lenient.Check().has_value());
}

// A scan flood: a 4000 x 4000 progressive frame and 3000 scans of 10 bytes (30 KB). libjpeg warns that
// each scan's data is missing and fills in grey, which OpenCV alone would pass on as an image.
TEST(DecodeImage, RefusesAProgressiveJpegOfEmptyScans) {
  const auto empty_scans = testing::JpegOfEmptyScans(4000, 4000, 3000);
  ASSERT_LT(empty_scans.size(), 40'000u);
  auto decoded = DecodeImage(empty_scans);
  ASSERT_FALSE(decoded) << "a JPEG of empty scans was decoded";
  EXPECT_EQ(decoded.error().code, ErrorCode::kInvalidImage);
  EXPECT_NE(decoded.error().message.find("premature end of data segment"), std::string::npos) << decoded.error().message;
}

// JPEG data that libjpeg can only decode by filling in grey is refused (400), not
// decoded into a grey image.
TEST(DecodeImage, RefusesJpegsWhoseDataIsShorterThanTheFrame) {
  cv::Mat photo = cv::imread(kOpencvData + "box.png", cv::IMREAD_GRAYSCALE);
  ASSERT_FALSE(photo.empty());
  cv::resize(photo, photo, cv::Size(512, 480));
  const auto jpeg = Encode(photo, ".jpg");
  ASSERT_TRUE(DecodeImage(jpeg));
  // Cut at 30%, with an end marker appended so that it does not look truncated.
  std::vector<uint8_t> cut(jpeg.begin(), jpeg.begin() + static_cast<long>(jpeg.size() * 3 / 10));
  cut.insert(cut.end(), {0xFF, 0xD9});
  auto decoded = DecodeImage(cut);
  ASSERT_FALSE(decoded) << "a JPEG cut at 30% was decoded";
  EXPECT_EQ(decoded.error().code, ErrorCode::kInvalidImage);
  EXPECT_NE(decoded.error().message.find("corrupt or truncated"), std::string::npos) << decoded.error().message;
}

TEST(DecodeImage, RefusesAJpegFrameLargerThanItsData) {
  cv::Mat photo = cv::imread(kOpencvData + "box.png", cv::IMREAD_GRAYSCALE);
  ASSERT_FALSE(photo.empty());
  cv::resize(photo, photo, cv::Size(512, 480));
  // The frame header claims 6000 x 6000 (36 MP, under the pixel limit) over the data of 512 x 480.
  const auto claimed = testing::WithJpegFrameSize(Encode(photo, ".jpg"), 6000, 6000);
  auto info = ReadImageHeader(claimed);
  ASSERT_TRUE(info && info->width == 6000 && info->height == 6000);
  auto oversized = DecodeImage(claimed);
  ASSERT_FALSE(oversized) << "a 6000x6000 frame over 512x480 of data was decoded";
  EXPECT_EQ(oversized.error().code, ErrorCode::kInvalidImage);
}

// libtiff decodes the first of repeated ImageWidth/ImageLength entries, so the pixel limit is checked on
// those (the last ones could say 1 x 1 while libtiff allocates 1 GB for the first).
TEST(DecodeImage, ChecksTheTiffDimensionsLibtiffDecodes) {
  const auto bomb = testing::TiffWithRepeatedDimensions({32000, 32000}, {1, 1});
  ASSERT_LT(bomb.size(), 1000u);
  auto info = ReadImageHeader(bomb);
  ASSERT_TRUE(info) << info.error().ToString();
  EXPECT_EQ(info->width, 32000u);
  EXPECT_EQ(info->height, 32000u);
  auto decoded = DecodeImage(bomb);
  ASSERT_FALSE(decoded);
  EXPECT_EQ(decoded.error().code, ErrorCode::kImageTooLarge) << decoded.error().ToString();
  EXPECT_NE(decoded.error().message.find("32000x32000"), std::string::npos) << decoded.error().message;
  // The other way round libtiff decodes a 1 x 1 image, and so does DecodeImage.
  auto small = DecodeImage(testing::TiffWithRepeatedDimensions({1, 1}, {32000, 32000}));
  ASSERT_TRUE(small) << small.error().ToString();
  EXPECT_EQ(small->original_width, 1);
  EXPECT_EQ(small->original_height, 1);
  // A hand-made TIFF without repeats decodes (the generator itself is sound).
  auto plain = DecodeImage(testing::HandMadeTiff(testing::GreyTiffEntries(16, 8, 1), testing::Bytes(16 * 8, 200)));
  ASSERT_TRUE(plain) << plain.error().ToString();
  EXPECT_EQ(plain->gray.width, 16);
  EXPECT_NEAR(plain->gray.at(3, 3), 200 / 255.0, 1e-6);
}

// A TIFF strip that does not decompress is corrupt data (400), whatever OpenCV makes of it (its RGBA
// path ignores libtiff's error); and a corrupt WebP or TIFF is not "this OpenCV build
// cannot decode webp/tiff" (415).
TEST(DecodeImage, RefusesATiffStripThatDoesNotDecompress) {
  auto garbage_strip = DecodeImage(testing::TiffWithGarbageDeflateStrip(64, 64));
  ASSERT_FALSE(garbage_strip) << "a TIFF with a garbage deflate strip was decoded";
  EXPECT_EQ(garbage_strip.error().code, ErrorCode::kInvalidImage) << garbage_strip.error().ToString();
  EXPECT_NE(garbage_strip.error().message.find("libtiff"), std::string::npos) << garbage_strip.error().message;
}

TEST(DecodeImage, CorruptTiffAndWebpAreInvalidNotUnsupported) {
  for (const std::string ext : {".webp", ".tiff"}) {
    if (!cv::haveImageWriter(ext)) continue;
    auto bytes = Encode(TestCard(), ext);
    ASSERT_TRUE(DecodeImage(bytes)) << ext;
    // Header intact, everything after the first 40 bytes overwritten.
    for (size_t i = 40; i < bytes.size(); ++i) bytes[i] = static_cast<uint8_t>(0xA5 ^ i);
    auto corrupt = DecodeImage(bytes);
    ASSERT_FALSE(corrupt) << ext;
    EXPECT_EQ(corrupt.error().code, ErrorCode::kInvalidImage) << ext << ": " << corrupt.error().ToString();
  }
}

TEST(DecodeImage, RefusesBadOptionsAndMissingFiles) {
  DecodeOptions bad;
  bad.max_image_side_px = 0;
  EXPECT_TRUE(bad.Check().has_value());
  auto decoded = DecodeImage(Encode(TestCard(), ".png"), bad);
  ASSERT_FALSE(decoded);
  EXPECT_EQ(decoded.error().code, ErrorCode::kInvalidArgument);

  auto missing = ReadImage("/nonexistent/image.jpg");
  ASSERT_FALSE(missing);
  EXPECT_EQ(missing.error().code, ErrorCode::kNotFound);
  EXPECT_NE(missing.error().message.find("/nonexistent/image.jpg"), std::string::npos);
}

// A PNG whose pixel data libpng refuses is reported once, as oxbow's error: it is not handed to
// OpenCV's decoder, whose libpng would refuse it again and print "libpng error: ..." to stderr.
TEST(DecodeImage, ADamagedPngPrintsNothingToStderr) {
  std::vector<uchar> png;
  cv::Mat noise(120, 160, CV_8U);
  cv::randu(noise, 0, 255);
  ASSERT_TRUE(cv::imencode(".png", noise, png));
  for (size_t i = png.size() / 2; i < png.size() / 2 + 16; ++i) png[i] ^= 0x5a;  // inside the pixel data
  const oxbow::testing::TempDir dir;
  const std::string captured = dir.path() + "/stderr.txt";
  std::fflush(stderr);
  const int saved = dup(STDERR_FILENO);
  const int file = open(captured.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  ASSERT_GE(file, 0);
  dup2(file, STDERR_FILENO);
  const auto decoded = DecodeImage(png);
  std::fflush(stderr);
  dup2(saved, STDERR_FILENO);
  close(file);
  close(saved);
  ASSERT_FALSE(decoded);
  EXPECT_EQ(decoded.error().code, ErrorCode::kInvalidImage);
  EXPECT_NE(decoded.error().message.find("png data could not be decoded"), std::string::npos) << decoded.error().message;
  EXPECT_EQ(oxbow::testing::FileBytes(captured), "");
}

// Links to folders are followed, each folder once: a link back to an ancestor ends, and no image is
// listed twice (a loop listed one image dozens of times, and `vocab train` sampled it as many).
TEST(ListImageFiles, FollowsFolderLinksOnceEach) {
  namespace fs = std::filesystem;
  const oxbow::testing::TempDir dir;
  const fs::path root = dir.path();
  fs::create_directories(root / "photos" / "sub");
  fs::create_directories(root / "elsewhere");
  for (const fs::path& image : {root / "photos" / "a.jpg", root / "photos" / "sub" / "b.jpg", root / "elsewhere" / "c.jpg"}) {
    std::ofstream(image) << "listed, not decoded";
  }
  fs::create_directory_symlink("..", root / "photos" / "sub" / "up");
  fs::create_directory_symlink(root / "elsewhere", root / "photos" / "linked");
  fs::create_directory_symlink(root / "elsewhere", root / "photos" / "linked-again");
  auto files = ListImageFiles((root / "photos").string());
  ASSERT_TRUE(files) << files.error().ToString();
  ASSERT_EQ(files->size(), 3u);
  EXPECT_EQ((*files)[0], (root / "photos" / "a.jpg").string());
  EXPECT_EQ((*files)[1], (root / "photos" / "linked" / "c.jpg").string());
  EXPECT_EQ((*files)[2], (root / "photos" / "sub" / "b.jpg").string());
}

}  // namespace
}  // namespace oxbow::sift
