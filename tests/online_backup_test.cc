// Online backup against the real `oxbow serve`: POST /v1/admin/backup and
// `oxbow index backup` (another process) copy the index while a client keeps adding images; each copy
// holds exactly a prefix of the acknowledged adds, serves as an index of its own (restore = serve it),
// answers searches as the source does, and the route needs the API key.
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <filesystem>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "tests/support/e2e.h"
#include "tests/support/server_suite.h"

#include <httplib.h>

namespace oxbow {
namespace {

using nlohmann::json;
using testing::ServerProcess;

const httplib::Headers kKey = {{"X-API-Key", "s3cret"}};

class OnlineBackupTest : public testing::ServerSuite {
 protected:
  static void SetUpTestSuite() {
    SetUpServerSuite("oxbow-online-backup-test");
    for (const char* name : {"graf1.png", "box_in_scene.png", "leuvenA.jpg", "building.jpg"}) {
      std::vector<uchar> png;
      ASSERT_TRUE(cv::imencode(".png", testing::Texture(400, 300, name), png));
      pictures_.emplace_back(png.begin(), png.end());
    }
  }

  // `oxbow serve` with the API key on a new index; *index_dir gets its folder.
  static std::unique_ptr<ServerProcess> StartWithKey(std::string* index_dir) {
    auto server = StartServer({"--api-key", "s3cret"});
    *index_dir = dir_->path() + "/index-" + std::to_string(counter_ - 1);
    return server;
  }
  // `oxbow serve` over an existing index folder (no vocabulary: it must open as it is).
  static std::unique_ptr<ServerProcess> Restore(const std::string& index_dir) {
    auto server = std::make_unique<ServerProcess>(
        std::vector<std::string>{"serve", "--index", index_dir, "--port", "0"},
        dir_->path() + "/restore-" + std::to_string(counter_++) + ".log");
    EXPECT_TRUE(server->port() > 0 && server->WaitReady()) << server->Log();
    return server;
  }

  static std::set<std::string> Ids(const ServerProcess& server) {
    auto client = server.Client();
    auto res = client.Get("/v1/images?limit=1000");
    std::set<std::string> ids;
    if (!res || res->status != 200) {
      ADD_FAILURE() << "GET /v1/images failed";
      return ids;
    }
    const json list = json::parse(res->body);
    for (const auto& image : list["images"]) ids.insert(image["id"].get<std::string>());
    return ids;
  }
  // The adds are serial, so the committed states are the first k adds: the k the copy holds, which must
  // lie between the adds acknowledged before the backup started and those started before it ended.
  static void ExpectPrefix(const std::set<std::string>& ids, const std::vector<std::string>& order,
                           size_t acknowledged_before, size_t started_after) {
    const std::set<std::string> prefix(order.begin(), order.begin() + static_cast<std::ptrdiff_t>(ids.size()));
    EXPECT_EQ(ids, prefix) << "the copy is not a prefix of the add sequence";
    EXPECT_GE(ids.size(), acknowledged_before);
    EXPECT_LE(ids.size(), started_after);
  }

