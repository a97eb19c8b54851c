// HTTP integration tests: start the real `oxbow serve` (OXBOW_BINARY) on 127.0.0.1 with an ephemeral
// port and talk HTTP to it with httplib::Client. Covers every route, every error status, auth, limits,
// graceful shutdown, restart with data intact and kill -9 during a stream of adds.
#include <fcntl.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <gtest/gtest.h>
#include <httplib.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdlib>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <regex>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "tests/support/e2e.h"
#include "tests/support/samples.h"
#include "tests/support/temp_dir.h"

namespace oxbow {
namespace {

using testing::ReadBytes;
using testing::SamplePath;
using nlohmann::json;

std::string ReadText(const std::string& path) {
  auto bytes = ReadBytes(path);
  return std::string(bytes.begin(), bytes.end());
}

using oxbow::testing::ServerProcess;

httplib::MultipartFormData Part(const std::string& name, const std::string& content, const std::string& filename = "",
                                const std::string& type = "") {
  return {name, content, filename, type};
}

// The status of a response, or -1 when none arrived (so an assertion fails instead of dereferencing).
int StatusOf(const httplib::Result& res) { return res ? res->status : -1; }

void ExpectErrorShape(const httplib::Result& res, int status, const std::string& code) {
  ASSERT_TRUE(res) << "no response";
  EXPECT_EQ(res->status, status) << res->body;
  auto body = json::parse(res->body, nullptr, false);
  ASSERT_FALSE(body.is_discarded()) << res->body;
  ASSERT_TRUE(body.contains("error")) << res->body;
  EXPECT_EQ(body["error"]["code"], code) << res->body;
  EXPECT_FALSE(body["error"]["message"].get<std::string>().empty());
  EXPECT_EQ(body["error"]["request_id"], res->get_header_value("X-Request-Id"));
  EXPECT_FALSE(res->get_header_value("X-Request-Id").empty());
}

class HttpServerTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    if (!std::filesystem::exists(SamplePath("box_in_scene.png"))) return;
    dir_ = new oxbow::testing::TempDir("oxbow-http-test");
    vocab_ = dir_->path() + "/vocab.oxvoc";
    auto vocabulary = testing::BuildTestVocabulary({"box_in_scene.png", "graf1.png", "leuvenA.jpg", "graf3.png"},
                                                        512, vocab_);
    ASSERT_TRUE(vocabulary) << vocabulary.error().ToString();
    box_ = ReadText(SamplePath("box.png"));
    scene_ = ReadText(SamplePath("box_in_scene.png"));
    graf1_ = ReadText(SamplePath("graf1.png"));
    graf3_ = ReadText(SamplePath("graf3.png"));
    leuven_ = ReadText(SamplePath("leuvenA.jpg"));
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  void SetUp() override {
    if (dir_ == nullptr) GTEST_SKIP() << "opencv-doc sample photos not installed (scripts/install-deps.sh)";
  }
  // Starts a server on a fresh index (or `index_dir`) with extra flags; waits until ready.
  std::unique_ptr<ServerProcess> Start(const std::vector<std::string>& extra = {}, std::string index_dir = "",
                                       bool with_vocab = true) {
    if (index_dir.empty()) index_dir = dir_->path() + "/index-" + std::to_string(counter_++);
    std::vector<std::string> args = {"serve", "--index", index_dir, "--port", "0", "--http-workers", "8"};
    if (with_vocab) {
      args.emplace_back("--vocab");
      args.push_back(vocab_);
    }
    args.insert(args.end(), extra.begin(), extra.end());
    auto server = std::make_unique<ServerProcess>(args, dir_->path() + "/server-" + std::to_string(counter_++) + ".log");
    EXPECT_GT(server->port(), 0) << server->Log();
    EXPECT_TRUE(server->port() > 0 && server->WaitReady()) << server->Log();
    return server;
  }

