// HTTP routes of a cluster front (front_http.h).
#include "server/cluster/front_http.h"

#include <chrono>
#include <cstdio>
#include <sstream>

#include "api/errors.h"
#include "api/json.h"
#include "api/params.h"
#include "api/service.h"
#include "server/http/http_server.h"
#include "sift/sift.h"
// After the project headers: <httplib.h> defines a `_res` macro that breaks Eigen.
#include <httplib.h>

namespace oxbow::cluster {
namespace {

void SendJson(httplib::Response& res, int status, const nlohmann::json& body) {
  res.status = status;
  res.set_content(body.dump(), "application/json");
}

// The id of the request this thread serves (httplib serves a request start to finish on one thread),
// set by the pre-routing handler: in the X-Request-Id header and error bodies, as a single node.
thread_local std::string t_request_id;

void SendError(httplib::Response& res, const api::HttpError& error) {
  SendJson(res, error.status, api::ErrorBody(error, t_request_id));
}

}  // namespace

class FrontHttpServer::Impl {
 public:
  Impl(std::shared_ptr<const ClusterFront> f, const sift::SiftExtractor& e, const FrontHttpOptions& o)
      : front(std::move(f)), extractor(e), options(o) {}

  // A request's parameters (query string and multipart text parts) and its image: the multipart part
  // "file" or "image", else the raw body.
  struct Parts {
    api::Params params;
    std::string_view image;
    std::string filename;
  };
  static Parts PartsOf(const httplib::Request& req) {
    Parts parts{api::Params(req.params.begin(), req.params.end()), req.body, ""};
    for (const auto& [name, part] : req.files) {
      if (name == "file" || name == "image") {
        parts.image = part.content;
        parts.filename = part.filename;
      } else {
        parts.params.emplace(name, part.content);
      }
    }
    return parts;
  }

  // The front's own parameter allow_partial (Elasticsearch's allow_partial_search_results): on by
  // default; taken out of `params`.
  static Result<bool> TakeAllowPartial(api::Params& params) {
    const auto it = params.find("allow_partial");
    if (it == params.end()) return true;
    if (it->second != "true" && it->second != "false")
      return Fail(ErrorCode::kInvalidArgument, "allow_partial must be true or false");
    const bool allow = it->second == "true";
    params.erase("allow_partial");
    return allow;
  }

  static void SendSearch(httplib::Response& res, const api::SearchResponse& response,
                         const ClusterFront::Coverage& coverage) {
    nlohmann::json answer = api::SearchResponseToJson(response);
    answer["partial"] = !coverage.failed.empty();
    answer["shards"] = {{"total", coverage.total}, {"ok", coverage.ok}, {"failed", coverage.failed}};
    SendJson(res, 200, answer);
  }

  void Search(const httplib::Request& req, httplib::Response& res) const {
    const auto start = std::chrono::steady_clock::now();
    Parts parts = PartsOf(req);
    const auto allow_partial = TakeAllowPartial(parts.params);
    if (!allow_partial) return SendError(res, api::ToHttpError(allow_partial.error()));
    auto query = api::ParseQueryParams(parts.params, options.default_query);
    if (!query) return SendError(res, api::ToHttpError(query.error()));
    if (parts.image.empty()) return SendError(res, api::ToHttpError({ErrorCode::kInvalidArgument, "no image in the request"}));
    api::SearchResponse response;
    response.options = *query;
    const auto* bytes = reinterpret_cast<const uint8_t*>(parts.image.data());
    auto features = extractor.ExtractFromBytes({bytes, parts.image.size()}, options.decode);
    if (!features) return SendError(res, api::ToHttpError(features.error()));
    response.decode_extract_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    response.query_width = features->image_width;
    response.query_height = features->image_height;
    response.extracted_features = static_cast<uint32_t>(features->size());
    ClusterFront::Coverage coverage;
    auto found = front->Query(*features, *query, *allow_partial, &coverage);
    if (!found) return SendError(res, api::ToHttpError(found.error()));
    response.index = std::move(*found);
    response.total_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    SendSearch(res, response, coverage);
  }

  void Similar(const std::string& id, const httplib::Request& req, httplib::Response& res) const {
    api::Params params(req.params.begin(), req.params.end());
    const auto allow_partial = TakeAllowPartial(params);
    if (!allow_partial) return SendError(res, api::ToHttpError(allow_partial.error()));
    auto query = api::ParseQueryParams(params, options.default_query);
    if (!query) return SendError(res, api::ToHttpError(query.error()));
    ClusterFront::Coverage coverage;
    auto found = front->QuerySimilar(id, *query, *allow_partial, &coverage);
    if (!found) return SendError(res, api::ToHttpError(found.error()));
    SendSearch(res, *found, coverage);
  }

  // GET /v1/images/{id} and {id}/similar, told apart on the request target as sent, as a single node
  // does: a slash sent encoded (%2F) belongs to the id.
  void GetImageOrSimilar(const httplib::Request& req, httplib::Response& res) const {
    constexpr std::string_view kPrefix = "/v1/images/";
    const std::string_view path(req.path);
    const std::string_view target = std::string_view(req.target).substr(0, req.target.find('?'));
    for (const std::string_view sub : {std::string_view("/similar"), std::string_view("/thumbnail")}) {
      if (!target.ends_with(sub) || path.size() <= kPrefix.size() + sub.size()) continue;
      if (sub == "/thumbnail") return NotYet(req, res);
      return Similar(std::string(path.substr(kPrefix.size(), path.size() - kPrefix.size() - sub.size())), req, res);
    }
    auto record = front->Get(std::string(path.substr(kPrefix.size())));
    if (!record) return SendError(res, api::ToHttpError(record.error()));
    SendJson(res, 200, api::ImageRecordToJson(*record));
  }

