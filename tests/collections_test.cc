// Collections over HTTP (api/collections.h, server/http/http_server.h): a real `oxbow serve --data` with
// an admin key; collections created, filled, searched and deleted; keys tried across collections and
// without; limits; metrics; the key file re-read on SIGHUP; a restart keeps collections, settings and keys.
#include <gtest/gtest.h>

#include <csignal>
#include <filesystem>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include <httplib.h>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "tests/support/server_suite.h"

namespace oxbow {
namespace {

using nlohmann::json;
using oxbow::testing::ServerProcess;

constexpr const char* kAdmin = "admin-key-of-the-collections-test";

int StatusOf(const httplib::Result& res) { return res ? res->status : -1; }
json BodyOf(const httplib::Result& res) { return res ? json::parse(res->body, nullptr, false) : json(); }
std::string CodeOf(const httplib::Result& res) {
  const json body = BodyOf(res);
  return body.is_object() && body.contains("error") ? body["error"].value("code", "") : "";
}
std::string MessageOf(const httplib::Result& res) {
  const json body = BodyOf(res);
  return body.is_object() && body.contains("error") ? body["error"].value("message", "") : "";
}
httplib::Headers Key(const std::string& key) { return {{"X-API-Key", key}}; }

class CollectionsTest : public testing::ServerSuite {
 protected:
  static void SetUpTestSuite() { SetUpServerSuite("oxbow-collections-test"); }

