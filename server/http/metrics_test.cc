// The Prometheus text of the request metrics (counters, cumulative histograms, gauges, label escaping).
#include <gtest/gtest.h>

#include <string>

#include "server/http/metrics.h"

namespace oxbow::server {
namespace {

TEST(Metrics, RendersCountersAndCumulativeHistograms) {
  Metrics metrics;
  metrics.Observe("/v1/search", "POST", 200, 0.004);
  metrics.Observe("/v1/search", "POST", 200, 0.2);
  metrics.Observe("/v1/search", "POST", 400, 0.0005);
  metrics.Observe("/v1/images/{id}", "GET", 404, 100.0);  // beyond the last bucket: only +Inf
  EXPECT_EQ(metrics.Count("/v1/search", "POST", 200), 2u);
  EXPECT_EQ(metrics.Count("/v1/search", "POST", 500), 0u);
  const std::string text = metrics.Render({{"oxbow_index_images", "Live images.", 3, ""}});
  EXPECT_NE(text.find("# TYPE oxbow_http_requests_total counter"), std::string::npos);
  EXPECT_NE(text.find("oxbow_http_requests_total{route=\"/v1/search\",method=\"POST\",status=\"200\"} 2"), std::string::npos);
  // 0.004 s falls in le=0.005; 0.2 s in le=0.25 (cumulative: 1 then 2).
  EXPECT_NE(text.find("route=\"/v1/search\",method=\"POST\",status=\"200\",le=\"0.0025\"} 0"), std::string::npos);
  EXPECT_NE(text.find("route=\"/v1/search\",method=\"POST\",status=\"200\",le=\"0.005\"} 1"), std::string::npos);
  EXPECT_NE(text.find("route=\"/v1/search\",method=\"POST\",status=\"200\",le=\"0.25\"} 2"), std::string::npos);
  EXPECT_NE(text.find("route=\"/v1/images/{id}\",method=\"GET\",status=\"404\",le=\"30\"} 0"), std::string::npos);
  EXPECT_NE(text.find("route=\"/v1/images/{id}\",method=\"GET\",status=\"404\",le=\"+Inf\"} 1"), std::string::npos);
  EXPECT_NE(text.find("# TYPE oxbow_index_images gauge\noxbow_index_images 3\n"), std::string::npos);
  EXPECT_EQ(EscapeLabelValue("a\"b\\c\n"), "a\\\"b\\\\c\\n");
}

// Requests of a collection carry its label (counted with the others by Count); gauges of one name with
// labels share one HELP/TYPE header.
TEST(Metrics, CollectionLabels) {
  Metrics metrics;
  metrics.Observe("/v1/collections/{name}/search", "POST", 200, 0.01, "paris");
  metrics.Observe("/v1/collections/{name}/search", "POST", 200, 0.01, "tokyo");
  EXPECT_EQ(metrics.Count("/v1/collections/{name}/search", "POST", 200), 2u);
  const std::string text = metrics.Render({{"oxbow_index_images", "Live images.", 3, R"(collection="paris")"},
                                           {"oxbow_index_images", "Live images.", 5, R"(collection="tokyo")"}});
  EXPECT_NE(text.find(R"(oxbow_http_requests_total{route="/v1/collections/{name}/search",method="POST",status="200",collection="paris"} 1)"),
            std::string::npos) << text;
  EXPECT_NE(text.find("# TYPE oxbow_index_images gauge\noxbow_index_images{collection=\"paris\"} 3\n"
                      "oxbow_index_images{collection=\"tokyo\"} 5\n"),
            std::string::npos) << text;
}

}  // namespace
}  // namespace oxbow::server
