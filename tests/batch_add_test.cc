// POST /v1/images/batch against the real `oxbow serve`: several images in one request
// are added with one index transaction, each answered on its own (an undecodable image, a taken or
// repeated id, a bad id or metadata fail alone), the image cap refuses the request with nothing stored,
// the API key guards it, and every image acknowledged before a kill -9 is there after a restart.
#include <signal.h>

#include <gtest/gtest.h>

#include <memory>
#include <string>
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

struct Upload {
  std::string id;
  std::string image;
  std::string metadata;  // "" = none
};

// The multipart body of a batch: for each upload an `image` part and an `id` part, in order; `metadata`
// parts (one per upload) when any upload has metadata.
httplib::MultipartFormDataItems BatchBody(const std::vector<Upload>& uploads) {
  httplib::MultipartFormDataItems items;
  bool any_metadata = false;
  for (const auto& u : uploads) any_metadata = any_metadata || !u.metadata.empty();
  for (const auto& u : uploads) {
    items.push_back({"image", u.image, u.id + ".png", "image/png"});
    items.push_back({"id", u.id, "", ""});
    if (any_metadata) items.push_back({"metadata", u.metadata, "", ""});
  }
  return items;
}

json Parse(const httplib::Result& res) {
  if (!res) return json();
  return json::parse(res->body, nullptr, false);
}

class BatchAddTest : public testing::ServerSuite {
 protected:
  static void SetUpTestSuite() {
    SetUpServerSuite("oxbow-batch-add-test");
    // Textures unlike each other: different pictures, or far-apart crops of one.
    const std::vector<cv::Mat> pictures = {testing::Texture(400, 300, "graf1.png"),
                                           testing::Texture(400, 300, "box_in_scene.png"),
                                           testing::Texture(400, 300, "leuvenA.jpg"),
                                           testing::Texture(400, 300, "building.jpg")};
    for (const auto& picture : pictures) {
      std::vector<uchar> png;
      ASSERT_TRUE(cv::imencode(".png", picture, png));
      images_.emplace_back(png.begin(), png.end());
    }
  }

  static httplib::Result PostBatch(const ServerProcess& server, const std::vector<Upload>& uploads,
                                   const httplib::Headers& headers = {}) {
    auto client = server.Client();
    return client.Post("/v1/images/batch", headers, BatchBody(uploads));
  }

  static int Total(const ServerProcess& server) {
    auto client = server.Client();
    const json list = Parse(client.Get("/v1/images?limit=1000"));
    return list.is_object() ? list["total"].get<int>() : -1;
  }

  static inline std::vector<std::string> images_;
};

TEST_F(BatchAddTest, SeveralImagesAreAddedInOneRequestAndFound) {
  auto server = StartServer({});
  const std::vector<Upload> uploads = {{"one", images_[0], R"({"n": 1})"},
                                       {"two", images_[1], ""},
                                       {"three", images_[2], R"(["x"])"},
                                       {"four", images_[3], ""}};
  auto res = PostBatch(*server, uploads);
  ASSERT_TRUE(res);
  ASSERT_EQ(res->status, 200) << res->body;
  const json body = Parse(res);
  EXPECT_EQ(body["added"], 4);
  EXPECT_EQ(body["failed"], 0);
  ASSERT_EQ(body["results"].size(), 4u);
  for (size_t i = 0; i < uploads.size(); ++i) {
    const json& result = body["results"][i];
    EXPECT_EQ(result["id"], uploads[i].id);  // request order
    EXPECT_EQ(result["status"], 201);
    EXPECT_EQ(result["image"]["id"], uploads[i].id);
  }
  EXPECT_EQ(body["results"][0]["image"]["metadata"], json::parse(R"({"n": 1})"));
  EXPECT_FALSE(body["results"][1]["image"].contains("metadata") &&
               !body["results"][1]["image"]["metadata"].is_null());
  EXPECT_TRUE(body["timings_ms"].contains("decode_extract"));
  EXPECT_EQ(Total(*server), 4);

  auto client = server->Client();
  for (const auto& u : uploads) {
    const json record = Parse(client.Get("/v1/images/" + u.id));
    EXPECT_EQ(record["id"], u.id);
    auto thumbnail = client.Get("/v1/images/" + u.id + "/thumbnail");
    ASSERT_TRUE(thumbnail);
    EXPECT_EQ(thumbnail->status, 200);  // stored before the batch was indexed
    httplib::MultipartFormDataItems query = {{"file", u.image, "q.png", "image/png"}};
    const json found = Parse(client.Post("/v1/search", query));
    ASSERT_TRUE(found.is_object() && !found["results"].empty()) << found.dump();
    EXPECT_EQ(found["results"][0]["id"], u.id);
  }
}

