// Filtered search through the real `oxbow serve` and `oxbow query`: the `filter`
// parameter of POST /v1/search and GET /v1/images/{id}/similar keeps only images whose metadata
// matches, malformed filters are 400 invalid_argument naming the problem, and `oxbow query --filter`
// on the same index gives the same answer.
#include <gtest/gtest.h>

#include <algorithm>
#include <fstream>
#include <memory>
#include <set>
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

std::vector<std::string> Ids(const json& response) {
  std::vector<std::string> ids;
  for (const json& r : response["results"]) ids.push_back(r["id"].get<std::string>());
  return ids;
}

class FilteredSearchTest : public testing::ServerSuite {
 protected:
  static void SetUpTestSuite() {
    SetUpServerSuite("oxbow-filtered-search-test");
    for (const char* sample : {"graf1.png", "box_in_scene.png", "leuvenA.jpg"}) {
      std::vector<uchar> png;
      ASSERT_TRUE(cv::imencode(".png", testing::Texture(400, 300, sample), png));
      pictures_.emplace_back(png.begin(), png.end());
    }
  }

  // A server over a new index holding the graf picture twice (Paris 2004, Lyon 1999), the box picture
  // (Paris, no year) and the leuven one (no metadata); `index_dir` receives its folder.
  static std::unique_ptr<testing::ServerProcess> StartIndexedServer(std::string* index_dir) {
    *index_dir = dir_->path() + "/index-" + std::to_string(counter_);
    auto server = StartServer({});
    auto client = server->Client();
    const std::vector<std::pair<std::string, std::pair<const std::string*, std::string>>> images = {
        {"graf-paris", {&pictures_[0], R"({"city":"Paris","year":2004})"}},
        {"graf-lyon", {&pictures_[0], R"({"city":"Lyon","year":1999})"}},
        {"box-paris", {&pictures_[1], R"({"city":"Paris"})"}},
        {"leuven", {&pictures_[2], ""}}};
    for (const auto& [id, image] : images) {
      httplib::MultipartFormDataItems form = {{"file", *image.first, id + ".png", "image/png"}, {"id", id, "", ""}};
      if (!image.second.empty()) form.push_back({"metadata", image.second, "", ""});
      auto res = client.Post("/v1/images", form);
      EXPECT_TRUE(res && res->status == 201) << id << ": " << (res ? res->body : "no answer");
    }
    return server;
  }

  static httplib::Result Search(const testing::ServerProcess& server, const std::string& filter,
                                const std::string& top_k = "10") {
    auto client = server.Client();
    return client.Post("/v1/search", httplib::MultipartFormDataItems{{"file", pictures_[0], "q.png", "image/png"},
                                                                     {"filter", filter, "", ""},
                                                                     {"top_k", top_k, "", ""}});
  }

  static json Ok(const httplib::Result& res) {
    EXPECT_TRUE(res && res->status == 200) << (res ? res->body : "no answer");
    return res && res->status == 200 ? json::parse(res->body) : json::object({{"results", json::array()}});
  }

  // A 400 invalid_argument whose message names the parameter and `problem`.
  static void ExpectRefused(const httplib::Result& res, const std::string& problem) {
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 400) << res->body;
    const json body = json::parse(res->body, nullptr, false);
    ASSERT_TRUE(body.is_object()) << res->body;
    EXPECT_EQ(body["error"]["code"], "invalid_argument") << res->body;
    const std::string message = body["error"]["message"].get<std::string>();
    EXPECT_NE(message.find("parameter 'filter'"), std::string::npos) << message;
    EXPECT_NE(message.find(problem), std::string::npos) << message;
  }

  static inline std::vector<std::string> pictures_;
};