  static inline std::vector<std::string> pictures_;
};

TEST_F(OnlineBackupTest, RouteAndCliCopyAPrefixOfTheAcknowledgedAddsWhileServing) {
  std::string index_dir;
  auto server = StartWithKey(&index_dir);
  auto client = server->Client();

  // Authentication and arguments first.
  const std::string out_http = dir_->path() + "/backup-http";
  EXPECT_EQ(client.Post("/v1/admin/backup", json{{"out", out_http}}.dump(), "application/json")->status, 401);
  EXPECT_EQ(client.Post("/v1/admin/backup", {{"X-API-Key", "nope"}}, json{{"out", out_http}}.dump(),
                        "application/json")->status, 403);
  auto relative = client.Post("/v1/admin/backup", kKey, json{{"out", "backup"}}.dump(), "application/json");
  ASSERT_TRUE(relative);
  EXPECT_EQ(relative->status, 400) << relative->body;
  EXPECT_FALSE(std::filesystem::exists(out_http));

  // The order of the adds, the number started and the number acknowledged, as the client sees them.
  std::vector<std::string> order;
  order.reserve(400);
  for (int i = 0; i < 400; ++i) order.push_back("img-" + std::to_string(i));
  std::atomic<size_t> started{0}, acknowledged{0};
  std::atomic<bool> stop{false};
  std::thread adder([&] {
    auto c = server->Client();
    for (size_t i = 0; i < order.size() && !stop; ++i) {
      started = i + 1;
      auto res = c.Post(("/v1/images?id=" + order[i]).c_str(), kKey, pictures_[i % pictures_.size()], "image/png");
      if (!res || res->status != 201) {
        ADD_FAILURE() << "add " << order[i] << ": " << (res ? res->body : "no answer");
        return;
      }
      acknowledged = i + 1;
    }
  });
  for (int waited = 0; acknowledged < 3 && waited < 6000; ++waited) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  if (acknowledged < 3) {
    stop = true;
    adder.join();
    FAIL() << "no adds acknowledged in 60 s";
  }

  size_t before = acknowledged;
  auto backup = client.Post("/v1/admin/backup", kKey, json{{"out", out_http}}.dump(), "application/json");
  size_t after = started;
  ASSERT_TRUE(backup);
  ASSERT_EQ(backup->status, 200) << backup->body;
  const json answer = json::parse(backup->body);
  EXPECT_EQ(answer["out"], out_http);
  const size_t http_images = answer["images"].get<size_t>();
  const size_t http_before = before, http_after = after;

  const std::string out_cli = dir_->path() + "/backup-cli";
  before = acknowledged;
  int exit_code = -1;
  const std::string printed = testing::RunCommand(
      std::string(OXBOW_BINARY) + " index backup --index " + index_dir + " --out " + out_cli + " 2>/dev/null",
      &exit_code);
  after = started;
  ASSERT_EQ(exit_code, 0) << printed;
  const size_t cli_images = json::parse(printed)["images"].get<size_t>();
  stop = true;
  adder.join();

  // An existing folder is refused, through both.
  auto again = client.Post("/v1/admin/backup", kKey, "out=" + out_http, "application/x-www-form-urlencoded");
  ASSERT_TRUE(again);
  EXPECT_EQ(again->status, 409) << again->body;
  testing::RunCommand(std::string(OXBOW_BINARY) + " index backup --index " + index_dir + " --out " + out_cli +
                          " 2>/dev/null",
                      &exit_code);
  EXPECT_EQ(exit_code, 5);

  {
    auto restored = Restore(out_http);
    const auto ids = Ids(*restored);
    EXPECT_EQ(ids.size(), http_images);
    ExpectPrefix(ids, order, http_before, http_after);
    EXPECT_EQ(restored->Log().find("checkpoint unusable"), std::string::npos) << restored->Log();
  }
  {
    auto restored = Restore(out_cli);
    const auto ids = Ids(*restored);
    EXPECT_EQ(ids.size(), cli_images);
    ExpectPrefix(ids, order, before, after);
  }

  // A copy of the quiescent index answers a search exactly as the source does, thumbnails included.
  const std::string out_final = dir_->path() + "/backup-final";
  auto final_backup = client.Post("/v1/admin/backup", kKey, json{{"out", out_final}}.dump(), "application/json");
  ASSERT_TRUE(final_backup);
  ASSERT_EQ(final_backup->status, 200) << final_backup->body;
  auto restored = Restore(out_final);
  EXPECT_EQ(Ids(*restored), Ids(*server));
  auto copy_client = restored->Client();
  for (const auto& picture : pictures_) {
    auto a = client.Post("/v1/search?top_k=20", picture, "image/png");
    auto b = copy_client.Post("/v1/search?top_k=20", picture, "image/png");
    ASSERT_TRUE(a && b);
    ASSERT_EQ(a->status, 200);
    ASSERT_EQ(b->status, 200);
    const json ra = json::parse(a->body)["results"], rb = json::parse(b->body)["results"];
    ASSERT_EQ(ra.size(), rb.size());
    for (size_t i = 0; i < ra.size(); ++i) {
      EXPECT_EQ(ra[i]["id"], rb[i]["id"]);
      EXPECT_NEAR(ra[i]["score"].get<double>(), rb[i]["score"].get<double>(), 1e-6);
    }
  }
  auto thumbnail = copy_client.Get("/v1/images/img-0/thumbnail");
  ASSERT_TRUE(thumbnail);
  EXPECT_EQ(thumbnail->status, 200);
}

TEST_F(OnlineBackupTest, RouteIsRefusedWithoutAServerKey) {
  auto server = StartServer({});
  auto client = server->Client();
  const std::string out = dir_->path() + "/backup-keyless";
  auto refused = client.Post("/v1/admin/backup", json{{"out", out}}.dump(), "application/json");
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->status, 403) << refused->body;
  EXPECT_FALSE(std::filesystem::exists(out));
}

}  // namespace
}  // namespace oxbow
