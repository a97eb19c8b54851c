// Hostile parameters against the real `oxbow serve`: metadata nested deep
// enough to overflow a worker's stack in a recursive JSON dump, ids that read as the /similar and
// /thumbnail sub-routes, and repeated parameters. Each refused request gets a 400 naming the rule, the
// server stays up and nothing stored changes. A server that dies on a request (the client sees no
// response) is reported by these tests as a status of -1. Last, large request bodies
// must give their memory back to the system once answered.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <memory>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "index/image_index.h"
#include "sift/sift.h"
#include "tests/support/e2e.h"
#include "tests/support/samples.h"
#include "tests/support/temp_dir.h"

namespace oxbow {
namespace {

using nlohmann::json;

int StatusOf(const httplib::Result& res) { return res ? res->status : -1; }

// `depth` nested arrays: the shape of the crash report (100000 deep, 195 KiB).
std::string Nested(int depth) { return std::string(static_cast<size_t>(depth), '[') + std::string(static_cast<size_t>(depth), ']'); }

// A 400 whose message contains `says`.
void ExpectRefused(const httplib::Result& res, const std::string& says) {
  ASSERT_TRUE(res) << "no response: the server crashed or reset the connection";
  EXPECT_EQ(res->status, 400) << res->body;
  const auto body = json::parse(res->body, nullptr, false);
  ASSERT_FALSE(body.is_discarded()) << res->body;
  EXPECT_EQ(body["error"]["code"], "invalid_argument") << res->body;
  EXPECT_NE(body["error"]["message"].get<std::string>().find(says), std::string::npos) << res->body;
}

class HostileParamsTest : public ::testing::Test {
 protected:
  // An index holding what an older server or `oxbow index add` could store: "a", the id "a/similar"
  // (which ParseAddParams now refuses) and metadata nested 100000 deep (which it refuses too).
  static void SetUpTestSuite() {
    dir_ = new oxbow::testing::TempDir("oxbow-hostile-params-test");
    std::vector<uchar> png;
    ASSERT_TRUE(cv::imencode(".png", oxbow::testing::Texture(400, 300), png));
    image_.assign(png.begin(), png.end());
    const std::string image_path = dir_->path() + "/texture.png";
    std::ofstream(image_path, std::ios::binary) << image_;
    index_ = dir_->path() + "/index";
    const std::string settings = testing::TestSiftOptions().Describe();
    auto vocabulary = oxbow::testing::RandomVocabulary(settings);
    ASSERT_TRUE(vocabulary) << vocabulary.error().ToString();
    auto index = index::ImageIndex::Create(index_, *vocabulary, settings);
    ASSERT_TRUE(index) << index.error().ToString();
    auto extractor = sift::SiftExtractor::Create(testing::TestSiftOptions());
    ASSERT_TRUE(extractor) << extractor.error().ToString();
    auto features = extractor->ExtractFromFile(image_path);
    ASSERT_TRUE(features) << features.error().ToString();
    for (const auto& [id, metadata] : std::vector<std::pair<std::string, std::string>>{
             {"a", R"({"k":1})"}, {"a/similar", R"({"k":2})"}, {"deep-stored", Nested(100000)}}) {
      auto added = (*index)->Add(id, *features, {image_path, metadata, settings});
      ASSERT_TRUE(added) << added.error().ToString();
    }
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  void SetUp() override {
    server_ = std::make_unique<oxbow::testing::ServerProcess>(
        std::vector<std::string>{"serve", "--index", index_, "--port", "0"}, dir_->path() + "/server.log");
    ASSERT_TRUE(server_->port() > 0 && server_->WaitReady()) << server_->Log();
  }
  void TearDown() override {
    if (server_) {
      EXPECT_EQ(server_->Stop(), 0) << server_->Log();  // alive to the end, and stops cleanly
    }
  }

  int64_t StoredImages() {
    auto res = server_->Client().Get("/v1/stats");
    return res && res->status == 200 ? json::parse(res->body)["images"].get<int64_t>() : -1;
  }
  int StatusOfImage(const std::string& encoded_id) { return StatusOf(server_->Client().Get("/v1/images/" + encoded_id)); }

  static inline oxbow::testing::TempDir* dir_ = nullptr;
  static inline std::string index_;
  static inline std::string image_;
  std::unique_ptr<oxbow::testing::ServerProcess> server_;
};

TEST_F(HostileParamsTest, DeeplyNestedMetadataIsRefusedAndTheServerStaysUp) {
  auto client = server_->Client();
  const int64_t before = StoredImages();
  ASSERT_EQ(before, 3);
  const httplib::MultipartFormDataItems crash = {{"id", "nested", "", ""},
                                                 {"metadata", Nested(100000), "", ""},
                                                 {"file", image_, "t.png", "image/png"}};
  ExpectRefused(client.Post("/v1/images", crash), "parameter 'metadata' must be at most");
  const httplib::MultipartFormDataItems just_over = {{"id", "nested", "", ""},
                                                     {"metadata", Nested(65), "", ""},
                                                     {"file", image_, "t.png", "image/png"}};
  ExpectRefused(client.Post("/v1/images", just_over), "64 levels");
  const httplib::MultipartFormDataItems large = {{"id", "nested", "", ""},
                                                 {"metadata", json(std::string(20000, 'x')).dump(), "", ""},
                                                 {"file", image_, "t.png", "image/png"}};
  ExpectRefused(client.Post("/v1/images", large), "at most 16384 bytes");
  EXPECT_EQ(StatusOf(client.Get("/healthz")), 200);
  EXPECT_EQ(StatusOfImage("nested"), 404);
  EXPECT_EQ(StoredImages(), before);
  // At the limit it is stored and returned as the document it is.
  const httplib::MultipartFormDataItems at_limit = {{"id", "nested", "", ""},
                                                    {"metadata", Nested(64), "", ""},
                                                    {"file", image_, "t.png", "image/png"}};
  ASSERT_EQ(StatusOf(client.Post("/v1/images", at_limit)), 201);
  auto got = client.Get("/v1/images/nested");
  ASSERT_EQ(StatusOf(got), 200);
  EXPECT_EQ(json::parse(got->body)["metadata"].dump(), Nested(64));
  ASSERT_EQ(StatusOf(client.Delete("/v1/images/nested")), 200);
}

// Metadata stored deeper than the limit (older server, `oxbow index add --metadata`) comes back as its
// text: parsed, its dump recursed once per level on every GET, list and search that returned it.
TEST_F(HostileParamsTest, DeepStoredMetadataIsReturnedAsText) {
  auto got = server_->Client().Get("/v1/images/deep-stored");
  ASSERT_EQ(StatusOf(got), 200) << "no response: the server crashed";
  const auto metadata = json::parse(got->body)["metadata"];
  ASSERT_TRUE(metadata.is_string());
  EXPECT_EQ(metadata.get<std::string>().size(), 200000u);
  EXPECT_EQ(StatusOf(server_->Client().Get("/v1/images?limit=10")), 200);
}

// The command line keeps the same rules: `oxbow index add --metadata` refuses what POST /v1/images
// refuses (stored, deeper metadata would crash whoever dumps it), and `oxbow query` prints stored deep
// metadata as its text (a recursive dump of it would crash).
TEST_F(HostileParamsTest, CommandLineAppliesTheMetadataLimits) {
  const std::string copy = dir_->path() + "/cli-index";
  std::filesystem::remove_all(copy);
  std::filesystem::copy(index_, copy, std::filesystem::copy_options::recursive);
  const std::string image_path = dir_->path() + "/texture.png";
  const std::string deep = dir_->path() + "/deep.json";
  std::ofstream(deep) << Nested(8000);  // under the size limit, over the depth limit
  int rc = 0;
  std::string out = oxbow::testing::RunCommand(std::string(OXBOW_BINARY) + " index add --index " + copy + " --id cli-deep" +
                                                   " --metadata \"$(cat " + deep + ")\" " + image_path + " 2>&1", &rc);
  EXPECT_EQ(rc, 2) << out;
  EXPECT_NE(out.find("--metadata must nest"), std::string::npos) << out;
  // A second, different picture: the three stored copies of the texture then share words that do not
  // occur in every image, so their idf is positive and the query finds them.
  cv::Mat noise(300, 400, CV_8UC1);
  cv::RNG(7).fill(noise, cv::RNG::UNIFORM, 0, 256);
  cv::GaussianBlur(noise, noise, cv::Size(0, 0), 2.0);
  const std::string other = dir_->path() + "/other.png";
  ASSERT_TRUE(cv::imwrite(other, noise));
  out = oxbow::testing::RunCommand(std::string(OXBOW_BINARY) + " index add --index " + copy + " " + other, &rc);
  ASSERT_EQ(rc, 0) << out;
  out = oxbow::testing::RunCommand(std::string(OXBOW_BINARY) + " query --index " + copy + " --top-k 5 " + image_path, &rc);
  ASSERT_EQ(rc, 0) << "oxbow query over stored deep metadata: " << out.substr(0, 2000);
  const json results = json::parse(out.substr(out.find('{')))["results"];
  bool saw_deep = false;
  for (const auto& r : results) saw_deep |= r["id"] == "deep-stored" && r["metadata"].is_string();
  EXPECT_TRUE(saw_deep) << out.substr(0, 2000);
}

TEST_F(HostileParamsTest, IdsEndingInASubrouteAreRefusedAndStoredOnesStayReachable) {
  auto client = server_->Client();
  // Stored before the rule: reachable with the slash encoded, also its own sub-routes.
  auto stored = client.Get("/v1/images/a%2Fsimilar");
  ASSERT_EQ(StatusOf(stored), 200);
  EXPECT_EQ(json::parse(stored->body)["id"], "a/similar");
  EXPECT_EQ(json::parse(stored->body)["metadata"]["k"], 2);
  auto thumbnail = client.Get("/v1/images/a%2Fsimilar/thumbnail");
  ASSERT_EQ(StatusOf(thumbnail), 200);
  EXPECT_EQ(thumbnail->get_header_value("Content-Type"), "image/jpeg");
  auto similar = client.Get("/v1/images/a%2Fsimilar/similar");
  ASSERT_EQ(StatusOf(similar), 200);
  EXPECT_EQ(json::parse(similar->body)["query"]["id"], "a/similar");
  // A literal slash still names the sub-route of "a", encoded letters or not.
  for (const char* path : {"/v1/images/a/similar", "/v1/images/a/%73imilar"}) {
    auto of_a = client.Get(path);
    ASSERT_EQ(StatusOf(of_a), 200) << path;
    EXPECT_EQ(json::parse(of_a->body)["query"]["id"], "a") << path;
  }
  // New ones are refused, with the rule named, and not stored.
  for (const char* id : {"b%2Fsimilar", "b%2Fthumbnail"}) {
    ExpectRefused(client.Post(std::string("/v1/images?id=") + id, image_, "image/png"), "must not end in '/similar'");
  }
  ExpectRefused(client.Post("/v1/images?id=a%2Fsimilar&replace=true", image_, "image/png"), "must not end in");
  EXPECT_EQ(StatusOfImage("b%2Fsimilar"), 404);
  EXPECT_EQ(StoredImages(), 3);
}

TEST_F(HostileParamsTest, RepeatedParametersAreRefused) {
  auto client = server_->Client();
  ExpectRefused(client.Post("/v1/search?top_k=5&top_k=500000", image_, "image/png"), "'top_k' is given 2 times");
  ExpectRefused(client.Get("/v1/images/a/similar?top_k=5&top_k=6"), "'top_k'");
  ExpectRefused(client.Get("/v1/images?limit=1&limit=2"), "'limit'");
  ExpectRefused(client.Get("/v1/images/a/thumbnail?size=64&size=128"), "'size'");
  ExpectRefused(client.Post("/v1/images?id=dupA&id=dupB", image_, "image/png"), "'id' is given 2 times");
  // In multipart fields, and once in each.
  const httplib::MultipartFormDataItems twice = {{"id", "dupA", "", ""}, {"id", "dupB", "", ""},
                                                 {"file", image_, "t.png", "image/png"}};
  ExpectRefused(client.Post("/v1/images", twice), "'id'");
  const httplib::MultipartFormDataItems once_here = {{"id", "dupB", "", ""}, {"file", image_, "t.png", "image/png"}};
  ExpectRefused(client.Post("/v1/images?id=dupA", once_here), "'id'");
  // Two images for one add: which one is meant is as unknown.
  const httplib::MultipartFormDataItems two_files = {{"id", "dupA", "", ""}, {"file", image_, "t.png", "image/png"},
                                                     {"file", image_, "u.png", "image/png"}};
  ExpectRefused(client.Post("/v1/images", two_files), "'file'");
  const httplib::MultipartFormDataItems search_twice = {{"top_k", "5", "", ""}, {"file", image_, "t.png", "image/png"}};
  ExpectRefused(client.Post("/v1/search?top_k=500000", search_twice), "'top_k'");
  EXPECT_EQ(StatusOfImage("dupA"), 404);
  EXPECT_EQ(StatusOfImage("dupB"), 404);
  EXPECT_EQ(StoredImages(), 3);
  // Given once, each still works.
  EXPECT_EQ(StatusOf(client.Post("/v1/search?top_k=5", image_, "image/png")), 200);
}

// Resident memory of a process, from /proc (MiB).
int64_t ResidentMiB(pid_t pid) {
  std::ifstream status("/proc/" + std::to_string(pid) + "/status");
  for (std::string line; std::getline(status, line);) {
    if (line.rfind("VmRSS:", 0) == 0) return std::stoll(line.substr(6)) / 1024;
  }
  return -1;
}

// Large requests give their memory back. Three bursts of 8 concurrent 20 MB bodies that are not images
// (each read in full, then refused): with glibc's own raised mmap threshold the later bodies would stay in
// its arenas (~450 MiB resident); with the server's fixed threshold the RSS comes back to within 64 MiB of
// where it started.
TEST_F(HostileParamsTest, LargeBodiesGiveTheirMemoryBack) {
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
  GTEST_SKIP() << "sanitizer builds replace glibc's malloc (ASan also quarantines freed blocks): the mmap "
                  "threshold under test does not apply; the normal suite measures it";
#endif
  std::string junk(size_t{20'000'000}, ' ');  // every byte overwritten below
  std::mt19937 rng(3);
  for (char& c : junk) c = static_cast<char>(rng());
  const int64_t start = ResidentMiB(server_->pid());
  ASSERT_GT(start, 0);
  for (int burst = 0; burst < 3; ++burst) {
    std::vector<std::thread> clients;
    clients.reserve(8);
    std::vector<int> statuses(8, 0);
    for (int i = 0; i < 8; ++i) {
      clients.emplace_back([&, i] { statuses[static_cast<size_t>(i)] = StatusOf(server_->Client().Post("/v1/search", junk, "image/jpeg")); });
    }
    for (auto& t : clients) t.join();
    for (int status : statuses) EXPECT_EQ(status, 400);
  }
  // Freed blocks go back at once; the poll only waits for the last worker to finish its response.
  int64_t after = ResidentMiB(server_->pid());
  for (int i = 0; i < 100 && after > start + 64; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    after = ResidentMiB(server_->pid());
  }
  EXPECT_LE(after, start + 64) << "resident MiB at start " << start << ", after three bursts " << after;
}

}  // namespace
}  // namespace oxbow
