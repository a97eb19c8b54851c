#include "server/http/metrics.h"

#include <charconv>
#include <sstream>

namespace oxbow::server {

namespace {

// Shortest text that reads back to the same double (0.0025, not 0.0025000000000000001).
std::string FormatDouble(double v) {
  char buf[64];
  auto [end, ec] = std::to_chars(buf, buf + sizeof buf, v);
  return ec == std::errc() ? std::string(buf, end) : std::string("NaN");
}

}  // namespace

std::string EscapeLabelValue(const std::string& value) {
  std::string out;
  out.reserve(value.size());
  for (char c : value) {
    if (c == '\\') {
      out += "\\\\";
    } else if (c == '"') {
      out += "\\\"";
    } else if (c == '\n') {
      out += "\\n";
    } else {
      out += c;
    }
  }
  return out;
}

void Metrics::Observe(const std::string& route, const std::string& method, int status, double seconds,
                      const std::string& collection) {
  size_t bucket = 0;
  while (bucket < kBucketsSeconds.size() && seconds > kBucketsSeconds[bucket]) ++bucket;
  std::lock_guard<std::mutex> lock(mutex_);
  Series& s = series_[Key{route, method, status, collection}];
  if (bucket < kBucketsSeconds.size()) ++s.buckets[bucket];
  ++s.count;
  s.sum_seconds += seconds;
}

uint64_t Metrics::Count(const std::string& route, const std::string& method, int status) const {
  std::lock_guard<std::mutex> lock(mutex_);
  uint64_t count = 0;
  for (const auto& [key, series] : series_) {
    if (std::get<0>(key) == route && std::get<1>(key) == method && std::get<2>(key) == status) count += series.count;
  }
  return count;
}

std::string Metrics::Render(const std::vector<Gauge>& gauges) const {
  std::map<Key, Series> copy;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    copy = series_;
  }
  std::ostringstream out;
  out << "# HELP oxbow_http_requests_total HTTP requests by route pattern, method and status.\n"
         "# TYPE oxbow_http_requests_total counter\n";
  auto labels_of = [](const Key& key) {
    const auto& [route, method, status, collection] = key;
    std::string labels = "route=\"" + EscapeLabelValue(route) + "\",method=\"" + EscapeLabelValue(method) +
                         "\",status=\"" + std::to_string(status) + "\"";
    if (!collection.empty()) labels += ",collection=\"" + EscapeLabelValue(collection) + "\"";
    return labels;
  };
  for (const auto& [key, s] : copy) out << "oxbow_http_requests_total{" << labels_of(key) << "} " << s.count << "\n";
  out << "# HELP oxbow_http_request_duration_seconds Time from the request headers to the response, seconds.\n"
         "# TYPE oxbow_http_request_duration_seconds histogram\n";
  for (const auto& [key, s] : copy) {
    const std::string labels = labels_of(key);
    uint64_t cumulative = 0;
    for (size_t b = 0; b < kBucketsSeconds.size(); ++b) {
      cumulative += s.buckets[b];
      out << "oxbow_http_request_duration_seconds_bucket{" << labels << ",le=\"" << FormatDouble(kBucketsSeconds[b])
          << "\"} " << cumulative << "\n";
    }
    out << "oxbow_http_request_duration_seconds_bucket{" << labels << ",le=\"+Inf\"} " << s.count << "\n";
    out << "oxbow_http_request_duration_seconds_sum{" << labels << "} " << FormatDouble(s.sum_seconds) << "\n";
    out << "oxbow_http_request_duration_seconds_count{" << labels << "} " << s.count << "\n";
  }
  for (size_t i = 0; i < gauges.size(); ++i) {
    const Gauge& g = gauges[i];
    if (i == 0 || gauges[i - 1].name != g.name) out << "# HELP " << g.name << " " << g.help << "\n# TYPE " << g.name << " gauge\n";
    out << g.name << (g.labels.empty() ? "" : "{" + g.labels + "}") << " " << FormatDouble(g.value) << "\n";
  }
  return out.str();
}

}  // namespace oxbow::server
