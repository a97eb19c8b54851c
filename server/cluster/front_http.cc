// HTTP routes of a cluster front (front_http.h).
#include "server/cluster/front_http.h"

#include <chrono>
#include <cstdio>
#include <sstream>

#include "api/errors.h"
#include "api/json.h"
#include "api/params.h"
#include "api/service.h"
#include "sift/sift.h"
// After the project headers: <httplib.h> defines a `_res` macro that breaks Eigen.
#include <httplib.h>

namespace oxbow::cluster {
namespace {

void SendJson(httplib::Response& res, int status, const nlohmann::json& body) {
  res.status = status;
  res.set_content(body.dump(), "application/json");
}

void SendError(httplib::Response& res, const api::HttpError& error) {
  SendJson(res, error.status, api::ErrorBody(error, ""));
}

}  // namespace

class FrontHttpServer::Impl {
 public:
  Impl(std::shared_ptr<const ClusterFront> f, const sift::SiftExtractor& e, const FrontHttpOptions& o)
      : front(std::move(f)), extractor(e), options(o) {}

  void Search(const httplib::Request& req, httplib::Response& res) const {
    const auto start = std::chrono::steady_clock::now();
    api::Params params(req.params.begin(), req.params.end());
    std::string body = req.body;
    for (const auto& [name, part] : req.files) {
      if (name == "file" || name == "image")
        body = part.content;
      else
        params.emplace(name, part.content);
    }
    // The front's own parameter (Elasticsearch's allow_partial_search_results): on by default.
    bool allow_partial = true;
    if (const auto it = params.find("allow_partial"); it != params.end()) {
      if (it->second != "true" && it->second != "false")
        return SendError(res, api::ToHttpError({ErrorCode::kInvalidArgument, "allow_partial must be true or false"}));
      allow_partial = it->second == "true";
      params.erase("allow_partial");
    }
    auto query = api::ParseQueryParams(params, options.default_query);
    if (!query) return SendError(res, api::ToHttpError(query.error()));
    if (body.empty()) return SendError(res, api::ToHttpError({ErrorCode::kInvalidArgument, "no image in the request"}));
    api::SearchResponse response;
    response.options = *query;
    const auto* bytes = reinterpret_cast<const uint8_t*>(body.data());
    auto features = extractor.ExtractFromBytes({bytes, body.size()}, options.decode);
    if (!features) return SendError(res, api::ToHttpError(features.error()));
    response.decode_extract_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    response.query_width = features->image_width;
    response.query_height = features->image_height;
    response.extracted_features = static_cast<uint32_t>(features->size());
    ClusterFront::Coverage coverage;
    auto found = front->Query(*features, *query, allow_partial, &coverage);
    if (!found) return SendError(res, api::ToHttpError(found.error()));
    response.index = std::move(*found);
    response.total_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    nlohmann::json answer = api::SearchResponseToJson(response);
    answer["partial"] = !coverage.failed.empty();
    answer["shards"] = {{"total", coverage.total}, {"ok", coverage.ok}, {"failed", coverage.failed}};
    SendJson(res, 200, answer);
  }

  void Metrics(httplib::Response& res) const {
    std::ostringstream out;
    out << "# HELP oxbow_shard_calls_total Calls from this front to a shard replica.\n"
           "# TYPE oxbow_shard_calls_total counter\n";
    const auto metrics = front->Metrics();
    const auto labels = [](const ReplicaMetrics& m) {
      return "{partition=\"" + std::to_string(m.partition) + "\",replica=\"" + m.address + "\"}";
    };
    for (const auto& m : metrics) out << "oxbow_shard_calls_total" << labels(m) << " " << m.calls << "\n";
    out << "# HELP oxbow_shard_errors_total Calls to a shard replica that failed (unreachable, deadline, error).\n"
           "# TYPE oxbow_shard_errors_total counter\n";
    for (const auto& m : metrics) out << "oxbow_shard_errors_total" << labels(m) << " " << m.errors << "\n";
    out << "# HELP oxbow_shard_call_seconds_total Time spent in calls to a shard replica.\n"
           "# TYPE oxbow_shard_call_seconds_total counter\n";
    for (const auto& m : metrics) out << "oxbow_shard_call_seconds_total" << labels(m) << " " << m.total_ms / 1000 << "\n";
    res.set_content(out.str(), "text/plain; version=0.0.4");
  }

  std::shared_ptr<const ClusterFront> front;
  sift::SiftExtractor extractor;
  FrontHttpOptions options;
  httplib::Server http;
  int port = 0;
};

Result<std::unique_ptr<FrontHttpServer>> FrontHttpServer::Create(std::shared_ptr<const ClusterFront> front,
                                                                  const FrontHttpOptions& options) {
  // As api::Service does for an index made from a vocabulary without recorded settings.
  std::string settings = front->vocabulary().extractor_settings();
  if (settings.empty()) {
    sift::SiftOptions defaults;
    defaults.descriptor = front->vocabulary().descriptor_kind();
    settings = defaults.Describe();
  }
  auto sift_options = sift::SiftOptions::FromDescription(settings);
  if (!sift_options) return std::unexpected(sift_options.error());
  sift_options->num_threads = options.threads_per_request;
  auto extractor = sift::SiftExtractor::Create(*sift_options);
  if (!extractor) return std::unexpected(extractor.error());
  auto impl = std::make_unique<Impl>(std::move(front), *extractor, options);
  Impl* i = impl.get();
  i->http.new_task_queue = [threads = options.threads] { return new httplib::ThreadPool(static_cast<size_t>(threads)); };
  i->http.set_payload_max_length(options.max_body_bytes);
  i->http.Get("/healthz", [](const httplib::Request&, httplib::Response& res) { SendJson(res, 200, {{"status", "ok"}}); });
  i->http.Get("/readyz", [](const httplib::Request&, httplib::Response& res) { SendJson(res, 200, {{"status", "ready"}}); });
  i->http.Get("/metrics", [i](const httplib::Request&, httplib::Response& res) { i->Metrics(res); });
  i->http.Post("/v1/search", [i](const httplib::Request& req, httplib::Response& res) { i->Search(req, res); });
  const auto not_yet = [](const httplib::Request& req, httplib::Response& res) {
    SendError(res, {501, "not_implemented", req.method + " " + req.path + " is not served by a cluster front yet"});
  };
  i->http.Get("/v1/.*", not_yet);
  i->http.Post("/v1/.*", not_yet);
  i->http.Delete("/v1/.*", not_yet);
  return std::unique_ptr<FrontHttpServer>(new FrontHttpServer(std::move(impl)));
}

FrontHttpServer::FrontHttpServer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
FrontHttpServer::~FrontHttpServer() = default;

Result<int> FrontHttpServer::Bind() {
  const int port = impl_->options.port == 0 ? impl_->http.bind_to_any_port(impl_->options.host)
                                            : (impl_->http.bind_to_port(impl_->options.host, impl_->options.port)
                                                   ? impl_->options.port
                                                   : -1);
  if (port <= 0)
    return Fail(ErrorCode::kIoError, "cannot listen on " + impl_->options.host + ":" + std::to_string(impl_->options.port));
  impl_->port = port;
  return port;
}

void FrontHttpServer::Run() { impl_->http.listen_after_bind(); }

void FrontHttpServer::Shutdown() { impl_->http.stop(); }

}  // namespace oxbow::cluster