  static inline oxbow::testing::TempDir* dir_ = nullptr;
  static inline std::string vocab_;
  static inline std::string box_, scene_, graf1_, graf3_, leuven_;
  static inline int counter_ = 0;
};

TEST_F(HttpServerTest, HealthReadyAndRouteIndex) {
  auto server = Start();
  auto client = server->Client();
  auto health = client.Get("/healthz");
  ASSERT_TRUE(health);
  EXPECT_EQ(health->status, 200);
  EXPECT_EQ(json::parse(health->body)["status"], "ok");
  auto ready = client.Get("/readyz");
  ASSERT_TRUE(ready);
  EXPECT_EQ(ready->status, 200);
  auto routes = client.Get("/v1");
  ASSERT_TRUE(routes);
  EXPECT_EQ(routes->status, 200);
  EXPECT_GE(json::parse(routes->body)["routes"].size(), 8u);
  // Routes take no trailing slash: the 404 names the route without it.
  for (const std::string path : {"/v1/images/", "/v1/stats/"}) {
    auto slashed = client.Get(path);
    ExpectErrorShape(slashed, 404, "not_found");
    EXPECT_NE(slashed->body.find("the route is " + path.substr(0, path.size() - 1) + ", without the trailing slash"),
              std::string::npos) << slashed->body;
  }
  auto unknown = client.Get("/v1/nothing/");
  ExpectErrorShape(unknown, 404, "not_found");
  EXPECT_NE(unknown->body.find("GET /v1 lists the routes"), std::string::npos) << unknown->body;
  // The request id: generated, or the client's own when sane.
  httplib::Headers headers = {{"X-Request-Id", "my-trace.42"}};
  auto traced = client.Get("/healthz", headers);
  ASSERT_TRUE(traced);
  EXPECT_EQ(traced->get_header_value("X-Request-Id"), "my-trace.42");
  EXPECT_EQ(health->get_header_value("X-Request-Id").size(), 16u);
}

TEST_F(HttpServerTest, ImagesLifecycle) {
  auto server = Start();
  auto client = server->Client();
  auto added = client.Post("/v1/images?id=scene", scene_, "image/png");
  ASSERT_TRUE(added);
  ASSERT_EQ(added->status, 201) << added->body;
  auto body = json::parse(added->body);
  EXPECT_EQ(body["id"], "scene");
  EXPECT_EQ(body["width"], 512);
  EXPECT_EQ(body["height"], 384);
  EXPECT_GT(body["features"].get<int>(), 100);
  EXPECT_FALSE(added->get_header_value("Server-Timing").empty());

  ExpectErrorShape(client.Post("/v1/images?id=scene", graf1_, "image/png"), 409, "already_exists");

  auto replaced = client.Post("/v1/images?id=scene&replace=true", graf3_, "image/png");
  ASSERT_TRUE(replaced);
  ASSERT_EQ(replaced->status, 200) << replaced->body;
  EXPECT_TRUE(json::parse(replaced->body)["replaced"].get<bool>());
  EXPECT_EQ(json::parse(replaced->body)["width"], 800);

  httplib::MultipartFormDataItems form = {Part("id", "leuven"), Part("metadata", R"({"city":"Leuven","n":1})"),
                                          Part("file", leuven_, "leuvenA.jpg", "image/jpeg")};
  auto multipart = client.Post("/v1/images", form);
  ASSERT_TRUE(multipart);
  ASSERT_EQ(multipart->status, 201) << multipart->body;

  auto got = client.Get("/v1/images/leuven");
  ASSERT_TRUE(got);
  ASSERT_EQ(got->status, 200);
  auto record = json::parse(got->body);
  EXPECT_EQ(record["metadata"]["city"], "Leuven");
  EXPECT_EQ(record["width"], 751);
  EXPECT_EQ(record["source"], "http:leuvenA.jpg");

  // Ids may hold spaces, '/', '?', '#' and any UTF-8; Location names the image in a form that reaches it.
  EXPECT_EQ(added->get_header_value("Location"), "/v1/images/scene");
  const std::string odd_id = "a b/c?v=2#\u00fc";
  const std::string location = oxbow::testing::RawResponseHeader(
      server->port(),
      "POST /v1/images?id=a%20b%2Fc%3Fv%3D2%23%C3%BC HTTP/1.1\r\nHost: localhost\r\nContent-Type: image/png\r\n"
      "Content-Length: " + std::to_string(box_.size()) + "\r\nConnection: close\r\n\r\n" + box_,
      "Location");
  EXPECT_EQ(location, "/v1/images/a%20b%2Fc%3Fv%3D2%23%C3%BC");
  auto odd = client.Get(location);
  ASSERT_TRUE(odd);
  EXPECT_EQ(odd->status, 200) << odd->body;
  EXPECT_EQ(json::parse(odd->body)["id"], odd_id) << odd->body;

  auto list = client.Get("/v1/images?offset=1&limit=2");
  ASSERT_TRUE(list);
  ASSERT_EQ(list->status, 200);
  auto page = json::parse(list->body);
  EXPECT_EQ(page["total"], 3);
  ASSERT_EQ(page["images"].size(), 2u);
  EXPECT_EQ(page["images"][0]["id"], "leuven");  // ordered by id: "a b/c?v=2#\u00fc", "leuven", "scene"
  ExpectErrorShape(client.Get("/v1/images?limit=0"), 400, "invalid_argument");
  ExpectErrorShape(client.Get("/v1/images?limit=abc"), 400, "invalid_argument");

  auto deleted = client.Delete("/v1/images/leuven");
  ASSERT_TRUE(deleted);
  EXPECT_EQ(deleted->status, 200);
  ExpectErrorShape(client.Delete("/v1/images/leuven"), 404, "not_found");
  ExpectErrorShape(client.Get("/v1/images/leuven"), 404, "not_found");
  ExpectErrorShape(client.Post("/v1/images", box_, "image/png"), 400, "invalid_argument");         // no id
  ExpectErrorShape(client.Post("/v1/images?id=x&metadata=%7Bbad", box_, "image/png"), 400, "invalid_argument");
}

TEST_F(HttpServerTest, SearchSimilarAndMatch) {
  auto server = Start();
  auto client = server->Client();
  for (const auto& [id, bytes] : std::vector<std::pair<std::string, std::string>>{
           {"scene", scene_}, {"graf1", graf1_}, {"leuven", leuven_}}) {
    ASSERT_EQ(StatusOf(client.Post("/v1/images?id=" + id, bytes, "image/png")), 201);
  }
  auto found = client.Post("/v1/search?top_k=2", box_, "image/png");
  ASSERT_TRUE(found);
  ASSERT_EQ(found->status, 200) << found->body;
  auto body = json::parse(found->body);
  ASSERT_GE(body["results"].size(), 1u);
  EXPECT_LE(body["results"].size(), 2u);
  const auto& first = body["results"][0];
  EXPECT_EQ(first["id"], "scene");
  EXPECT_TRUE(first["verified"].get<bool>());
  EXPECT_GE(first["inliers"].get<int>(), 6);
  EXPECT_EQ(first["transform"].size(), 2u);
  ASSERT_TRUE(first["region"].is_array());
  EXPECT_LE(first["region"][2].get<double>(), 512.0);
  for (const char* stage : {"decode_extract", "quantize", "score", "verify", "qe", "total"}) {
    EXPECT_TRUE(body["timings_ms"].contains(stage)) << stage;
  }
  EXPECT_GT(body["timings_ms"]["decode_extract"].get<double>(), 0);

  // Multipart with fields, a bbox and query expansion.
  httplib::MultipartFormDataItems form = {Part("file", box_, "box.png", "image/png"), Part("top_k", "1"),
                                          Part("bbox", "0,0,200,200"), Part("qe", "true")};
  auto multipart = client.Post("/v1/search", form);
  ASSERT_TRUE(multipart);
  ASSERT_EQ(multipart->status, 200) << multipart->body;
  auto mbody = json::parse(multipart->body);
  EXPECT_EQ(mbody["results"].size(), 1u);
  EXPECT_EQ(mbody["query"]["bbox"][2], 200.0);
  EXPECT_TRUE(mbody["params"]["qe"].get<bool>());
  EXPECT_LT(mbody["query"]["features_used"].get<int>(), mbody["query"]["features"].get<int>());

  ExpectErrorShape(client.Post("/v1/search?top_k=0", box_, "image/png"), 400, "invalid_argument");
  ExpectErrorShape(client.Post("/v1/search?topk=3", box_, "image/png"), 400, "invalid_argument");
  ExpectErrorShape(client.Post("/v1/search?bbox=1,2,3", box_, "image/png"), 400, "invalid_argument");

  auto similar = client.Get("/v1/images/graf1/similar?top_k=3");
  ASSERT_TRUE(similar);
  ASSERT_EQ(similar->status, 200) << similar->body;
  auto sbody = json::parse(similar->body);
  EXPECT_EQ(sbody["query"]["id"], "graf1");
  EXPECT_EQ(sbody["results"][0]["id"], "graf1");
  ExpectErrorShape(client.Get("/v1/images/nope/similar"), 404, "not_found");

  httplib::MultipartFormDataItems pair = {Part("a", box_, "box.png"), Part("b", scene_, "box_in_scene.png")};
  auto matched = client.Post("/v1/match", pair);
  ASSERT_TRUE(matched);
  ASSERT_EQ(matched->status, 200) << matched->body;
  auto match = json::parse(matched->body);
  EXPECT_TRUE(match["verified"].get<bool>());
  EXPECT_GE(match["inliers"].get<int>(), 10);
  EXPECT_EQ(match["b"]["width"], 512);
  EXPECT_EQ(match["transform"].size(), 3u);
  httplib::MultipartFormDataItems homography = {Part("a", box_), Part("b", scene_), Part("model", "homography")};
  auto fitted = client.Post("/v1/match", homography);
  ASSERT_TRUE(fitted);
  EXPECT_EQ(fitted->status, 200) << fitted->body;
  EXPECT_EQ(json::parse(fitted->body)["model"], "homography");
  httplib::MultipartFormDataItems missing = {Part("a", box_)};
  ExpectErrorShape(client.Post("/v1/match", missing), 400, "invalid_argument");
  ExpectErrorShape(client.Post("/v1/match", box_, "image/png"), 415, "unsupported_format");
  // What `curl --data-binary @box.png` sends (a form label): the same 415 at any size under the upload
  // limit, not the HTTP library's 8 KiB form limit reported as the server's.
  ASSERT_GT(box_.size(), 8192u);
  for (const std::string& labelled : {box_.substr(0, 8000), box_}) {
    ExpectErrorShape(client.Post("/v1/match", labelled, "application/x-www-form-urlencoded"), 415, "unsupported_format");
  }
  httplib::MultipartFormDataItems bad_model = {Part("a", box_), Part("b", scene_), Part("model", "magic")};
  ExpectErrorShape(client.Post("/v1/match", bad_model), 400, "invalid_argument");
}

TEST_F(HttpServerTest, ErrorStatusesAndLimits) {
  auto server = Start({"--max-upload-mb", "2", "--max-megapixels", "0.6"});
  auto client = server->Client();
  ExpectErrorShape(client.Get("/v1/nothing"), 404, "not_found");
  ExpectErrorShape(client.Get("/favicon.ico"), 404, "not_found");
  auto wrong = client.Put("/v1/search", box_, "image/png");
  ExpectErrorShape(wrong, 405, "method_not_allowed");
  EXPECT_EQ(wrong->get_header_value("Allow"), "POST");
  auto wrong_on_read = client.Delete("/v1/stats");
  ExpectErrorShape(wrong_on_read, 405, "method_not_allowed");
  EXPECT_EQ(wrong_on_read->get_header_value("Allow"), "GET, HEAD");  // HEAD is answered wherever GET is
  auto head = client.Head("/v1/stats");
  ASSERT_TRUE(head);
  EXPECT_EQ(head->status, 200);
  EXPECT_TRUE(head->body.empty());
  ExpectErrorShape(client.Delete("/v1/images"), 405, "method_not_allowed");

  // Corrupt, truncated, empty and non-image bodies.
  ExpectErrorShape(client.Post("/v1/search", "this is not an image at all", "application/octet-stream"), 400, "invalid_image");
  ExpectErrorShape(client.Post("/v1/images?id=half", box_.substr(0, box_.size() / 2), "image/png"), 400, "invalid_image");
  ExpectErrorShape(client.Post("/v1/search", "", "image/png"), 400, "invalid_image");
  ExpectErrorShape(client.Post("/v1/search", R"({"image":"x"})", "application/json"), 415, "unsupported_format");
  // curl --data-binary without -H sends application/x-www-form-urlencoded: taken as the image bytes
  // (box.png is over httplib's 8 KiB form limit), and a form that is not an image is refused as such.
  ASSERT_GT(box_.size(), 8192u);
  auto curl_default = client.Post("/v1/search", box_, "application/x-www-form-urlencoded");
  ASSERT_TRUE(curl_default);
  EXPECT_EQ(curl_default->status, 200) << curl_default->body;
  ExpectErrorShape(client.Post("/v1/search", "top_k=5&rerank=0", "application/x-www-form-urlencoded"), 400, "invalid_image");

  // Over the body limit (2 MiB) and over the pixel limit (0.6 MP; a 1000 x 800 PNG is small on disk).
  ExpectErrorShape(client.Post("/v1/search", std::string(3u << 20, 'x'), "application/octet-stream"), 413, "payload_too_large");
  std::vector<uchar> png;
  ASSERT_TRUE(cv::imencode(".png", cv::Mat(800, 1000, CV_8UC1, cv::Scalar(128)), png));
  ASSERT_LT(png.size(), 1u << 20);
  ExpectErrorShape(client.Post("/v1/images?id=big", std::string(png.begin(), png.end()), "image/png"), 413, "image_too_large");
  ExpectErrorShape(client.Get("/v1/images/big"), 404, "not_found");

  // The server survived all of it.
  auto health = client.Get("/healthz");
  ASSERT_TRUE(health);
  EXPECT_EQ(health->status, 200);

  // Metrics and stats count what happened.
  ASSERT_EQ(StatusOf(client.Post("/v1/images?id=box", box_, "image/png")), 201);
  auto stats = client.Get("/v1/stats");
  ASSERT_TRUE(stats);
  ASSERT_EQ(stats->status, 200);
  auto s = json::parse(stats->body);
  EXPECT_EQ(s["images"], 1);
  EXPECT_GT(s["features"].get<int>(), 50);
  EXPECT_EQ(s["words"], 512);
  EXPECT_GT(s["bytes_per_feature"].get<double>(), 0);
  EXPECT_GT(s["memory_rss_bytes"].get<double>(), 1e6);
  EXPECT_GE(s["uptime_s"].get<double>(), 0);
  // A request is counted by the logger, right after its response was sent: poll briefly.
  // Requests of an image or search route carry the collection they acted on ("default"); those refused
  // before a route ran (413 here) have none.
  const std::string added_series = R"(oxbow_http_requests_total{route="/v1/images",method="POST",status="201",collection="default"} 1)";
  std::string text;
  for (int i = 0; i < 100 && text.find(added_series) == std::string::npos; ++i) {
    auto metrics = client.Get("/metrics");
    ASSERT_TRUE(metrics);
    ASSERT_EQ(metrics->status, 200);
    EXPECT_EQ(metrics->get_header_value("Content-Type"), "text/plain; version=0.0.4");
    text = metrics->body;
    if (text.find(added_series) == std::string::npos) std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  EXPECT_NE(text.find(R"(oxbow_http_requests_total{route="/v1/search",method="POST",status="400",collection="default"} 3)"), std::string::npos) << text;
  EXPECT_NE(text.find(R"(oxbow_http_requests_total{route="/v1/search",method="POST",status="200",collection="default"} 1)"), std::string::npos);
  EXPECT_NE(text.find(R"(oxbow_http_requests_total{route="/v1/search",method="POST",status="413"} 1)"), std::string::npos);
  EXPECT_NE(text.find(added_series), std::string::npos);
  EXPECT_NE(text.find(R"(oxbow_http_requests_total{route="unmatched",method="GET",status="404"} 2)"), std::string::npos);
  EXPECT_NE(text.find("oxbow_http_request_duration_seconds_bucket{route=\"/v1/images\",method=\"POST\",status=\"201\",collection=\"default\",le=\"+Inf\"} 1"),
            std::string::npos);
  EXPECT_NE(text.find("oxbow_index_images{collection=\"default\"} 1\n"), std::string::npos);

  // One log line per request, with the request id.
  EXPECT_EQ(server->Stop(SIGTERM), 0);
  const std::string log = server->Log();
  EXPECT_NE(log.find("route=/v1/search status=413"), std::string::npos) << log;
  EXPECT_NE(log.find(" POST /v1/images route=/v1/images status=201 ms="), std::string::npos) << log;
  EXPECT_NE(log.find("decode_extract="), std::string::npos);
}

TEST_F(HttpServerTest, ApiKeyProtectsWrites) {
  auto server = Start({"--api-key", "s3cret"});
  auto client = server->Client();
  ExpectErrorShape(client.Post("/v1/images?id=box", box_, "image/png"), 401, "unauthenticated");
  httplib::Headers wrong = {{"Authorization", "Bearer nope"}};
  ExpectErrorShape(client.Post("/v1/images?id=box", wrong, box_, "image/png"), 403, "permission_denied");
  httplib::Headers bearer = {{"Authorization", "Bearer s3cret"}};
  auto added = client.Post("/v1/images?id=box", bearer, box_, "image/png");
  ASSERT_TRUE(added);
  EXPECT_EQ(added->status, 201) << added->body;
  ExpectErrorShape(client.Delete("/v1/images/box"), 401, "unauthenticated");
  httplib::Headers key = {{"X-API-Key", "s3cret"}};
  auto deleted = client.Delete("/v1/images/box", key);
  ASSERT_TRUE(deleted);
  EXPECT_EQ(deleted->status, 200);
  // Reads and searches stay open.
  auto search = client.Post("/v1/search", box_, "image/png");
  ASSERT_TRUE(search);
  EXPECT_EQ(search->status, 200) << search->body;
  EXPECT_EQ(StatusOf(client.Get("/v1/images")), 200);
}

TEST_F(HttpServerTest, RestartKeepsDataAndGracefulStopFinishesInFlightRequests) {
  const std::string index_dir = dir_->path() + "/restart";
  {
    auto server = Start({}, index_dir);
    auto client = server->Client();
    ASSERT_EQ(StatusOf(client.Post("/v1/images?id=scene&metadata=%7B%22k%22%3A1%7D", scene_, "image/png")), 201);
    ASSERT_EQ(StatusOf(client.Post("/v1/images?id=graf1", graf1_, "image/png")), 201);
    // A search in flight when SIGTERM arrives still gets its answer. To be sure it is in flight, the
    // test holds back the second half of its body until the server has logged the signal.
    const int fd = oxbow::testing::ConnectTo(server->port());
    ASSERT_GE(fd, 0);
    const std::string head = "POST /v1/search?qe=true HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/png\r\n"
                             "Content-Length: " + std::to_string(graf3_.size()) +
                             "\r\nExpect: 100-continue\r\nConnection: close\r\n\r\n";
    std::string response;
    ASSERT_TRUE(oxbow::testing::SendAll(fd, head));
    ASSERT_TRUE(oxbow::testing::ReadUntil(fd, oxbow::testing::kContinue, &response)) << response;  // a worker has it
    const size_t half = graf3_.size() / 2;
    ASSERT_TRUE(oxbow::testing::SendAll(fd, graf3_.substr(0, half)));
    server->Signal(SIGTERM);
    EXPECT_TRUE(server->WaitForLog("received SIGTERM")) << server->Log();
    ASSERT_TRUE(oxbow::testing::SendAll(fd, graf3_.substr(half)));
    EXPECT_TRUE(oxbow::testing::ReadUntil(fd, std::string(oxbow::testing::kContinue) + "HTTP/1.1 200 ", &response))
        << "in-flight search was dropped: " << response;
    close(fd);
    EXPECT_EQ(server->Wait(), 0) << server->Log();
    const std::string log = server->Log();
    const size_t signalled = log.find("received SIGTERM");
    const size_t answered = log.find("POST /v1/search route=/v1/search status=200");
    ASSERT_NE(signalled, std::string::npos) << log;
    ASSERT_NE(answered, std::string::npos) << log;
    EXPECT_LT(signalled, answered) << log;
  }
  // No --vocab: the index folder carries its vocabulary.
  auto server = Start({}, index_dir, /*with_vocab=*/false);
  auto client = server->Client();
  auto got = client.Get("/v1/images/scene");
  ASSERT_TRUE(got);
  ASSERT_EQ(got->status, 200);
  EXPECT_EQ(json::parse(got->body)["metadata"]["k"], 1);
  auto found = client.Post("/v1/search", box_, "image/png");
  ASSERT_TRUE(found);
  ASSERT_EQ(found->status, 200);
  EXPECT_EQ(json::parse(found->body)["results"][0]["id"], "scene");

  // A missing index without --vocab is a clear start-up error, not a crash.
  ServerProcess broken({"serve", "--index", dir_->path() + "/none", "--port", "0"}, dir_->path() + "/broken.log");
  EXPECT_EQ(broken.Stop(0), ExitCodeFor(ErrorCode::kNotFound));  // signal 0: just wait for it to exit
  EXPECT_NE(broken.Log().find("--vocab"), std::string::npos) << broken.Log();
}

// A second server on the folder or the port of a running one is refused with a clear error, and the
// first goes on serving: no two processes write one index (index/storage/folder_lock.h), no two servers split
// the connections of one port (SO_REUSEPORT is off).
TEST_F(HttpServerTest, ASecondServerOnTheSameFolderOrPortIsRefused) {
  const std::string index_dir = dir_->path() + "/index-" + std::to_string(counter_++);
  auto first = Start({}, index_dir);
  ASSERT_EQ(StatusOf(first->Client().Post("/v1/images?id=box", box_, "image/png")), 201);

  const std::string folder_log = dir_->path() + "/server-" + std::to_string(counter_++) + ".log";
  ServerProcess same_folder({"serve", "--index", index_dir, "--port", "0", "--vocab", vocab_}, folder_log);
  EXPECT_EQ(same_folder.Wait(), 7) << same_folder.Log();
  EXPECT_NE(same_folder.Log().find("open in another process (pid " + std::to_string(first->pid()) + ")"),
            std::string::npos)
      << same_folder.Log();

  const std::string port_log = dir_->path() + "/server-" + std::to_string(counter_++) + ".log";
  ServerProcess same_port({"serve", "--index", dir_->path() + "/index-" + std::to_string(counter_++), "--port",
                           std::to_string(first->port()), "--vocab", vocab_},
                          port_log);
  EXPECT_EQ(same_port.port(), 0) << "a second server listens on the port of the first";
  EXPECT_NE(same_port.Wait(), 0) << same_port.Log();
  EXPECT_NE(same_port.Log().find("cannot bind 127.0.0.1:" + std::to_string(first->port())), std::string::npos)
      << same_port.Log();

  auto client = first->Client();
  EXPECT_EQ(StatusOf(client.Get("/readyz")), 200);
  EXPECT_EQ(StatusOf(client.Get("/v1/images/box")), 200);
}

TEST_F(HttpServerTest, KillNineDuringAddsLosesNoAcknowledgedImage) {
  const std::string index_dir = dir_->path() + "/kill9";
  std::set<std::string> acknowledged;
  std::set<std::string> attempted;
  {
    auto server = Start({}, index_dir);
    std::mutex mutex;
    std::atomic<bool> stop{false};
    const std::vector<const std::string*> images = {&box_, &scene_, &leuven_};
    std::vector<std::thread> writers;
    writers.reserve(2);
    for (int w = 0; w < 2; ++w) {
      writers.emplace_back([&, w] {
        auto client = server->Client();
        for (int i = 0; !stop; ++i) {
          const std::string id = "w" + std::to_string(w) + "-" + std::to_string(i);
          {
            std::lock_guard<std::mutex> lock(mutex);
            attempted.insert(id);
          }
          auto res = client.Post("/v1/images?id=" + id, *images[static_cast<size_t>(i) % images.size()], "image/png");
          if (!res) return;  // the server is gone
          if (res->status == 201) {
            std::lock_guard<std::mutex> lock(mutex);
            acknowledged.insert(id);
          }
        }
      });
    }
    // Kill once a few adds were acknowledged, while more are in flight (waits up to 120 s: a TSan build
    // on a loaded machine takes seconds per add).
    for (int i = 0; i < 24000; ++i) {
      {
        std::lock_guard<std::mutex> lock(mutex);
        if (acknowledged.size() >= 6) break;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    EXPECT_EQ(server->Stop(SIGKILL), 128 + SIGKILL);
    stop = true;
    for (auto& t : writers) t.join();
  }
  ASSERT_GE(acknowledged.size(), 6u);
  auto server = Start({}, index_dir, /*with_vocab=*/false);
  auto client = server->Client();
  for (const auto& id : acknowledged) {
    auto got = client.Get("/v1/images/" + id);
    ASSERT_TRUE(got);
    EXPECT_EQ(got->status, 200) << "acknowledged image " << id << " lost";
  }
  // Nothing half-added: every image present is one we tried to add, whole (features, usable in a query).
  auto list = client.Get("/v1/images?limit=1000");
  ASSERT_TRUE(list);
  auto page = json::parse(list->body);
  EXPECT_GE(page["total"].get<size_t>(), acknowledged.size());
  EXPECT_LE(page["total"].get<size_t>(), acknowledged.size() + 2);  // at most one unacknowledged add per writer
  for (const auto& image : page["images"]) {
    const std::string id = image["id"];
    EXPECT_TRUE(attempted.contains(id)) << id;
    EXPECT_GT(image["features"].get<int>(), 50) << id;
    auto similar = client.Get("/v1/images/" + id + "/similar?top_k=1");
    ASSERT_TRUE(similar);
    EXPECT_EQ(similar->status, 200) << similar->body;
  }
}

TEST_F(HttpServerTest, SaturatedExtractionAnswers503NotACrash) {
  auto server = Start({"--extractions", "1", "--extraction-wait-ms", "0"});
  std::vector<int> statuses(8, 0);
  std::vector<std::thread> clients;
  for (size_t i = 0; i < statuses.size(); ++i) {
    clients.emplace_back([&, i] {
      auto res = server->Client().Post("/v1/search", graf1_, "image/png");
      statuses[i] = res ? res->status : -1;
      if (res && res->status == 503) {
        auto body = json::parse(res->body);
        if (body["error"]["code"] != "resource_exhausted") statuses[i] = -2;
      }
    });
  }
  for (auto& t : clients) t.join();
  int ok = 0, busy = 0;
  for (int s : statuses) {
    EXPECT_TRUE(s == 200 || s == 503) << s;
    ok += s == 200;
    busy += s == 503;
  }
  EXPECT_GE(ok, 1);
  EXPECT_GE(busy, 1) << "8 concurrent 800x640 extractions with one slot and no wait should overflow";
  auto health = server->Client().Get("/healthz");
  ASSERT_TRUE(health);
  EXPECT_EQ(health->status, 200);
}

// ---- The web page's routes: static files, thumbnails, match correspondences -------------------------

// Width and height of a JPEG response (decoded), or {0, 0}.
std::pair<int, int> JpegSize(const std::string& bytes) {
  const cv::Mat raw(1, static_cast<int>(bytes.size()), CV_8UC1, const_cast<char*>(bytes.data()));
  const cv::Mat image = cv::imdecode(raw, cv::IMREAD_COLOR);
  return {image.cols, image.rows};
}

TEST_F(HttpServerTest, WebPageAndStaticFiles) {
  auto server = Start();
  auto client = server->Client();
  auto page = client.Get("/");
  ASSERT_TRUE(page);
  ASSERT_EQ(page->status, 200);
  EXPECT_EQ(page->get_header_value("Content-Type"), "text/html; charset=utf-8");
  EXPECT_NE(page->body.find(R"(src="/static/app.js")"), std::string::npos);
  EXPECT_NE(page->get_header_value("Content-Security-Policy").find("default-src 'self'"), std::string::npos);
  for (const auto& [path, type] : std::vector<std::pair<std::string, std::string>>{
           {"/static/app.js", "text/javascript; charset=utf-8"}, {"/static/style.css", "text/css; charset=utf-8"}}) {
    auto file = client.Get(path);
    ASSERT_TRUE(file);
    ASSERT_EQ(file->status, 200) << path;
    EXPECT_EQ(file->get_header_value("Content-Type"), type) << path;
    EXPECT_GT(file->body.size(), 100u) << path;
    // Revalidation: the same ETag gets 304 without a body.
    const std::string etag = file->get_header_value("ETag");
    ASSERT_EQ(etag.size(), 18u) << etag;
    auto again = client.Get(path, {{"If-None-Match", etag}});
    ASSERT_TRUE(again);
    EXPECT_EQ(again->status, 304) << path;
    EXPECT_TRUE(again->body.empty());
  }
  ExpectErrorShape(client.Get("/static/nope.js"), 404, "not_found");
  ExpectErrorShape(client.Get("/static/../CMakeLists.txt"), 404, "not_found");
  ExpectErrorShape(client.Post("/static/app.js", "x", "text/plain"), 405, "method_not_allowed");
}

TEST_F(HttpServerTest, ThumbnailsStoredAtAddSurviveRestartAndGoWithDelete) {
  const std::string index_dir = dir_->path() + "/thumbnails";
  std::string etag_before;
  {
    auto server = Start({}, index_dir);
    auto client = server->Client();
    ASSERT_EQ(StatusOf(client.Post("/v1/images?id=scene", scene_, "image/png")), 201);
    auto thumb = client.Get("/v1/images/scene/thumbnail");
    ASSERT_TRUE(thumb);
    ASSERT_EQ(thumb->status, 200) << thumb->body;
    EXPECT_EQ(thumb->get_header_value("Content-Type"), "image/jpeg");
    EXPECT_EQ(JpegSize(thumb->body), std::make_pair(256, 192));  // 512 x 384, default longest side 256
    etag_before = thumb->get_header_value("ETag");
    auto small = client.Get("/v1/images/scene/thumbnail?size=100");
    ASSERT_TRUE(small);
    ASSERT_EQ(small->status, 200);
    EXPECT_EQ(JpegSize(small->body), std::make_pair(100, 75));
    auto largest = client.Get("/v1/images/scene/thumbnail?size=512");
    ASSERT_TRUE(largest);
    EXPECT_EQ(JpegSize(largest->body), std::make_pair(512, 384));
    auto cached = client.Get("/v1/images/scene/thumbnail", {{"If-None-Match", etag_before}});
    ASSERT_TRUE(cached);
    EXPECT_EQ(cached->status, 304);
    // If-None-Match as caches and proxies send it: weak tags, lists, "*" (RFC 9110 weak comparison).
    for (const std::string& sent : {"W/" + etag_before, "\"other\", " + etag_before, std::string("*")}) {
      auto revalidated = client.Get("/v1/images/scene/thumbnail", {{"If-None-Match", sent}});
      ASSERT_TRUE(revalidated);
      EXPECT_EQ(revalidated->status, 304) << sent;
    }
    auto stale = client.Get("/v1/images/scene/thumbnail", {{"If-None-Match", "\"other\", W/\"another\""}});
    ASSERT_TRUE(stale);
    EXPECT_EQ(stale->status, 200);
    auto over = client.Get("/v1/images/scene/thumbnail?size=1000");  // larger than stored: the stored one
    ASSERT_TRUE(over);
    EXPECT_EQ(JpegSize(over->body), std::make_pair(512, 384));
    ExpectErrorShape(client.Get("/v1/images/scene/thumbnail?size=2049"), 400, "invalid_argument");
    ExpectErrorShape(client.Get("/v1/images/scene/thumbnail?size=8"), 400, "invalid_argument");
    ExpectErrorShape(client.Get("/v1/images/scene/thumbnail?sise=64"), 400, "invalid_argument");
    ExpectErrorShape(client.Get("/v1/images/nope/thumbnail"), 404, "not_found");
    EXPECT_EQ(server->Stop(SIGTERM), 0);
  }
  // After a restart the uploaded image (no source file on the server) still has its thumbnail.
  auto server = Start({}, index_dir, /*with_vocab=*/false);
  auto client = server->Client();
  auto thumb = client.Get("/v1/images/scene/thumbnail");
  ASSERT_TRUE(thumb);
  ASSERT_EQ(thumb->status, 200) << thumb->body;
  EXPECT_EQ(thumb->get_header_value("ETag"), etag_before);
  ASSERT_EQ(StatusOf(client.Delete("/v1/images/scene")), 200);
  ExpectErrorShape(client.Get("/v1/images/scene/thumbnail"), 404, "not_found");
}

TEST_F(HttpServerTest, ThumbnailsOfCliIndexedImagesComeFromTheirSourceFile) {
  // `oxbow index build` records each image's path; the server makes the thumbnail from it.
  const std::string index_dir = dir_->path() + "/cli-index";
  const std::string list = dir_->path() + "/cli-list.txt";
  {
    std::ofstream out(list);
    out << SamplePath("graf1.png") << "\n";
  }
  const std::string command = std::string(OXBOW_BINARY) + " index build --vocab " + vocab_ + " --list " + list +
                              " --out " + index_dir + " > /dev/null 2>&1";
  ASSERT_EQ(std::system(command.c_str()), 0) << command;
  auto server = Start({}, index_dir, /*with_vocab=*/false);
  auto client = server->Client();
  auto thumb = client.Get("/v1/images/graf1/thumbnail?size=200");
  ASSERT_TRUE(thumb);
  ASSERT_EQ(thumb->status, 200) << thumb->body;
  EXPECT_EQ(JpegSize(thumb->body), std::make_pair(200, 160));  // 800 x 640
}

TEST_F(HttpServerTest, MatchReturnsCorrespondencesWhenAsked) {
  auto server = Start();
  auto client = server->Client();
  httplib::MultipartFormDataItems plain = {Part("a", box_), Part("b", scene_)};
  auto without = client.Post("/v1/match", plain);
  ASSERT_TRUE(without);
  ASSERT_EQ(without->status, 200);
  EXPECT_FALSE(json::parse(without->body).contains("correspondences"));

  httplib::MultipartFormDataItems asked = {Part("a", box_), Part("b", scene_), Part("correspondences", "true")};
  auto with = client.Post("/v1/match", asked);
  ASSERT_TRUE(with);
  ASSERT_EQ(with->status, 200) << with->body;
  auto body = json::parse(with->body);
  ASSERT_TRUE(body["verified"].get<bool>());
  const auto& pairs = body["correspondences"];
  ASSERT_EQ(pairs.size(), body["inliers"].get<size_t>());
  // Every pair lies in its images and agrees with the fitted transform (b = T a, projective: the default
  // model hough-homography gives a homography) within a few pixels.
  const auto& t = body["transform"];
  std::vector<double> errors;
  for (const auto& p : pairs) {
    ASSERT_EQ(p.size(), 4u);
    const double ax = p[0], ay = p[1], bx = p[2], by = p[3];
    EXPECT_TRUE(ax >= 0 && ax < 324 && ay >= 0 && ay < 223) << p;
    EXPECT_TRUE(bx >= 0 && bx < 512 && by >= 0 && by < 384) << p;
    const double pw = t[2][0].get<double>() * ax + t[2][1].get<double>() * ay + t[2][2].get<double>();
    const double px = (t[0][0].get<double>() * ax + t[0][1].get<double>() * ay + t[0][2].get<double>()) / pw;
    const double py = (t[1][0].get<double>() * ax + t[1][1].get<double>() * ay + t[1][2].get<double>()) / pw;
    errors.push_back(std::hypot(px - bx, py - by));
  }
  std::sort(errors.begin(), errors.end());
  EXPECT_LT(errors[errors.size() / 2], 5.0);
  httplib::MultipartFormDataItems bad = {Part("a", box_), Part("b", scene_), Part("correspondences", "maybe")};
  ExpectErrorShape(client.Post("/v1/match", bad), 400, "invalid_argument");
}

}  // namespace
}  // namespace oxbow