TEST_F(BatchAddTest, AFailedImageDoesNotFailTheOthers) {
  auto server = StartServer({});
  auto client = server->Client();
  ASSERT_EQ(client.Post("/v1/images?id=taken", images_[0], "image/png")->status, 201);
  const std::vector<Upload> uploads = {{"good-1", images_[1], ""},
                                       {"broken", "not an image at all", ""},
                                       {"taken", images_[2], ""},
                                       {"good-2", images_[3], R"({"k": "v"})"},
                                       {"good-1", images_[0], ""},
                                       {"x/similar", images_[0], ""},
                                       {"batch", images_[0], ""},
                                       {"bad-metadata", images_[0], "{nope"}};
  auto res = PostBatch(*server, uploads);
  ASSERT_TRUE(res);
  ASSERT_EQ(res->status, 200) << res->body;
  const json body = Parse(res);
  EXPECT_EQ(body["added"], 2);
  EXPECT_EQ(body["failed"], 6);
  const std::vector<std::pair<int, std::string>> expected = {
      {201, ""},
      {400, "invalid_image"},
      {409, "already_exists"},
      {201, ""},
      {409, "already_exists"},  // repeated earlier in the batch
      {400, "invalid_argument"},
      {400, "invalid_argument"},
      {400, "invalid_argument"}};
  ASSERT_EQ(body["results"].size(), expected.size()) << body.dump();
  for (size_t i = 0; i < expected.size(); ++i) {
    const json& result = body["results"][i];
    EXPECT_EQ(result["id"], uploads[i].id);
    EXPECT_EQ(result["status"], expected[i].first) << result.dump();
    if (expected[i].first != 201) {
      EXPECT_EQ(result["error"]["code"], expected[i].second) << result.dump();
      EXPECT_EQ(result["error"]["request_id"], res->get_header_value("X-Request-Id"));
    }
  }
  EXPECT_EQ(Total(*server), 3);  // taken, good-1, good-2
  EXPECT_EQ(client.Get("/v1/images/broken")->status, 404);
  EXPECT_EQ(client.Get("/v1/images/batch")->status, 404);
  // The image already indexed as "taken" kept its own record and thumbnail.
  EXPECT_EQ(Parse(client.Get("/v1/images/taken"))["width"], 400);
  EXPECT_EQ(client.Get("/v1/images/taken/thumbnail")->status, 200);
}

