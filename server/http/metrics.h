// Request metrics in the Prometheus text exposition format (version 0.0.4), served by GET /metrics:
//
//   oxbow_http_requests_total{route,method,status,collection}              counter
//   oxbow_http_request_duration_seconds{route,method,status,collection}    histogram (le buckets 1 ms .. 30 s)
//   + gauges supplied at render time (index size, memory, in-flight work; per collection)
//
// `route` is the route pattern ("/v1/images/{id}"), never the raw path, so label cardinality stays
// bounded whatever ids clients send. `collection` is the collection a request addressed ("default" for
// the routes without a collection prefix); requests outside a collection (status routes, /v1/match,
// unknown collections) have no collection label (Prometheus's reading of an empty value). Thread-safe: Observe and Render take a mutex held only to update or
// copy a few counters (no I/O under it).
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <mutex>
#include <string>
#include <tuple>
#include <vector>

namespace oxbow::server {

struct Gauge {
  std::string name;   // metric name, e.g. "oxbow_index_images"
  std::string help;   // one line
  double value = 0;
  std::string labels; // label pairs, escaped: collection="paris" (empty: none); series of one name are consecutive
};

class Metrics {
 public:
  // Upper bounds of the latency buckets, seconds (the +Inf bucket is implicit).
  static constexpr std::array<double, 13> kBucketsSeconds = {0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1,
                                                            0.25,  0.5,    1.0,   2.5,  5.0,   30.0};

  // Records one finished request (`collection` "" outside a collection). O(log series) under the mutex.
  void Observe(const std::string& route, const std::string& method, int status, double seconds,
               const std::string& collection = "");
  // The exposition text: the two request families, then `gauges` (TYPE gauge).
  std::string Render(const std::vector<Gauge>& gauges) const;
  // Requests observed so far with this route, method and status, all collections (for tests and logs).
  uint64_t Count(const std::string& route, const std::string& method, int status) const;

 private:
  struct Series {
    std::array<uint64_t, kBucketsSeconds.size()> buckets{};  // non-cumulative counts per bucket
    uint64_t count = 0;
    double sum_seconds = 0;
  };
  using Key = std::tuple<std::string, std::string, int, std::string>;  // route, method, status, collection
  mutable std::mutex mutex_;                               // guards series_
  std::map<Key, Series> series_;
};

// Escapes a label value for the exposition format (backslash, double quote, newline).
std::string EscapeLabelValue(const std::string& value);

}  // namespace oxbow::server
