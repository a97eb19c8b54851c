#include "eval/runner/experiment.h"

#include <gtest/gtest.h>

#include <string>

#include "index/image_index.h"

namespace oxbow::eval {
namespace {

const std::string kDepth = std::to_string(index::QueryOptions{}.transitive_depth);

// A server eval starts itself receives every setting of the run.
TEST(SearchTarget, SendsEverySettingToItsOwnServer) {
  const ExperimentOptions a;
  EXPECT_EQ(SearchTarget(a, 100, true, true, true, 50),
            "/v1/search?top_k=50&rerank=100&qe=true&transitive_depth=" + kDepth + "&hamming=true");
  EXPECT_EQ(SearchTarget(a, 0, false, false, false, 7),
            "/v1/search?top_k=7&rerank=0&qe=false&transitive_depth=0&hamming=false");
}

// A running server receives only the settings given on eval's command line; `--transitive on` asks for
// the built-in depth, so it turns transitive verification back on in a server started with
// --transitive-depth 0.
TEST(SearchTarget, SendsARunningServerOnlyTheSettingsGiven) {
  ExperimentOptions a;
  a.server = "http://127.0.0.1:8080";
  EXPECT_EQ(SearchTarget(a, 100, true, true, true, 10), "/v1/search?top_k=10");
  a.server_settings_given = {"transitive"};
  EXPECT_EQ(SearchTarget(a, 100, true, true, true, 10), "/v1/search?top_k=10&transitive_depth=" + kDepth);
  EXPECT_EQ(SearchTarget(a, 100, true, false, true, 10), "/v1/search?top_k=10&transitive_depth=0");
  a.server_settings_given = {"rerank", "hamming"};
  EXPECT_EQ(SearchTarget(a, 300, true, true, false, 10), "/v1/search?top_k=10&rerank=300&hamming=false");
}

}  // namespace
}  // namespace oxbow::eval
