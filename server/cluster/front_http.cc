// HTTP routes of a cluster front (front_http.h).
#include "server/cluster/front_http.h"

#include <chrono>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "api/json.h"
#include "api/params.h"
#include "server/http/errors.h"
#include "sift/base/log.h"
#include "sift/sift.h"
// After the project headers: <httplib.h> defines a `_res` macro that breaks Eigen.
#include <httplib.h>

namespace oxbow::cluster {
namespace {

using server::SendJsonAnswer;

void SendError(httplib::Response& res, const Error& error) { server::SendJsonError(res, server::ToHttpError(error)); }

std::span<const uint8_t> Bytes(std::string_view text) {
  return {reinterpret_cast<const uint8_t*>(text.data()), text.size()};
}

// The front's own parameter allow_partial (Elasticsearch's allow_partial_search_results): on by
// default; taken out of `params`.
Result<bool> TakeAllowPartial(api::Params& params) {
  const auto it = params.find("allow_partial");
  if (it == params.end()) return true;
  if (params.count("allow_partial") > 1) return Fail(ErrorCode::kInvalidArgument, "allow_partial given twice");
  if (it->second != "true" && it->second != "false")
    return Fail(ErrorCode::kInvalidArgument, "allow_partial must be true or false");
  const bool allow = it->second == "true";
  params.erase("allow_partial");
  return allow;
}

void SendSearch(httplib::Response& res, const api::SearchResponse& response, const ClusterFront::Coverage& coverage) {
  const auto& t = response.index.timings;
  server::RecordStages(res, {{"decode_extract", response.decode_extract_ms}, {"quantize", t.quantize_ms},
                             {"score", t.score_ms}, {"verify", t.verify_ms}, {"qe", t.qe_ms}});
  nlohmann::json answer = api::SearchResponseToJson(response);
  answer["partial"] = !coverage.failed.empty();
  answer["shards"] = {{"total", coverage.total}, {"ok", coverage.ok}, {"failed", coverage.failed}};
  SendJsonAnswer(res, 200, answer);
}

}  // namespace

class FrontHttpServer::Impl {
 public:
  using Clock = std::chrono::steady_clock;

  Impl(std::shared_ptr<const ClusterFront> f, const sift::SiftExtractor& extractor, const FrontHttpOptions& o)
      : front(std::move(f)), options(o), extractions(extractor, o.service.Extraction()) {}

  // As the single node's route wrapper: the API key of writes; admin routes need a key to be set.
  enum class Access { kWrite, kAdmin };
  bool Refused(Access access, const httplib::Request& req, httplib::Response& res) const {
    if (access == Access::kAdmin && options.http.api_key.empty()) {
      server::SendJsonError(res, server::PermissionDenied("this route writes on the shards' file systems and is enabled "
                                                       "only with an API key (oxbow serve --api-key)"));
      return true;
    }
    if (auto refused = server::CheckApiKey(req, options.http.api_key)) {
      server::SendJsonError(res, *refused);
      return true;
    }
    return false;
  }

  void Search(const httplib::Request& req, httplib::Response& res) const {
    const auto start = Clock::now();
    api::Params params = server::CollectParams(req, {"file", "image"});
    const auto allow_partial = TakeAllowPartial(params);
    if (!allow_partial) return SendError(res, allow_partial.error());
    auto query = api::ParseQueryParams(params, options.service.default_query);
    if (!query) return SendError(res, query.error());
    std::string filename;
    auto image = server::RequestImage(req, "file", "image", &filename);
    if (!image) return SendError(res, image.error());
    api::SearchResponse response;
    response.options = *query;
    const sift::StopRequested client_gone = server::ClientGone();
    auto features = extractions.Extract(Bytes(*image), extractions.Start(client_gone), &response.decode_extract_ms);
    if (!features) return SendError(res, features.error());
    response.query_width = features->image_width;
    response.query_height = features->image_height;
    response.extracted_features = static_cast<uint32_t>(features->size());
    ClusterFront::Coverage coverage;
    auto found = front->Query(*features, *query, *allow_partial, &coverage);
    if (!found) return SendError(res, found.error());
    response.index = std::move(*found);
    response.total_ms = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
    SendSearch(res, response, coverage);
  }

  void Similar(const std::string& id, const httplib::Request& req, httplib::Response& res) const {
    api::Params params = server::CollectParams(req, {});
    const auto allow_partial = TakeAllowPartial(params);
    if (!allow_partial) return SendError(res, allow_partial.error());
    auto query = api::ParseQueryParams(params, options.service.default_query);
    if (!query) return SendError(res, query.error());
    ClusterFront::Coverage coverage;
    auto found = front->QuerySimilar(id, *query, *allow_partial, &coverage);
    if (!found) return SendError(res, found.error());
    SendSearch(res, *found, coverage);
  }