TEST_F(FilteredSearchTest, SearchAndSimilarReturnOnlyMatchingImages) {
  std::string index_dir;
  auto server = StartIndexedServer(&index_dir);

  EXPECT_EQ(Ids(Ok(Search(*server, R"({"city": "Lyon"})"))), std::vector<std::string>{"graf-lyon"});
  EXPECT_EQ(Ids(Ok(Search(*server, R"({"year": {"gte": 2000, "lt": 2010}})"))), std::vector<std::string>{"graf-paris"});
  const json paris = Ok(Search(*server, R"({"city": {"in": ["Paris", "Nice"]}})"));
  const std::vector<std::string> paris_ids = Ids(paris);
  EXPECT_EQ(std::set<std::string>(paris_ids.begin(), paris_ids.end()).count("graf-paris"), 1u);
  for (const json& r : paris["results"]) EXPECT_EQ(r["metadata"]["city"], "Paris") << r;
  EXPECT_TRUE(Ids(Ok(Search(*server, R"({"city": "Rome"})"))).empty());
  // {} is no filter: the leuven picture (no metadata) may come back.
  EXPECT_FALSE(Ids(Ok(Search(*server, "{}"))).empty());

  auto client = server->Client();
  const std::string lyon = httplib::detail::encode_query_param(R"({"city":{"in":["Lyon"]}})");
  EXPECT_EQ(Ids(Ok(client.Get("/v1/images/graf-paris/similar?filter=" + lyon))),
            std::vector<std::string>{"graf-lyon"});
  // The queried image itself is filtered like any other.
  const std::vector<std::string> others = Ids(Ok(client.Get("/v1/images/leuven/similar?filter=" + lyon)));
  EXPECT_EQ(std::count(others.begin(), others.end(), "leuven"), 0);
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

TEST_F(FilteredSearchTest, MalformedFiltersAre400NamingTheProblem) {
  std::string index_dir;
  auto server = StartIndexedServer(&index_dir);
  ExpectRefused(Search(*server, R"({"city": )"), "is not valid JSON");
  ExpectRefused(Search(*server, R"(["Paris"])"), "must be a JSON object of metadata keys, got array");
  ExpectRefused(Search(*server, R"({"city": {"like": "P%"}})"), "unknown operator 'like' for key 'city'");
  ExpectRefused(Search(*server, R"({"year": {"gt": true}})"), "operator 'gt' of key 'year' needs a number or a string");
  ExpectRefused(Search(*server, R"({"city": null})"), "key 'city' must be a string, number, boolean");
  ExpectRefused(Search(*server, R"({"a": {"in": [[[1]]]}})"), "nests deeper than 3 levels");
  ExpectRefused(Search(*server, "{\"k\": \"" + std::string(20000, 'x') + "\"}"), "must be at most 16384 bytes");
  auto client = server->Client();
  ExpectRefused(client.Get("/v1/images/graf-paris/similar?filter=" + httplib::detail::encode_query_param(R"({"city": {}})")),
                "needs at least one of");
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

TEST_F(FilteredSearchTest, QueryCommandFilters) {
  std::string index_dir;
  auto server = StartIndexedServer(&index_dir);
  ASSERT_EQ(server->Stop(), 0) << server->Log();
  const std::string query_image = dir_->path() + "/query.png";
  std::ofstream(query_image, std::ios::binary) << pictures_[0];
  const std::string query = std::string(OXBOW_BINARY) + " query --index " + index_dir + " " + query_image;
  int rc = -1;
  std::string out = testing::RunCommand(query + R"( --filter '{"city": "Lyon"}' 2>&1)", &rc);
  ASSERT_EQ(rc, 0) << out;
  EXPECT_EQ(Ids(json::parse(out.substr(out.find('{')))), std::vector<std::string>{"graf-lyon"}) << out;
  out = testing::RunCommand(query + R"( --filter '{"year": {"lt": 2000}}' --rerank 0 2>&1)", &rc);
  ASSERT_EQ(rc, 0) << out;
  EXPECT_EQ(Ids(json::parse(out.substr(out.find('{')))), std::vector<std::string>{"graf-lyon"}) << out;
  out = testing::RunCommand(query + R"( --filter '{"city": {"like": "L%"}}' 2>&1)", &rc);
  EXPECT_NE(rc, 0) << out;
  EXPECT_NE(out.find("--filter: unknown operator 'like' for key 'city'"), std::string::npos) << out;
}

}  // namespace
}  // namespace oxbow