TEST_F(BatchAddTest, MalformedBatchesAreRefusedWhole) {
  auto server = StartServer({"--max-batch-images", "3"});
  auto client = server->Client();
  std::vector<Upload> four;
  four.reserve(4);
  for (int i = 0; i < 4; ++i) four.push_back({"cap-" + std::to_string(i), images_[static_cast<size_t>(i)], ""});
  auto res = PostBatch(*server, four);
  ASSERT_TRUE(res);
  EXPECT_EQ(res->status, 413) << res->body;
  EXPECT_EQ(Parse(res)["error"]["code"], "payload_too_large");
  EXPECT_NE(res->body.find("--max-batch-images"), std::string::npos) << res->body;
  EXPECT_EQ(Total(*server), 0);  // nothing stored

  four.pop_back();
  auto fits = PostBatch(*server, four);
  ASSERT_TRUE(fits);
  EXPECT_EQ(fits->status, 200) << fits->body;
  EXPECT_EQ(Total(*server), 3);

  // One id part short; a parameter the route does not take; no image; not multipart.
  auto items = BatchBody({{"m-1", images_[0], ""}, {"m-2", images_[1], ""}});
  items.erase(items.begin() + 3);
  EXPECT_EQ(client.Post("/v1/images/batch", items)->status, 400);
  EXPECT_EQ(client.Post("/v1/images/batch?replace=true", BatchBody({{"m-1", images_[0], ""}}))->status, 400);
  EXPECT_EQ(client.Post("/v1/images/batch", httplib::MultipartFormDataItems{{"id", "m-1", "", ""}})->status, 400);
  EXPECT_EQ(client.Post("/v1/images/batch", images_[0], "image/png")->status, 415);
  EXPECT_EQ(Total(*server), 3);
  // Every image refused on its own: still 200, each with its error, nothing stored.
  const json none = Parse(PostBatch(*server, {{"batch", images_[0], ""}, {"cap-0", images_[1], ""}}));
  EXPECT_EQ(none["added"], 0) << none.dump();
  EXPECT_EQ(none["failed"], 2) << none.dump();
  EXPECT_EQ(Total(*server), 3);
  // The cap is published for clients that size their batches.
  EXPECT_EQ(Parse(client.Get("/v1"))["limits"]["max_batch_images"], 3);
}

TEST_F(BatchAddTest, NeedsTheApiKey) {
  auto server = StartServer({"--api-key", "sesame"});
  const std::vector<Upload> uploads = {{"k-1", images_[0], ""}};
  auto missing = PostBatch(*server, uploads);
  ASSERT_TRUE(missing);
  EXPECT_EQ(missing->status, 401);
  auto wrong = PostBatch(*server, uploads, {{"Authorization", "Bearer nope"}});
  ASSERT_TRUE(wrong);
  EXPECT_EQ(wrong->status, 403);
  EXPECT_EQ(Total(*server), 0);
  auto right = PostBatch(*server, uploads, {{"X-API-Key", "sesame"}});
  ASSERT_TRUE(right);
  EXPECT_EQ(right->status, 200) << right->body;
  EXPECT_EQ(Total(*server), 1);
}

TEST_F(BatchAddTest, AcknowledgedImagesSurviveAKill) {
  const std::string index_dir = dir_->path() + "/durable";
  const std::vector<std::string> args = {"serve", "--index", index_dir, "--vocab", vocab_, "--port", "0"};
  std::vector<std::string> acknowledged;
  {
    ServerProcess server(args, dir_->path() + "/durable-1.log");
    ASSERT_TRUE(server.port() > 0 && server.WaitReady()) << server.Log();
    for (int round = 0; round < 3; ++round) {
      std::vector<Upload> uploads;
      for (size_t i = 0; i < images_.size(); ++i) {
        uploads.push_back({"r" + std::to_string(round) + "-" + std::to_string(i), images_[i], ""});
      }
      auto res = PostBatch(server, uploads);
      ASSERT_TRUE(res);
      ASSERT_EQ(res->status, 200) << res->body;
      const json body = Parse(res);
      for (const auto& result : body["results"]) {
        if (result["status"] == 201) acknowledged.push_back(result["id"]);
      }
    }
    EXPECT_EQ(server.Stop(SIGKILL), 128 + SIGKILL);  // right after the last 200
  }
  ASSERT_EQ(acknowledged.size(), 3 * images_.size());
  ServerProcess again({"serve", "--index", index_dir, "--port", "0"}, dir_->path() + "/durable-2.log");
  ASSERT_TRUE(again.port() > 0 && again.WaitReady()) << again.Log();
  auto client = again.Client();
  for (const auto& id : acknowledged) {
    auto res = client.Get("/v1/images/" + id);
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 200) << id;
    auto thumbnail = client.Get("/v1/images/" + id + "/thumbnail");
    ASSERT_TRUE(thumbnail);
    EXPECT_EQ(thumbnail->status, 200) << id;
  }
  EXPECT_EQ(Total(again), static_cast<int>(acknowledged.size()));
}

}  // namespace
}  // namespace oxbow