  void GetImageOrSubresource(const httplib::Request& req, httplib::Response& res) const {
    const server::ImagePath path = server::ImagePathOf(req);
    if (path.sub == "similar") return Similar(path.id, req, res);
    if (path.sub == "thumbnail") {
      auto size = server::ThumbnailSizeParam(req);
      if (!size) return SendError(res, size.error());
      auto jpeg = front->Thumbnail(path.id, *size);
      if (!jpeg) return SendError(res, jpeg.error());
      return server::SendThumbnail(req, res, *jpeg);
    }
    auto record = front->Get(path.id);
    if (!record) return SendError(res, record.error());
    SendJsonAnswer(res, 200, api::ImageRecordToJson(*record));
  }

  void List(const httplib::Request& req, httplib::Response& res) const {
    auto params = api::ParseListParams(server::CollectParams(req, {}));
    if (!params) return SendError(res, params.error());
    auto list = front->List(params->offset, params->limit);
    if (!list) return SendError(res, list.error());
    SendJsonAnswer(res, 200, api::ListResponseToJson(*list));
  }

  void Stats(httplib::Response& res) const {
    auto stats = front->Stats();
    if (!stats) return SendError(res, stats.error());
    SendJsonAnswer(res, 200, api::StatsToJson(*stats));
  }

  void Add(const httplib::Request& req, httplib::Response& res) const {
    if (Refused(Access::kWrite, req, res)) return;
    auto params = api::ParseAddParams(server::CollectParams(req, {"file", "image"}));
    if (!params) return SendError(res, params.error());
    std::string filename;
    auto image = server::RequestImage(req, "file", "image", &filename);
    if (!image) return SendError(res, image.error());
    api::AddImageRequest add;
    add.id = params->id;
    add.image = Bytes(*image);
    add.metadata_json = params->metadata_json;
    add.replace = params->replace;
    add.source_name = filename.empty() ? "http" : "http:" + filename;
    auto added = front->Add(add);
    if (!added) return SendError(res, added.error());
    server::RecordStages(res, {{"decode_extract", added->decode_extract_ms}, {"add", added->add_ms}});
    res.set_header("Location", "/v1/images/" + added->record.id);
    SendJsonAnswer(res, added->replaced ? 200 : 201, api::AddImageResponseToJson(*added));
  }

  void AddBatch(const httplib::Request& req, httplib::Response& res) const {
    if (Refused(Access::kWrite, req, res)) return;
    server::ServeImageBatch(req, res, options.http.max_batch_images,
                            [&](api::AddBatchRequest& batch) { return front->AddBatch(batch); });
  }

  void Delete(const httplib::Request& req, httplib::Response& res) const {
    if (Refused(Access::kWrite, req, res)) return;
    const std::string id = req.matches[1];
    if (auto removed = front->Delete(id); !removed) return SendError(res, removed.error());
    SendJsonAnswer(res, 200, {{"id", id}, {"deleted", true}});
  }

  void Match(const httplib::Request& req, httplib::Response& res) const {
    const sift::StopRequested client_gone = server::ClientGone();
    server::ServeMatch(req, res, [&](std::span<const uint8_t> a, std::span<const uint8_t> b,
                                     const api::PairMatchOptions& match) {
      return api::MatchImages(extractions, options.service.threads_per_request, a, b, match, client_gone);
    });
  }

  // {"out", "partitions": [{"partition", "out", "images", ...}]}: each partition's folder is on the
  // machine of the replica that made it.
  void Backup(const httplib::Request& req, httplib::Response& res) const {
    if (Refused(Access::kAdmin, req, res)) return;
    auto out = server::BackupFolderParam(req);
    if (!out) return SendError(res, out.error());
    auto done = front->Backup(*out);
    if (!done) return SendError(res, done.error());
    nlohmann::json partitions = nlohmann::json::array();
    for (const ClusterFront::PartitionBackup& p : *done) {
      nlohmann::json one = api::BackupToJson(p.out, p.result);
      one["partition"] = p.partition;
      partitions.push_back(std::move(one));
    }
    SendJsonAnswer(res, 200, {{"out", *out}, {"partitions", std::move(partitions)}});
  }

  void RefreshStatistics(const httplib::Request& req, httplib::Response& res) const {
    if (Refused(Access::kWrite, req, res)) return;
    auto refreshed = front->RefreshStatistics();
    if (!refreshed) return SendError(res, refreshed.error());
    SendJsonAnswer(res, 200, {{"images", refreshed->images}, {"partitions", refreshed->partitions},
                              {"replicas", refreshed->replicas}, {"ms", refreshed->ms}});
  }

