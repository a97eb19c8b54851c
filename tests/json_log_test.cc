// `oxbow serve --log-format json` (server/README.md): every stderr line of the process, from start to
// stop, is one JSON object with time, level and message, and each request's line carries its id,
// method, path, route, status, latency and stage timings, also for errors, for requests refused before
// they were read, and for paths holding bytes that are not UTF-8 or are JSON's own quote and backslash.
// In the text format, bytes a client chose never end a line or start one.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <regex>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "tests/support/server_suite.h"

namespace oxbow {
namespace {

using nlohmann::json;
namespace fs = std::filesystem;

// Every line of `log` parsed as JSON: fails the test for a line that is not an object with the three
// fields every line has.
std::vector<json> ParseLines(const std::string& log) {
  std::vector<json> lines;
  std::istringstream in(log);
  std::string text;
  const std::regex time(R"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z)");
  while (std::getline(in, text)) {
    json line = json::parse(text, nullptr, false);
    EXPECT_TRUE(line.is_object()) << "not a JSON object: " << text;
    if (!line.is_object()) continue;
    EXPECT_TRUE(line["time"].is_string() && std::regex_match(line["time"].get<std::string>(), time)) << text;
    EXPECT_TRUE(line["level"] == "debug" || line["level"] == "info" || line["level"] == "warning" ||
                line["level"] == "error") << text;
    EXPECT_TRUE(line["message"].is_string()) << text;
    lines.push_back(std::move(line));
  }
  EXPECT_FALSE(lines.empty()) << log;
  return lines;
}

// The request lines of `lines`, by request id.
std::map<std::string, json> RequestLines(const std::vector<json>& lines) {
  std::map<std::string, json> by_id;
  for (const auto& line : lines) {
    if (line.contains("request_id")) by_id[line["request_id"].get<std::string>()] = line;
  }
  return by_id;
}

bool HasMessage(const std::vector<json>& lines, const std::string& level, const std::string& starts_with) {
  for (const auto& line : lines) {
    if (line["level"] == level && line["message"].get<std::string>().rfind(starts_with, 0) == 0) return true;
  }
  return false;
}

class JsonLogTest : public testing::ServerSuite {
 protected:
  static void SetUpTestSuite() { SetUpServerSuite("oxbow-json-log-test"); }
};

TEST_F(JsonLogTest, EveryLineIsJsonAndRequestLinesCarryTheirFields) {
  auto server = StartServer({"--log-format", "json"});
  ASSERT_GT(server->port(), 0);
  auto client = server->Client();
  const auto id = [](const char* value) { return httplib::Headers{{"X-Request-Id", value}}; };
  ASSERT_EQ(client.Get("/v1/stats", id("stats"))->status, 200);
  ASSERT_EQ(client.Post("/v1/images?id=pic", id("add"), image_, "image/png")->status, 201);
  ASSERT_EQ(client.Post("/v1/search?top_k=3", id("search"), image_, "image/png")->status, 200);
  ASSERT_EQ(client.Post("/v1/search?top_k=0", id("bad-param"), image_, "image/png")->status, 400);
  ASSERT_EQ(client.Get("/v1/images/unknown", id("not-found"))->status, 404);
  // A path decoding to a byte that is not UTF-8, a quote, a backslash and a newline (no route matches it).
  const int fd = oxbow::testing::ConnectTo(server->port());
  ASSERT_GE(fd, 0);
  std::string answer;
  ASSERT_TRUE(oxbow::testing::SendAll(fd, "GET /v1/%FF%22%5C%0A HTTP/1.1\r\nHost: x\r\nX-Request-Id: odd-path\r\n"
                                          "Connection: close\r\n\r\n"));
  ASSERT_TRUE(oxbow::testing::ReadUntil(fd, "\r\n\r\n", &answer));
  EXPECT_EQ(answer.rfind("HTTP/1.1 404", 0), 0u) << answer;
  close(fd);
  // Refused before httplib reads it (server/http/request_guard.cc).
  const int refused = oxbow::testing::ConnectTo(server->port());
  ASSERT_GE(refused, 0);
  answer.clear();
  ASSERT_TRUE(oxbow::testing::SendAll(refused, "POST /v1/search HTTP/1.1\r\nHost: x\r\nX-Request-Id: refused\r\n"
                                               "Content-Encoding: gzip\r\nContent-Length: 0\r\n\r\n"));
  ASSERT_TRUE(oxbow::testing::ReadUntil(refused, "\r\n\r\n", &answer));
  EXPECT_EQ(answer.rfind("HTTP/1.1 415", 0), 0u) << answer;
  close(refused);
  ASSERT_TRUE(server->WaitForLog("\"request_id\":\"refused\"")) << server->Log();
  ASSERT_EQ(server->Stop(), 0);

  const std::string log = server->Log();
  const auto lines = ParseLines(log);
  EXPECT_TRUE(HasMessage(lines, "info", "listening on http://127.0.0.1:")) << log;
  EXPECT_TRUE(HasMessage(lines, "info", "received SIGTERM")) << log;
  EXPECT_TRUE(HasMessage(lines, "info", "stopped")) << log;
  const auto requests = RequestLines(lines);

  struct Expected {
    std::string id, method, path, route;
    int status;
    std::vector<std::string> stages;
  };
  const std::vector<Expected> expected = {
      {"stats", "GET", "/v1/stats", "/v1/stats", 200, {}},
      {"add", "POST", "/v1/images", "/v1/images", 201, {"decode_extract", "add"}},
      {"search", "POST", "/v1/search", "/v1/search", 200, {"decode_extract", "quantize", "score", "verify", "qe"}},
      {"bad-param", "POST", "/v1/search", "/v1/search", 400, {}},
      {"not-found", "GET", "/v1/images/unknown", "/v1/images/{id}", 404, {}},
      {"odd-path", "GET", "/v1/\xef\xbf\xbd\"\\?", "unmatched", 404, {}},  // the server logs a newline as '?'
  };
  for (const auto& e : expected) {
    SCOPED_TRACE(e.id);
    ASSERT_TRUE(requests.contains(e.id)) << log;
    const json& line = requests.at(e.id);
    EXPECT_EQ(line["level"], "info");
    EXPECT_EQ(line["method"], e.method) << line;
    EXPECT_EQ(line["path"], e.path) << line;
    EXPECT_EQ(line["route"], e.route) << line;
    EXPECT_EQ(line["status"], e.status) << line;
    EXPECT_TRUE(line["latency_ms"].is_number() && line["latency_ms"].get<double>() > 0) << line;
    ASSERT_TRUE(line["stages_ms"].is_object()) << line;
    EXPECT_EQ(line["stages_ms"].size(), e.stages.size()) << line;
    for (const auto& stage : e.stages) EXPECT_TRUE(line["stages_ms"][stage].is_number()) << stage << " in " << line;
    EXPECT_FALSE(line.contains("refused")) << line;
    // The message is the text format's line.
    EXPECT_EQ(line["message"].get<std::string>().rfind("http " + e.id + " " + e.method + " ", 0), 0u) << line;
  }
  ASSERT_TRUE(requests.contains("refused")) << log;
  const json& refused_line = requests.at("refused");
  EXPECT_EQ(refused_line["status"], 415) << refused_line;
  EXPECT_EQ(refused_line["method"], "POST") << refused_line;
  EXPECT_EQ(refused_line["route"], "/v1/search") << refused_line;
  EXPECT_EQ(refused_line["latency_ms"], 0) << refused_line;
  EXPECT_EQ(refused_line["stages_ms"], json::object()) << refused_line;
  EXPECT_NE(refused_line["refused"].get<std::string>().find("Content-Encoding 'gzip'"), std::string::npos) << refused_line;
}

TEST_F(JsonLogTest, AFailedStartEndsWithAJsonErrorLine) {
  // An index whose vocabulary copy is damaged: the server binds, fails to load, exits non-zero.
  std::string index;
  {
    auto first = StartServer({});
    index = dir_->path() + "/index-" + std::to_string(counter_ - 1);
    ASSERT_EQ(first->Stop(), 0);
  }
  {
    std::fstream vocabulary(index + "/vocabulary.oxvoc", std::ios::in | std::ios::out | std::ios::binary);
    vocabulary.seekp(100);
    vocabulary.put('\x5a');
  }
  const std::string log_path = dir_->path() + "/failed-start.log";
  oxbow::testing::ServerProcess server({"serve", "--index", index, "--port", "0", "--log-format", "json"}, log_path);
  EXPECT_GT(server.port(), 0) << server.Log();
  EXPECT_NE(server.Wait(), 0);
  const std::string log = server.Log();
  const auto lines = ParseLines(log);
  EXPECT_TRUE(HasMessage(lines, "error", "cannot open the index")) << log;
  // Nobody sent a signal: the log does not say one was received.
  EXPECT_EQ(log.find("received SIG"), std::string::npos) << log;
  ASSERT_FALSE(lines.empty());
  EXPECT_EQ(lines.back()["level"], "error") << log;
  EXPECT_EQ(lines.back()["message"].get<std::string>().rfind("oxbow: error: ", 0), 0u) << log;
}

TEST_F(JsonLogTest, WhatTakesNoTimeToRefuseIsRefusedBeforeListening) {
  // No index in the folder and no --vocab to create one; a folder that holds other files.
  fs::create_directories(dir_->path() + "/other-files");
  std::ofstream(dir_->path() + "/other-files/notes.txt") << "not an index";
  for (const auto& args : std::vector<std::vector<std::string>>{
           {"--index", dir_->path() + "/no-index"},
           {"--index", dir_->path() + "/other-files", "--vocab", vocab_}}) {
    std::vector<std::string> all = {"serve", "--port", "0", "--log-format", "json"};
    all.insert(all.end(), args.begin(), args.end());
    oxbow::testing::ServerProcess server(all, dir_->path() + "/refused-" + std::to_string(args.size()) + ".log");
    EXPECT_EQ(server.port(), 0) << "it listened:\n" << server.Log();
    EXPECT_NE(server.Wait(), 0);
    const std::string log = server.Log();
    const auto lines = ParseLines(log);
    ASSERT_FALSE(lines.empty());
    EXPECT_EQ(lines.back()["level"], "error") << log;
    EXPECT_EQ(lines.back()["message"].get<std::string>().rfind("oxbow: error: ", 0), 0u) << log;
  }
  EXPECT_FALSE(fs::exists(dir_->path() + "/no-index"));
}

TEST_F(JsonLogTest, TextStaysTheDefault) {
  auto server = StartServer({});
  ASSERT_EQ(server->Client().Get("/v1/stats", httplib::Headers{{"X-Request-Id", "plain"}})->status, 200);
  ASSERT_TRUE(server->WaitForLog("http plain GET /v1/stats route=/v1/stats status=200 ms=")) << server->Log();
  EXPECT_EQ(server->Log().find('{'), std::string::npos) << server->Log();
}

TEST_F(JsonLogTest, ClientBytesCannotForgeATextLine) {
  auto server = StartServer({"--api-key", "k"});
  auto client = server->Client();
  const httplib::Headers key = {{"X-API-Key", "k"}};
  const std::string forged = "2026-01-01T00:00:00Z I forged";
  // A backup folder with a newline is refused (a path the client chose, index/storage/backup.h) and, whatever
  // is logged about it, no line of the log starts with what followed the newline.
  const std::string out = dir_->path() + "/forged-backup\n" + forged;
  const auto backup = client.Post("/v1/admin/backup", key, json{{"out", out}}.dump(), "application/json");
  ASSERT_TRUE(backup);
  EXPECT_EQ(backup->status, 400) << backup->body;
  // A path decoding to CR LF and the forged line.
  ASSERT_EQ(client.Get("/v1/images/x%0D%0A2026-01-01T00:00:00Z%20I%20forged")->status, 404);
  ASSERT_EQ(client.Get("/v1/stats", httplib::Headers{{"X-Request-Id", "last"}})->status, 200);
  ASSERT_TRUE(server->WaitForLog("http last GET /v1/stats")) << server->Log();
  std::istringstream lines(server->Log());
  std::string line;
  while (std::getline(lines, line)) {
    EXPECT_NE(line.rfind(forged, 0), 0u) << "a forged line:\n" << server->Log();
    EXPECT_EQ(line.find('\r'), std::string::npos) << line;
  }
}

}  // namespace
}  // namespace oxbow
