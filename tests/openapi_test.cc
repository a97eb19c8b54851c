// The OpenAPI description (server/http/openapi.json, served at GET /v1/openapi.json) against real servers:
// tests/openapi_check.py sends requests that cover every route with success and error answers and
// validates every response against the document the server serves (python3-jsonschema, JSON Schema
// 2020-12). This test starts the servers it talks to.
#include <fstream>

#include "tests/support/server_suite.h"

namespace oxbow::testing {
namespace {

class OpenApiTest : public ServerSuite {
 protected:
  static void SetUpTestSuite() { SetUpServerSuite("openapi"); }
};

TEST_F(OpenApiTest, EveryResponseMatchesTheDescription) {
  // The open server refuses bodies over 1 MiB (413 without a 32 MiB upload); the keyed one times out
  // requests after 1 s (408) and takes 4 connections per client (503).
  auto open = StartServer({"--max-upload-mb", "1"});
  const std::string key = "openapi-test-key";
  auto keyed = StartServer({"--api-key", key, "--request-timeout-s", "1", "--max-connections-per-client", "4"});
  // The collection routes: a data folder whose collection "default" --vocab creates.
  ServerProcess data({"serve", "--data", dir_->path() + "/data", "--vocab", vocab_, "--api-key", key, "--port", "0"},
                     dir_->path() + "/data.log");
  ASSERT_TRUE(data.port() > 0 && data.WaitReady()) << data.Log();
  const std::string image = dir_->path() + "/texture.png";
  std::ofstream(image, std::ios::binary) << image_;
  const std::string other = dir_->path() + "/other.png";  // another crop: other visual words
  std::vector<uchar> png;
  ASSERT_TRUE(cv::imencode(".png", Texture(400, 300, "graf1.png", 200, 150), png));
  std::ofstream(other, std::ios::binary).write(reinterpret_cast<const char*>(png.data()), static_cast<std::streamsize>(png.size()));
  const std::string command = std::string(OXBOW_PYTHON3) + " tests/openapi_check.py --url http://127.0.0.1:" +
                              std::to_string(open->port()) + " --keyed-url http://127.0.0.1:" +
                              std::to_string(keyed->port()) + " --data-url http://127.0.0.1:" + std::to_string(data.port()) +
                              " --api-key " + key + " --image " + image + " --other-image " + other + " 2>&1";
  int exit_code = -1;
  const std::string output = RunCommand(command, &exit_code);
  if (exit_code == 77) GTEST_SKIP() << output;
  EXPECT_EQ(exit_code, 0) << output << "\nopen server log:\n" << open->Log().substr(0, 4000) << "\ndata server log:\n"
                          << data.Log().substr(0, 4000);
  std::cout << output;
}

}  // namespace
}  // namespace oxbow::testing
