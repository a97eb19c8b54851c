// Runs the Python client's tests (api/python/oxbow_client_test.py) against a real `oxbow serve --data` with
// an admin key over an empty data folder of the suite's random vocabulary, with three textured pictures to add
// and search. The Python tests never skip: without python3, or with a failing test, this test fails.
#include <gtest/gtest.h>

#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include <opencv2/imgcodecs.hpp>

#include "tests/support/server_suite.h"

namespace oxbow {
namespace {

class PythonClientTest : public testing::ServerSuite {
 protected:
  static void SetUpTestSuite() { SetUpServerSuite("oxbow-python-client-test"); }
};

TEST_F(PythonClientTest, ClientTestsPassAgainstARealServer) {
  const std::string images = dir_->path() + "/images";
  std::filesystem::create_directories(images);
  // Three different pictures: crops of one photo far enough apart to share few features.
  const std::vector<std::pair<std::string, cv::Mat>> pictures = {
      {"a.png", oxbow::testing::Texture(400, 300, "graf1.png", 0, 0)},
      {"b.png", oxbow::testing::Texture(400, 300, "box_in_scene.png", 0, 0)},
      {"c.png", oxbow::testing::Texture(320, 240, "fruits.jpg", 40, 30)}};
  for (const auto& [name, picture] : pictures) {
    std::string path = images;
    path.append("/").append(name);
    ASSERT_TRUE(cv::imwrite(path, picture));
  }

  const std::string key = "python-client-test-key";
  // A small batch cap, so that add_many's batching into several requests is exercised.
  // A data folder (collections) whose collection "default" --vocab creates; the client's collection tests
  // create theirs with the same vocabulary (OXBOW_VOCAB).
  auto server = std::make_unique<oxbow::testing::ServerProcess>(
      std::vector<std::string>{"serve", "--data", dir_->path() + "/data", "--vocab", vocab_, "--api-key", key,
                               "--max-batch-images", "2", "--port", "0"},
      dir_->path() + "/data.log");
  ASSERT_TRUE(server->port() > 0 && server->WaitReady()) << server->Log();
  const std::string command = "OXBOW_URL=http://127.0.0.1:" + std::to_string(server->port()) +
                              " OXBOW_API_KEY=" + key + " OXBOW_VOCAB='" + vocab_ + "' OXBOW_TEST_IMAGES='" + images +
                              "' PYTHONDONTWRITEBYTECODE=1 python3 " +
                              OXBOW_SOURCE_DIR "/api/python/oxbow_client_test.py -v 2>&1";
  int exit_code = -1;
  const std::string output = oxbow::testing::RunCommand(command, &exit_code);
  EXPECT_EQ(exit_code, 0) << output << "\nserver log:\n" << server->Log();
  // unittest's summary: every test ran (none skipped) and passed.
  EXPECT_NE(output.find("\nOK\n"), std::string::npos) << output;
  EXPECT_EQ(output.find("skipped"), std::string::npos) << output;
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

}  // namespace
}  // namespace oxbow