  void List(const httplib::Request& req, httplib::Response& res) const {
    auto params = api::ParseListParams(api::Params(req.params.begin(), req.params.end()));
    if (!params) return SendError(res, api::ToHttpError(params.error()));
    auto list = front->List(params->offset, params->limit);
    if (!list) return SendError(res, api::ToHttpError(list.error()));
    SendJson(res, 200, api::ListResponseToJson(*list));
  }

  void Stats(httplib::Response& res) const {
    auto stats = front->Stats();
    if (!stats) return SendError(res, api::ToHttpError(stats.error()));
    SendJson(res, 200, api::StatsToJson(*stats));
  }

  void Add(const httplib::Request& req, httplib::Response& res) const {
    if (auto refused = server::CheckApiKey(req, options.api_key)) return SendError(res, *refused);
    const Parts parts = PartsOf(req);
    auto params = api::ParseAddParams(parts.params);
    if (!params) return SendError(res, api::ToHttpError(params.error()));
    if (parts.image.empty()) return SendError(res, api::ToHttpError({ErrorCode::kInvalidImage, "no image in the request"}));
    api::AddImageRequest add;
    add.id = params->id;
    add.image = {reinterpret_cast<const uint8_t*>(parts.image.data()), parts.image.size()};
    add.metadata_json = params->metadata_json;
    add.replace = params->replace;
    add.source_name = parts.filename.empty() ? "http" : "http:" + parts.filename;
    auto added = front->Add(add);
    if (!added) return SendError(res, api::ToHttpError(added.error()));
    res.set_header("Location", "/v1/images/" + added->record.id);
    SendJson(res, added->replaced ? 200 : 201, api::AddImageResponseToJson(*added));
  }

  void Delete(const httplib::Request& req, httplib::Response& res) const {
    if (auto refused = server::CheckApiKey(req, options.api_key)) return SendError(res, *refused);
    const std::string id = req.matches[1];
    if (auto removed = front->Delete(id); !removed) return SendError(res, api::ToHttpError(removed.error()));
    SendJson(res, 200, {{"id", id}, {"deleted", true}});
  }

  void RefreshStatistics(const httplib::Request& req, httplib::Response& res) const {
    if (auto refused = server::CheckApiKey(req, options.api_key)) return SendError(res, *refused);
    auto refreshed = front->RefreshStatistics();
    if (!refreshed) return SendError(res, api::ToHttpError(refreshed.error()));
    SendJson(res, 200, {{"images", refreshed->images}, {"partitions", refreshed->partitions},
                        {"replicas", refreshed->replicas}, {"ms", refreshed->ms}});
  }

  static void NotYet(const httplib::Request& req, httplib::Response& res) {
    SendError(res, {501, "not_implemented", req.method + " " + req.path + " is not served by a cluster front yet"});
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
    out << "# HELP oxbow_shard_write_sequence The write sequence a shard replica last reported (-1: none yet).\n"
           "# TYPE oxbow_shard_write_sequence gauge\n";
    for (const auto& m : metrics) out << "oxbow_shard_write_sequence" << labels(m) << " " << m.write_sequence << "\n";
    out << "# HELP oxbow_shard_behind 1 for a replica that missed writes (kept out of reads until it catches up).\n"
           "# TYPE oxbow_shard_behind gauge\n";
    for (const auto& m : metrics) out << "oxbow_shard_behind" << labels(m) << " " << (m.behind ? 1 : 0) << "\n";
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
  i->http.set_pre_routing_handler([](const httplib::Request& req, httplib::Response& res) {
    t_request_id = server::RequestIdFor(req);
    res.set_header("X-Request-Id", t_request_id);
    server::TakeFormEncodedBodyAsImage(req);
    return httplib::Server::HandlerResponse::Unhandled;
  });
  i->http.Get("/healthz", [](const httplib::Request&, httplib::Response& res) { SendJson(res, 200, {{"status", "ok"}}); });
  i->http.Get("/readyz", [](const httplib::Request&, httplib::Response& res) { SendJson(res, 200, {{"status", "ready"}}); });
  i->http.Get("/metrics", [i](const httplib::Request&, httplib::Response& res) { i->Metrics(res); });
  i->http.Post("/v1/search", [i](const httplib::Request& req, httplib::Response& res) { i->Search(req, res); });
  i->http.Get("/v1/stats", [i](const httplib::Request&, httplib::Response& res) { i->Stats(res); });
  i->http.Get("/v1/images", [i](const httplib::Request& req, httplib::Response& res) { i->List(req, res); });
  i->http.Post("/v1/images", [i](const httplib::Request& req, httplib::Response& res) { i->Add(req, res); });
  i->http.Get(R"(/v1/images/(.+))", [i](const httplib::Request& req, httplib::Response& res) { i->GetImageOrSimilar(req, res); });
  i->http.Delete(R"(/v1/images/(.+))", [i](const httplib::Request& req, httplib::Response& res) { i->Delete(req, res); });
  i->http.Post("/v1/admin/refresh-statistics",
               [i](const httplib::Request& req, httplib::Response& res) { i->RefreshStatistics(req, res); });
  i->http.Get("/v1/.*", Impl::NotYet);
  i->http.Post("/v1/.*", Impl::NotYet);
  i->http.Delete("/v1/.*", Impl::NotYet);
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
