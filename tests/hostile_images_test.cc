// Hostile images and abandoned requests, through api::Service and the real
// `oxbow serve`:
//  - images that cost far more than their bytes (a progressive JPEG of empty or of too many scans, a TIFF
//    whose repeated dimension tags hide its size) and corrupt images that OpenCV used to decode into
//    grey (a JPEG cut short with an end marker appended, a frame larger than its data, a TIFF strip that
//    does not decompress, a damaged WebP) are refused with the right status, and a refused add leaves
//    the index as it was;
//  - a request whose processing passes --processing-timeout-s, whose client hangs up, or that is in
//    flight at SIGTERM has its extraction stopped and its slot freed.
// No wall-clock assertions: the server's log says why an extraction stopped, and the slot's next user
// is served.
#include <sys/socket.h>
#include <unistd.h>

#include <gtest/gtest.h>

#include <chrono>
#include <csignal>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "api/service.h"
#include "server/http/errors.h"
#include "sift/image.h"
#include "sift/sift.h"
#include "tests/support/e2e.h"
#include "tests/support/hostile_images.h"
#include "tests/support/samples.h"
#include "tests/support/temp_dir.h"

namespace oxbow {
namespace {

using Bytes = std::vector<uint8_t>;
using nlohmann::json;
using oxbow::testing::Texture;
namespace hostile = oxbow::sift::testing;

Bytes Encode(const std::string& ext, const cv::Mat& image) {
  std::vector<uchar> out;
  EXPECT_TRUE(cv::imencode(ext, image, out)) << ext;
  return Bytes(out.begin(), out.end());
}

class HostileImagesTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new oxbow::testing::TempDir("oxbow-hostile-images-test");
    test_vocab_ = dir_->path() + "/test.oxvoc";
    ASSERT_TRUE(oxbow::testing::RandomVocabulary(testing::TestSiftOptions().Describe())->Write(test_vocab_));
    // The server's own extractor (2x first octave): a 1600-pixel search then takes seconds on one core,
    // long enough to be abandoned while it runs.
    sift::SiftOptions production;
    production.descriptor = sift::DescriptorKind::kRootSift;
    production_vocab_ = dir_->path() + "/production.oxvoc";
    ASSERT_TRUE(oxbow::testing::RandomVocabulary(production.Describe())->Write(production_vocab_));
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }

  std::unique_ptr<api::Service> OpenService(const api::ServiceOptions& options = {}) {
    auto service = api::Service::Open(dir_->path() + "/index-" + std::to_string(counter_++), test_vocab_, options);
    EXPECT_TRUE(service) << service.error().ToString();
    return service ? std::move(*service) : nullptr;
  }

  // Search and add of `bytes` both fail with `code` (and its HTTP status); the add leaves no trace.
  static void ExpectRefused(api::Service& service, const Bytes& bytes, ErrorCode code, int http_status, const char* what) {
    SCOPED_TRACE(what);
    const uint64_t before = service.Stats().index.num_images;
    auto found = service.Search(bytes, service.options().default_query);
    ASSERT_FALSE(found) << "search accepted it";
    EXPECT_EQ(found.error().code, code) << found.error().ToString();
    EXPECT_EQ(server::ToHttpError(found.error()).status, http_status);
    api::AddImageRequest add;
    add.id = std::string("hostile-") + what;
    add.image = bytes;
    auto added = service.AddImage(add);
    ASSERT_FALSE(added) << "add accepted it";
    EXPECT_EQ(added.error().code, code) << added.error().ToString();
    EXPECT_EQ(service.Stats().index.num_images, before);
    EXPECT_FALSE(service.GetImage(add.id)) << "a refused add left a record";
  }

  // A server over a fresh index with the production extractor and one extraction slot.
  std::unique_ptr<oxbow::testing::ServerProcess> StartServer(const std::vector<std::string>& extra) {
    const std::string n = std::to_string(counter_++);
    std::vector<std::string> args = {"serve", "--index", dir_->path() + "/served-" + n, "--vocab", production_vocab_,
                                     "--port", "0", "--extractions", "1", "--threads-per-request", "1"};
    args.insert(args.end(), extra.begin(), extra.end());
    auto server = std::make_unique<oxbow::testing::ServerProcess>(args, dir_->path() + "/server-" + n + ".log");
    EXPECT_TRUE(server->port() > 0 && server->WaitReady()) << server->Log();
    return server;
  }