  // `oxbow serve --data DIR` with `extra` flags; ready.
  static std::unique_ptr<ServerProcess> StartData(const std::string& data, const std::vector<std::string>& extra) {
    std::vector<std::string> args = {"serve", "--data", data, "--port", "0"};
    args.insert(args.end(), extra.begin(), extra.end());
    auto server = std::make_unique<ServerProcess>(args, data + ".log");
    EXPECT_TRUE(server->port() > 0 && server->WaitReady()) << server->Log();
    return server;
  }
  static httplib::Result Create(httplib::Client& client, const json& body, const std::string& key = kAdmin) {
    return client.Post("/v1/collections", Key(key), body.dump(), "application/json");
  }
  static std::string MakeKey(httplib::Client& client, const std::string& collection, const std::string& access) {
    auto res = client.Post("/v1/collections/" + collection + "/keys", Key(kAdmin), json{{"access", access}}.dump(),
                           "application/json");
    EXPECT_EQ(StatusOf(res), 201) << (res ? res->body : "");
    return BodyOf(res).value("key", "");
  }
  httplib::Result Add(httplib::Client& client, const std::string& collection, const std::string& id,
                      const std::string& key) const {
    return client.Post("/v1/collections/" + collection + "/images?id=" + id, Key(key), image_, "image/png");
  }
};

TEST_F(CollectionsTest, KeysLimitsAndIsolationOverHttp) {
  const std::string data = dir_->path() + "/data";
  auto server = StartData(data, {"--api-key", kAdmin, "--vocab", vocab_});
  auto client = server->Client();

  // --vocab created the public collection "default", which the routes without a prefix act on.
  auto listed = client.Get("/v1/collections");
  ASSERT_EQ(StatusOf(listed), 200);
  ASSERT_EQ(BodyOf(listed)["collections"].size(), 1u) << listed->body;
  EXPECT_EQ(BodyOf(listed)["collections"][0]["name"], "default");
  EXPECT_EQ(BodyOf(listed)["collections"][0]["public"], true);

  // Creating needs the admin key; names and bodies are checked.
  EXPECT_EQ(StatusOf(Create(client, {{"name", "paris"}, {"vocabulary", vocab_}}, "")), 401);
  EXPECT_EQ(StatusOf(Create(client, {{"name", "paris"}, {"vocabulary", vocab_}}, "wrong")), 403);
  EXPECT_EQ(CodeOf(Create(client, {{"name", "Bad name"}, {"vocabulary", vocab_}})), "invalid_argument");
  EXPECT_EQ(CodeOf(Create(client, {{"name", "x"}, {"vocabulary", vocab_}, {"colour", "red"}})), "invalid_argument");
  EXPECT_EQ(CodeOf(Create(client, {{"name", "x"}, {"vocabulary", data + "/missing.oxvoc"}})), "not_found");
  auto paris = Create(client, {{"name", "paris"}, {"vocabulary", vocab_}});
  ASSERT_EQ(StatusOf(paris), 201) << paris->body;
  EXPECT_EQ(BodyOf(paris)["public"], false);
  EXPECT_EQ(BodyOf(paris)["images"], 0);
  EXPECT_EQ(StatusOf(Create(client, {{"name", "paris"}, {"vocabulary", vocab_}})), 409);
  auto tokyo = Create(client, {{"name", "tokyo"}, {"vocabulary", {{"like", "paris"}}}, {"public", true}, {"max_images", 1}});
  ASSERT_EQ(StatusOf(tokyo), 201) << tokyo->body;
  EXPECT_EQ(BodyOf(tokyo)["vocabulary"]["fingerprint"], BodyOf(paris)["vocabulary"]["fingerprint"]);
  EXPECT_EQ(BodyOf(tokyo)["limits"]["max_images"], 1);

  const std::string paris_write = MakeKey(client, "paris", "write");
  const std::string paris_read = MakeKey(client, "paris", "read");
  const std::string tokyo_write = MakeKey(client, "tokyo", "write");
  ASSERT_FALSE(paris_write.empty() || paris_read.empty() || tokyo_write.empty());
  // The key file keeps salted hashes, never a key.
  const std::string key_text = testing::FileBytes(data + "/keys.json");
  EXPECT_NE(key_text.find("sha256"), std::string::npos);
  EXPECT_EQ(key_text.find(paris_write.substr(17)), std::string::npos);

  // Writes: only paris's write key (or the admin's).
  EXPECT_EQ(StatusOf(Add(client, "paris", "a", "")), 401);
  EXPECT_EQ(StatusOf(Add(client, "paris", "a", tokyo_write)), 403);
  EXPECT_EQ(StatusOf(Add(client, "paris", "a", paris_read)), 403);
  auto added = Add(client, "paris", "a", paris_write);
  ASSERT_EQ(StatusOf(added), 201) << added->body;
  EXPECT_EQ(added->get_header_value("Location"), "/v1/collections/paris/images/a");
  // Two other pictures, so that the words of "a" are not in every image (tf-idf weighs those 0).
  for (const auto& [id, sample] : {std::pair{"b", "box_in_scene.png"}, std::pair{"c", "fruits.jpg"}}) {
    std::vector<uchar> png;
    ASSERT_TRUE(cv::imencode(".png", oxbow::testing::Texture(400, 300, sample, 0, 0), png));
    auto other = client.Post(std::string("/v1/collections/paris/images?id=") + id, Key(paris_write),
                             std::string(png.begin(), png.end()), "image/png");
    ASSERT_EQ(StatusOf(other), 201) << other->body;
  }

  // Reads of a private collection: its keys only. Another collection's key learns nothing: the answer is
  // the one for a collection that does not exist.
  auto search = [&](const std::string& collection, const std::string& key) {
    return client.Post("/v1/collections/" + collection + "/search", Key(key), image_, "image/png");
  };
  EXPECT_EQ(StatusOf(search("paris", "")), 401);
  auto foreign = search("paris", tokyo_write);
  auto missing = search("nowhere", tokyo_write);
  EXPECT_EQ(StatusOf(foreign), 403);
  EXPECT_EQ(StatusOf(missing), 403);
  std::string foreign_message = MessageOf(foreign), missing_message = MessageOf(missing);
  ASSERT_NE(foreign_message.find("'paris'"), std::string::npos) << foreign_message;
  foreign_message.replace(foreign_message.find("'paris'"), 7, "'nowhere'");
  EXPECT_EQ(foreign_message, missing_message);
  EXPECT_EQ(StatusOf(client.Get("/v1/collections/paris", Key(tokyo_write))), 403);
  EXPECT_EQ(StatusOf(client.Get("/v1/collections/nowhere", Key(tokyo_write))), 403);
  EXPECT_EQ(StatusOf(client.Get("/v1/collections/nowhere")), 401);
  EXPECT_EQ(CodeOf(client.Get("/v1/collections/nowhere", Key(kAdmin))), "not_found");
  auto found = search("paris", paris_read);
  ASSERT_EQ(StatusOf(found), 200) << found->body;
  ASSERT_FALSE(BodyOf(found)["results"].empty()) << found->body;
  EXPECT_EQ(BodyOf(found)["results"][0]["id"], "a");
  auto described = client.Get("/v1/collections/paris", Key(paris_read));
  ASSERT_EQ(StatusOf(described), 200);
  EXPECT_EQ(BodyOf(described)["images"], 3);
  EXPECT_GT(BodyOf(described)["disk_bytes"].get<uint64_t>(), 0u);
  EXPECT_TRUE(BodyOf(described).contains("stats"));
  EXPECT_EQ(StatusOf(client.Get("/v1/collections/paris/images/a/thumbnail", Key(paris_read))), 200);
  // Each collection is its own index: default and tokyo do not hold paris's image.
  EXPECT_EQ(BodyOf(client.Get("/v1/images"))["total"], 0);
  EXPECT_EQ(StatusOf(client.Get("/v1/collections/tokyo/images/a")), 404);
  // The list shows a key holder its collection and the public ones.
  auto visible = BodyOf(client.Get("/v1/collections", Key(paris_read)))["collections"];
  EXPECT_EQ(visible.size(), 3u);
  EXPECT_EQ(BodyOf(client.Get("/v1/collections", Key(tokyo_write)))["collections"].size(), 2u);

  // A public collection is read without a key; its limit answers 507.
  ASSERT_EQ(StatusOf(Add(client, "tokyo", "t1", tokyo_write)), 201);
  auto full = Add(client, "tokyo", "t2", tokyo_write);
  EXPECT_EQ(StatusOf(full), 507);
  EXPECT_EQ(CodeOf(full), "collection_full");
  EXPECT_EQ(BodyOf(client.Get("/v1/collections/tokyo/images"))["total"], 1);
  EXPECT_EQ(StatusOf(client.Delete("/v1/collections/tokyo/images/t1")), 401);

  // Keys: listed without their secret, revoked.
  auto keys = client.Get("/v1/collections/paris/keys", Key(kAdmin));
  ASSERT_EQ(StatusOf(keys), 200);
  ASSERT_EQ(BodyOf(keys)["keys"].size(), 2u);
  EXPECT_EQ(keys->body.find(paris_read.substr(17)), std::string::npos);
  EXPECT_EQ(StatusOf(client.Get("/v1/collections/paris/keys", Key(paris_write))), 403);
  const std::string read_id = paris_read.substr(4, 12);
  EXPECT_EQ(StatusOf(client.Delete("/v1/collections/paris/keys/" + read_id, Key(kAdmin))), 200);
  EXPECT_EQ(StatusOf(search("paris", paris_read)), 403);

  // Metrics: per-collection series.
  const std::string metrics = client.Get("/metrics")->body;
  EXPECT_NE(metrics.find(R"(route="/v1/collections/{name}/images",method="POST",status="201",collection="paris"} 3)"),
            std::string::npos) << metrics;
  EXPECT_NE(metrics.find(R"(oxbow_index_images{collection="paris"} 3)"), std::string::npos) << metrics;
  // Every refusal is logged with its request id.
  const std::string id = foreign->get_header_value("X-Request-Id");
  EXPECT_TRUE(server->WaitForLog("http " + id + " refused")) << server->Log();

  // Deleting a collection removes its folder and its keys.
  EXPECT_EQ(StatusOf(client.Delete("/v1/collections/tokyo", Key(tokyo_write))), 403);
  EXPECT_EQ(StatusOf(client.Delete("/v1/collections/tokyo", Key(kAdmin))), 200);
  EXPECT_FALSE(std::filesystem::exists(data + "/tokyo"));
  EXPECT_EQ(CodeOf(client.Get("/v1/collections/tokyo", Key(kAdmin))), "not_found");
  ASSERT_EQ(StatusOf(Create(client, {{"name", "tokyo"}, {"vocabulary", vocab_}})), 201);
  EXPECT_EQ(StatusOf(Add(client, "tokyo", "t1", tokyo_write)), 403);

  // A restart keeps the collections, their images, settings and keys.
  ASSERT_EQ(server->Stop(), 0) << server->Log();
  server = StartData(data, {"--api-key", kAdmin});
  auto restarted = server->Client();
  auto search_again = [&](const std::string& collection, const std::string& key) {
    return restarted.Post("/v1/collections/" + collection + "/search", Key(key), image_, "image/png");
  };
  EXPECT_EQ(BodyOf(restarted.Get("/v1/collections", Key(kAdmin)))["collections"].size(), 3u);
  EXPECT_EQ(StatusOf(search_again("paris", "")), 401);
  EXPECT_EQ(StatusOf(search_again("paris", paris_write)), 200);
  EXPECT_EQ(BodyOf(restarted.Get("/v1/collections/paris", Key(paris_write)))["images"], 3);

  // The key file is re-read on SIGHUP: a key removed by hand stops working.
  {
    std::ofstream out(data + "/keys.json", std::ios::trunc);
    out << R"({"keys": []})";
  }
  server->Signal(SIGHUP);
  EXPECT_TRUE(server->WaitForLog("re-read the collections' key file")) << server->Log();
  EXPECT_EQ(StatusOf(search_again("paris", paris_write)), 403);
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

TEST_F(CollectionsTest, OneIndexFolderIsTheDefaultCollection) {
  auto server = StartServer({"--api-key", kAdmin});
  auto client = server->Client();
  auto listed = client.Get("/v1/collections");
  ASSERT_EQ(StatusOf(listed), 200);
  ASSERT_EQ(BodyOf(listed)["collections"].size(), 1u);
  EXPECT_EQ(BodyOf(listed)["collections"][0]["name"], "default");
  EXPECT_EQ(CodeOf(Create(client, {{"name", "paris"}, {"vocabulary", vocab_}})), "incompatible");
  // /v1/collections/default/... and /v1/... are the same collection.
  ASSERT_EQ(StatusOf(client.Post("/v1/images?id=x", Key(kAdmin), image_, "image/png")), 201);
  EXPECT_EQ(StatusOf(client.Get("/v1/collections/default/images/x")), 200);
  EXPECT_EQ(BodyOf(client.Get("/v1/collections/default/stats"))["images"], 1);
  EXPECT_EQ(StatusOf(client.Delete("/v1/collections/default/images/x", Key(kAdmin))), 200);
  EXPECT_EQ(StatusOf(client.Get("/v1/images/x")), 404);
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

// The duplicate search as a job: started with write access, followed and cancelled with the
// collection's keys.
TEST_F(CollectionsTest, DuplicateSearchAsAJob) {
  const std::string data = dir_->path() + "/jobs-data";
  auto server = StartData(data, {"--api-key", kAdmin, "--vocab", vocab_});
  auto client = server->Client();
  ASSERT_EQ(StatusOf(Create(client, {{"name", "p"}, {"vocabulary", vocab_}})), 201);
  const std::string write = MakeKey(client, "p", "write");
  const std::string other = MakeKey(client, "default", "read");
  std::vector<uchar> png;
  ASSERT_TRUE(cv::imencode(".png", oxbow::testing::Texture(400, 300, "box_in_scene.png", 0, 0), png));
  const std::string second(png.begin(), png.end());
  ASSERT_EQ(StatusOf(Add(client, "p", "a", write)), 201);
  ASSERT_EQ(StatusOf(Add(client, "p", "a-copy", write)), 201);
  ASSERT_EQ(StatusOf(client.Post("/v1/collections/p/images?id=b", Key(write), second, "image/png")), 201);

  EXPECT_EQ(StatusOf(client.Post("/v1/collections/p/duplicates", "", "application/json")), 401);
  EXPECT_EQ(CodeOf(client.Post("/v1/collections/p/duplicates", Key(write), R"({"candidates": 0})", "application/json")),
            "invalid_argument");
  auto started = client.Post("/v1/collections/p/duplicates", Key(write), "", "application/json");
  ASSERT_EQ(StatusOf(started), 202) << started->body;
  const std::string job = BodyOf(started)["job"];
  EXPECT_EQ(started->get_header_value("Location"), "/v1/jobs/" + job);
  EXPECT_EQ(StatusOf(client.Get("/v1/jobs/" + job)), 401);
  EXPECT_EQ(StatusOf(client.Get("/v1/jobs/" + job, Key(other))), 403);
  json status;
  for (int i = 0; i < 600; ++i) {
    status = BodyOf(client.Get("/v1/jobs/" + job, Key(write)));
    if (status.value("state", "") != "running") break;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  ASSERT_EQ(status["state"], "done") << status.dump();
  EXPECT_EQ(status["total"], 3);
  EXPECT_EQ(status["done"], 3);
  const json& pairs = status["result"]["pairs"];
  ASSERT_EQ(pairs.size(), 1u) << status.dump();
  EXPECT_EQ(pairs[0]["a"], "a");
  EXPECT_EQ(pairs[0]["b"], "a-copy");
  EXPECT_EQ(pairs[0]["kind"], "exact");
  EXPECT_EQ(StatusOf(client.Delete("/v1/jobs/" + job, Key(other))), 403);
  EXPECT_EQ(StatusOf(client.Delete("/v1/jobs/" + job, Key(write))), 200);
  EXPECT_EQ(CodeOf(client.Get("/v1/jobs/" + job, Key(kAdmin))), "not_found");
  // The routes without a prefix start a job on "default".
  auto on_default = client.Post("/v1/duplicates", Key(kAdmin), "", "application/json");
  ASSERT_EQ(StatusOf(on_default), 202);
  EXPECT_EQ(BodyOf(on_default)["collection"], "default");
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

TEST_F(CollectionsTest, WithoutAnAdminKeyCollectionsCannotBeCreated) {
  const std::string data = dir_->path() + "/open-data";
  auto server = StartData(data, {"--vocab", vocab_});
  auto client = server->Client();
  EXPECT_EQ(StatusOf(Create(client, {{"name", "paris"}, {"vocabulary", vocab_}}, "")), 403);
  EXPECT_EQ(StatusOf(client.Delete("/v1/collections/default")), 403);
  // The image routes stay open, as on a single index without a key.
  EXPECT_EQ(StatusOf(client.Post("/v1/collections/default/images?id=x", image_, "image/png")), 201);
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

}  // namespace
}  // namespace oxbow
