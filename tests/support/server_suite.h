// A gtest fixture for suites that start real `oxbow serve` processes: one temporary folder, one random
// vocabulary (the test extractor's settings) and one 400 x 300 texture PNG per suite; every Start() gets a
// fresh index folder and its own log file.
#pragma once

#include <gtest/gtest.h>

#include <memory>
#include <string>
#include <vector>

#include <opencv2/imgcodecs.hpp>

#include "tests/support/e2e.h"
#include "tests/support/samples.h"
#include "tests/support/temp_dir.h"

namespace oxbow::testing {

class ServerSuite : public ::testing::Test {
 protected:
  // Call from the suite's SetUpTestSuite; `name` prefixes the temporary folder.
  static void SetUpServerSuite(const std::string& name) {
    dir_ = new oxbow::testing::TempDir(name);
    vocab_ = dir_->path() + "/vocab.oxvoc";
    ASSERT_TRUE(RandomVocabulary(testing::TestSiftOptions().Describe())->Write(vocab_));
    std::vector<uchar> png;
    ASSERT_TRUE(cv::imencode(".png", Texture(400, 300), png));
    image_.assign(png.begin(), png.end());
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  // `oxbow serve` on a new index over the suite's vocabulary, on a free port, with `extra` flags; ready.
  static std::unique_ptr<ServerProcess> StartServer(const std::vector<std::string>& extra) {
    const std::string n = std::to_string(counter_++);
    std::vector<std::string> args = {"serve", "--index", dir_->path() + "/index-" + n, "--vocab", vocab_, "--port", "0"};
    args.insert(args.end(), extra.begin(), extra.end());
    auto server = std::make_unique<ServerProcess>(args, dir_->path() + "/server-" + n + ".log");
    EXPECT_TRUE(server->port() > 0 && server->WaitReady()) << server->Log();
    return server;
  }

  static inline oxbow::testing::TempDir* dir_ = nullptr;
  static inline std::string vocab_;
  static inline std::string image_;  // the texture, PNG-encoded
  static inline int counter_ = 0;
};

}  // namespace oxbow::testing