  // Sends a search of `body` on a new raw connection and returns the socket once the server reports the
  // extraction running (-1 if it never does).
  static int StartSearch(const oxbow::testing::ServerProcess& server, const Bytes& body) {
    const int fd = oxbow::testing::ConnectTo(server.port());
    const std::string head = "POST /v1/search HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/jpeg\r\nContent-Length: " +
                             std::to_string(body.size()) + "\r\n\r\n";
    if (fd < 0 || !oxbow::testing::SendAll(fd, head + std::string(body.begin(), body.end()))) return -1;
    auto client = server.Client();
    const auto give_up = std::chrono::steady_clock::now() + std::chrono::seconds(60);
    while (std::chrono::steady_clock::now() < give_up) {
      auto stats = client.Get("/v1/stats");
      if (stats && stats->status == 200 && json::parse(stats->body)["extractions_in_flight"] == 1) return fd;
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    close(fd);
    return -1;
  }

  // The costliest image to extract at the default --max-image-side: 1600 x 1200 of fine random texture,
  // tens of thousands of keypoints (seconds of SIFT on one core, where a photo takes ~0.2 s).
  static const Bytes& HeavyJpeg() {
    static const Bytes jpeg = [] {
      cv::Mat noise(1200, 1600, CV_8UC1);
      cv::setRNGSeed(19);
      cv::randu(noise, 0, 255);
      cv::GaussianBlur(noise, noise, cv::Size(0, 0), 1.5);
      cv::normalize(noise, noise, 0, 255, cv::NORM_MINMAX);
      std::vector<uchar> out;
      EXPECT_TRUE(cv::imencode(".jpg", noise, out, {cv::IMWRITE_JPEG_QUALITY, 95}));
      return Bytes(out.begin(), out.end());
    }();
    return jpeg;
  }

  static inline oxbow::testing::TempDir* dir_ = nullptr;
  static inline std::string test_vocab_;
  static inline std::string production_vocab_;
  static inline int counter_ = 0;
};

TEST_F(HostileImagesTest, CostlyAndCorruptImagesAreRefusedAndNothingIsStored) {
  auto service = OpenService();
  ASSERT_TRUE(service);
  // Item 4: 3000 empty scans (30 KB) over a 4000 x 4000 frame; and 128 valid scans (over the limit of 100).
  ExpectRefused(*service, hostile::JpegOfEmptyScans(4000, 4000, 3000), ErrorCode::kInvalidImage, 400, "empty-scans");
  const cv::Mat small = Texture(160, 120);
  ExpectRefused(*service, hostile::ProgressiveJpegWithScans(Bytes(small.datastart, small.dataend), 160, 120, 128),
                ErrorCode::kInvalidImage, 400, "128-scans");
  // Item 5: ImageWidth/ImageLength 32000 then 1: libtiff decodes 32000 x 32000, over --max-megapixels.
  ExpectRefused(*service, hostile::TiffWithRepeatedDimensions({32000, 32000}, {1, 1}), ErrorCode::kImageTooLarge, 413,
                "repeated-tiff-tags");
  // Item 9: corrupt data that OpenCV decoded into grey, and corrupt files that were called unsupported.
  const Bytes jpeg = Encode(".jpg", Texture(512, 480));
  Bytes cut(jpeg.begin(), jpeg.begin() + static_cast<long>(jpeg.size() * 3 / 10));
  cut.insert(cut.end(), {0xFF, 0xD9});
  ExpectRefused(*service, cut, ErrorCode::kInvalidImage, 400, "jpeg-cut-with-eoi");
  ExpectRefused(*service, hostile::WithJpegFrameSize(jpeg, 6000, 6000), ErrorCode::kInvalidImage, 400, "jpeg-frame-over-data");
  ExpectRefused(*service, hostile::TiffWithGarbageDeflateStrip(256, 256), ErrorCode::kInvalidImage, 400, "tiff-garbage-strip");
  for (const char* ext : {".webp", ".tiff"}) {
    if (!cv::haveImageWriter(ext)) continue;
    Bytes damaged = Encode(ext, Texture(320, 240));
    for (size_t i = 40; i < damaged.size(); ++i) damaged[i] = static_cast<uint8_t>(0x5A ^ (i * 7));
    ExpectRefused(*service, damaged, ErrorCode::kInvalidImage, 400, ext);
  }
  // The intact originals are accepted (the refusals are about the damage).
  api::AddImageRequest add;
  add.id = "intact";
  add.image = jpeg;
  ASSERT_TRUE(service->AddImage(add));
  EXPECT_EQ(service->Stats().index.num_images, 1u);
}

// The processing deadline stops the extraction and frees its slot; a stopped add stores nothing.
TEST_F(HostileImagesTest, ProcessingDeadlineStopsTheExtraction) {
  api::ServiceOptions options;
  options.processing_timeout_ms = 1;  // any decode of a 1600 x 1200 JPEG takes longer
  options.max_concurrent_extractions = 1;
  options.extraction_wait_ms = 0;     // a slot still held would answer "slots stayed busy"
  auto service = OpenService(options);
  ASSERT_TRUE(service);
  for (int round = 0; round < 2; ++round) {
    auto found = service->Search(HeavyJpeg(), service->options().default_query);
    ASSERT_FALSE(found);
    EXPECT_EQ(found.error().code, ErrorCode::kResourceExhausted);
    EXPECT_NE(found.error().message.find("--processing-timeout-s"), std::string::npos) << found.error().message;
    api::AddImageRequest add;
    add.id = "late";
    add.image = HeavyJpeg();
    auto added = service->AddImage(add);
    ASSERT_FALSE(added);
    EXPECT_NE(added.error().message.find("--processing-timeout-s"), std::string::npos) << added.error().message;
    EXPECT_EQ(service->Stats().index.num_images, 0u);
    EXPECT_EQ(service->Stats().extractions_in_flight, 0);
  }
  api::ServiceOptions bad;
  bad.processing_timeout_ms = 0;
  EXPECT_TRUE(bad.Check().has_value());
}

// After StopExtractions (shutdown) work goes on for the grace, then stops; a stopped add stores nothing.
TEST_F(HostileImagesTest, StopExtractionsStopsWorkAfterItsGrace) {
  const Bytes jpeg = Encode(".jpg", Texture(320, 240));
  api::ServiceOptions patient;
  patient.shutdown_grace_ms = 600'000;
  auto finishing = OpenService(patient);
  ASSERT_TRUE(finishing);
  finishing->StopExtractions();
  EXPECT_TRUE(finishing->Search(jpeg, finishing->options().default_query));

  api::ServiceOptions immediate;
  immediate.shutdown_grace_ms = 0;
  auto stopped = OpenService(immediate);
  ASSERT_TRUE(stopped);
  stopped->StopExtractions();
  auto found = stopped->Search(jpeg, stopped->options().default_query);
  ASSERT_FALSE(found);
  EXPECT_EQ(found.error().code, ErrorCode::kResourceExhausted);
  EXPECT_NE(found.error().message.find("shutting down"), std::string::npos) << found.error().message;
  api::AddImageRequest add;
  add.id = "during-shutdown";
  add.image = jpeg;
  EXPECT_FALSE(stopped->AddImage(add));
  EXPECT_EQ(stopped->Stats().index.num_images, 0u);
  EXPECT_EQ(stopped->Stats().extractions_in_flight, 0);
}

// A client that hangs up during its search frees the only extraction slot for the next client. Before,
// the extraction ran to its end for nobody while everyone else waited (or got 503).
TEST_F(HostileImagesTest, AClientThatHangsUpFreesItsExtractionSlot) {
  auto server = StartServer({"--extraction-wait-ms", "600000"});
  ASSERT_GT(server->port(), 0);
  const int fd = StartSearch(*server, HeavyJpeg());
  ASSERT_GE(fd, 0) << "the search never started extracting\n" << server->Log();
  close(fd);
  // The next search takes the slot (it waits for it as long as it has to), then the log tells why the
  // first one ended.
  const Bytes light = Encode(".jpg", Texture(320, 240));
  auto res = server->Client().Post("/v1/search", std::string(light.begin(), light.end()), "image/jpeg");
  ASSERT_TRUE(res);
  EXPECT_EQ(res->status, 200) << res->body;
  EXPECT_TRUE(server->WaitForLog("the client closed its connection", std::chrono::seconds(5))) << server->Log();
  EXPECT_NE(server->Log().find("extraction stopped"), std::string::npos);
  EXPECT_EQ(server->Stop(), 0);
}

// SIGTERM stops an extraction still running after --shutdown-grace-s (its client gets 503) instead of
// waiting for it, and the server exits cleanly. (With the default grace of 5 s this search would finish:
// http_server_test's graceful stop.)
TEST_F(HostileImagesTest, ShutdownStopsExtractionsInFlight) {
  auto server = StartServer({"--shutdown-grace-s", "0"});
  ASSERT_GT(server->port(), 0);
  const int fd = StartSearch(*server, HeavyJpeg());
  ASSERT_GE(fd, 0) << "the search never started extracting\n" << server->Log();
  server->Signal(SIGTERM);
  std::string response;
  oxbow::testing::ReadUntil(fd, "\r\n\r\n", &response);
  close(fd);
  EXPECT_EQ(response.rfind("HTTP/1.1 503", 0), 0u) << response;
  EXPECT_EQ(server->Wait(), 0);
  const std::string log = server->Log();
  EXPECT_NE(log.find("extraction stopped"), std::string::npos) << log;
  EXPECT_NE(log.find("shutting down"), std::string::npos) << log;
}

}  // namespace
}  // namespace oxbow