  // Per shard replica, after the HTTP metrics.
  std::string ShardMetrics() const {
    std::ostringstream out;
    const auto metrics = front->Metrics();
    const auto labels = [](const ReplicaMetrics& m) {
      return "{partition=\"" + std::to_string(m.partition) + "\",replica=\"" + m.address + "\"}";
    };
    const auto family = [&](const char* name, const char* type, const char* help, auto value) {
      out << "# HELP " << name << " " << help << "\n# TYPE " << name << " " << type << "\n";
      for (const auto& m : metrics) out << name << labels(m) << " " << value(m) << "\n";
    };
    family("oxbow_shard_calls_total", "counter", "Calls from this front to a shard replica.",
           [](const ReplicaMetrics& m) { return static_cast<double>(m.calls); });
    family("oxbow_shard_errors_total", "counter",
           "Calls to a shard replica that failed (unreachable, deadline, internal error; not a refusal such as an unknown id).",
           [](const ReplicaMetrics& m) { return static_cast<double>(m.errors); });
    family("oxbow_shard_call_seconds_total", "counter", "Time spent in calls to a shard replica.",
           [](const ReplicaMetrics& m) { return m.total_ms / 1000; });
    family("oxbow_shard_write_sequence", "gauge", "The write sequence a shard replica last reported (-1: none yet).",
           [](const ReplicaMetrics& m) { return static_cast<double>(m.write_sequence); });
    family("oxbow_shard_behind", "gauge",
           "1 for a replica that missed writes (kept out of reads until it catches up).",
           [](const ReplicaMetrics& m) { return m.behind ? 1.0 : 0.0; });
    return out.str();
  }

  void Register(httplib::Server& server) {
    using Req = const httplib::Request&;
    using Res = httplib::Response&;
    server.Post("/v1/search", [this](Req req, Res res) { Search(req, res); });
    server.Post("/v1/match", [this](Req req, Res res) { Match(req, res); });
    server.Get("/v1/stats", [this](Req, Res res) { Stats(res); });
    server.Get("/v1/images", [this](Req req, Res res) { List(req, res); });
    server.Post("/v1/images", [this](Req req, Res res) { Add(req, res); });
    server.Post("/v1/images/batch", [this](Req req, Res res) { AddBatch(req, res); });
    server.Get(R"(/v1/images/(.+))", [this](Req req, Res res) { GetImageOrSubresource(req, res); });
    server.Delete(R"(/v1/images/(.+))", [this](Req req, Res res) { Delete(req, res); });
    server.Post("/v1/admin/backup", [this](Req req, Res res) { Backup(req, res); });
    server.Post("/v1/admin/refresh-statistics", [this](Req req, Res res) { RefreshStatistics(req, res); });
  }

  std::shared_ptr<const ClusterFront> front;
  FrontHttpOptions options;
  api::Extractions extractions;
  std::unique_ptr<server::HttpServer> http;  // last: its routes use the members above
};

Result<std::unique_ptr<FrontHttpServer>> FrontHttpServer::Create(std::shared_ptr<const ClusterFront> front,
                                                                  const FrontHttpOptions& options) {
  if (auto message = options.service.Check()) return Fail(ErrorCode::kInvalidArgument, "front options: " + *message);
  // As api::Service does for an index made from a vocabulary without recorded settings.
  std::string settings = front->vocabulary().extractor_settings();
  if (settings.empty()) {
    sift::SiftOptions defaults;
    defaults.descriptor = front->vocabulary().descriptor_kind();
    settings = defaults.Describe();
  }
  auto sift_options = sift::SiftOptions::FromDescription(settings);
  if (!sift_options) return std::unexpected(sift_options.error());
  sift_options->num_threads = options.service.threads_per_request;
  auto extractor = sift::SiftExtractor::Create(*sift_options);
  if (!extractor) return std::unexpected(extractor.error());
  auto impl = std::make_unique<Impl>(std::move(front), *extractor, options);
  Impl* i = impl.get();
  i->http = std::make_unique<server::HttpServer>(
      options.http, server::CustomRoutes{[i](httplib::Server& http) { i->Register(http); },
                                         [i] { return i->ShardMetrics(); },
                                         {{"/v1/admin/refresh-statistics", "/v1/admin/refresh-statistics", "POST"}}});
  return std::unique_ptr<FrontHttpServer>(new FrontHttpServer(std::move(impl)));
}

FrontHttpServer::FrontHttpServer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
FrontHttpServer::~FrontHttpServer() = default;

Result<int> FrontHttpServer::Bind() { return impl_->http->Bind(); }

void FrontHttpServer::Run() { impl_->http->Run(); }

void FrontHttpServer::Shutdown() {
  impl_->extractions.Stop();
  impl_->http->Shutdown();
}

}  // namespace oxbow::cluster
