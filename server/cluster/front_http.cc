// HTTP routes of a cluster front (front_http.h).
#include "server/cluster/front_http.h"

#include <chrono>
#include <functional>
#include <map>
#include <optional>
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

// The extractor of a collection's queries: as its vocabulary was made (its extractor settings), as
// api::Service does for an index made from a vocabulary without recorded settings.
Result<sift::SiftExtractor> ExtractorOf(const vocab::Vocabulary& vocabulary, int threads) {
  std::string settings = vocabulary.extractor_settings();
  if (settings.empty()) {
    sift::SiftOptions defaults;
    defaults.descriptor = vocabulary.descriptor_kind();
    settings = defaults.Describe();
  }
  auto sift_options = sift::SiftOptions::FromDescription(settings);
  if (!sift_options) return std::unexpected(sift_options.error());
  sift_options->num_threads = threads;
  return sift::SiftExtractor::Create(*sift_options);
}

class FrontHttpServer::Impl {
 public:
  using Clock = std::chrono::steady_clock;
  using Access = server::CollectionAccess;

  // One collection of the cluster: its front, settings and extraction slots.
  struct Served {
    std::shared_ptr<const ClusterFront> front;
    api::CollectionSettings settings;
    std::unique_ptr<api::Extractions> extractions;
  };
  using Req = const httplib::Request&;
  using Res = httplib::Response&;
  using Body = std::function<void(const Served&, Req, Res)>;

  explicit Impl(const FrontHttpOptions& o) : options(o) {}

  // A route of one collection (the one its path names): the key check (server::AuthorizeCollection, the
  // single node's rules), 404 for an unknown collection, then `body`.
  httplib::Server::Handler Route(Access access, Body body) const {
    return [this, access, body = std::move(body)](Req req, Res res) {
      const std::string name = server::CollectionOfPath(req.path);
      const auto it = collections.find(name);
      const std::optional<bool> is_public = it == collections.end() ? std::nullopt : std::optional(it->second.settings.is_public);
      if (auto refused = server::AuthorizeCollection(req, options.http.api_key, keys.get(), name, is_public, access))
        return server::SendJsonError(res, *refused);
      if (it == collections.end()) {
        return SendError(res, {ErrorCode::kNotFound, "no collection named '" + name + "' in this cluster" +
                                                         (name == api::kDefaultCollection
                                                              ? " (the routes without /v1/collections/{name} act on it)"
                                                              : "")});
      }
      server::NoteCollection(name);
      body(it->second, req, res);
    };
  }

  // Why adding `adding` images would pass the collection's limits (images and index bytes over every
  // partition), or nullopt. Asked of the partitions before the add: concurrent adds may each pass it.
  static std::optional<server::HttpError> CheckRoom(const Served& c, uint64_t adding) {
    const api::CollectionSettings& s = c.settings;
    if (!s.max_images && !s.max_bytes) return std::nullopt;
    auto stats = c.front->Stats();
    if (!stats) return server::ToHttpError(stats.error());
    const index::IndexStats& index = stats->index;
    const std::string name = c.front->collection();
    if (s.max_images && index.num_images + adding > *s.max_images) {
      return server::CollectionFull("collection '" + name + "' holds " + std::to_string(index.num_images) +
                                    " images; its limit is " + std::to_string(*s.max_images) +
                                    " (delete images, or raise max_images in cluster.json)");
    }
    const uint64_t bytes = index.postings_bytes + index.geometry_bytes + index.other_bytes;
    if (s.max_bytes && bytes >= *s.max_bytes) {
      return server::CollectionFull("collection '" + name + "' holds " + std::to_string(bytes) +
                                    " index bytes over its partitions; its limit is " + std::to_string(*s.max_bytes) +
                                    " (delete images, or raise max_bytes in cluster.json)");
    }
    return std::nullopt;
  }

  void Search(const Served& c, Req req, Res res) const {
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
    auto features =
        c.extractions->Extract(server::Bytes(*image), c.extractions->Start(client_gone), &response.decode_extract_ms);
    if (!features) return SendError(res, features.error());
    response.query_width = features->image_width;
    response.query_height = features->image_height;
    response.extracted_features = static_cast<uint32_t>(features->size());
    ClusterFront::Coverage coverage;
    auto found = c.front->Query(*features, *query, *allow_partial, &coverage);
    if (!found) return SendError(res, found.error());
    response.index = std::move(*found);
    response.total_ms = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
    SendSearch(res, response, coverage);
  }

  void Similar(const Served& c, const std::string& id, Req req, Res res) const {
    api::Params params = server::CollectParams(req, {});
    const auto allow_partial = TakeAllowPartial(params);
    if (!allow_partial) return SendError(res, allow_partial.error());
    auto query = api::ParseQueryParams(params, options.service.default_query);
    if (!query) return SendError(res, query.error());
    ClusterFront::Coverage coverage;
    auto found = c.front->QuerySimilar(id, *query, *allow_partial, &coverage);
    if (!found) return SendError(res, found.error());
    SendSearch(res, *found, coverage);
  }

  void GetImageOrSubresource(const Served& c, Req req, Res res) const {
    const server::ImagePath path = server::ImagePathOf(req);
    if (path.sub == "similar") return Similar(c, path.id, req, res);
    if (path.sub == "thumbnail") {
      auto size = server::ThumbnailSizeParam(req);
      if (!size) return SendError(res, size.error());
      auto jpeg = c.front->Thumbnail(path.id, *size);
      if (!jpeg) return SendError(res, jpeg.error());
      return server::SendThumbnail(req, res, *jpeg);
    }
    auto record = c.front->Get(path.id);
    if (!record) return SendError(res, record.error());
    SendJsonAnswer(res, 200, api::ImageRecordToJson(*record));
  }

  static void List(const Served& c, Req req, Res res) {
    auto params = api::ParseListParams(server::CollectParams(req, {}));
    if (!params) return SendError(res, params.error());
    auto list = c.front->List(params->offset, params->limit);
    if (!list) return SendError(res, list.error());
    SendJsonAnswer(res, 200, api::ListResponseToJson(*list));
  }

  static void Stats(const Served& c, Res res) {
    auto stats = c.front->Stats();
    if (!stats) return SendError(res, stats.error());
    SendJsonAnswer(res, 200, api::StatsToJson(*stats));
  }

  static void Add(const Served& c, Req req, Res res) {
    auto params = api::ParseAddParams(server::CollectParams(req, {"file", "image"}));
    if (!params) return SendError(res, params.error());
    std::string filename;
    auto image = server::RequestImage(req, "file", "image", &filename);
    if (!image) return SendError(res, image.error());
    if (auto full = CheckRoom(c, params->replace ? 0 : 1)) return server::SendJsonError(res, *full);
    auto added = c.front->Add(server::AddImageRequestOf(*params, *image, filename));
    if (!added) return SendError(res, added.error());
    server::RecordStages(res, {{"decode_extract", added->decode_extract_ms}, {"add", added->add_ms}});
    const std::string prefix =
        req.path.starts_with("/v1/collections/") ? "/v1/collections/" + c.front->collection() : std::string("/v1");
    res.set_header("Location", server::ImageLocation(prefix, added->record.id));
    SendJsonAnswer(res, added->replaced ? 200 : 201, api::AddImageResponseToJson(*added));
  }

  void AddBatch(const Served& c, Req req, Res res) const {
    if (auto full = CheckRoom(c, req.files.count("image"))) return server::SendJsonError(res, *full);
    server::ServeImageBatch(req, res, options.http.max_batch_images,
                            [&](api::AddBatchRequest& batch) { return c.front->AddBatch(batch); });
  }

  static void Delete(const Served& c, Req req, Res res) {
    const std::string id = req.matches[1];
    if (auto removed = c.front->Delete(id); !removed) return SendError(res, removed.error());
    SendJsonAnswer(res, 200, {{"id", id}, {"deleted", true}});
  }

  void Match(Req req, Res res) const {
    // A match needs no collection: it extracts with the default collection's settings (else the first's).
    const auto it = collections.contains(api::kDefaultCollection) ? collections.find(api::kDefaultCollection)
                                                                   : collections.begin();
    const api::Extractions& extractions = *it->second.extractions;
    const sift::StopRequested client_gone = server::ClientGone();
    server::ServeMatch(req, res, [&](std::span<const uint8_t> a, std::span<const uint8_t> b,
                                     const api::PairMatchOptions& match) {
      return api::MatchImages(extractions, options.service.threads_per_request, a, b, match, client_gone);
    });
  }

  // {"out", "partitions": [{"partition", "out", "images", ...}]}: each partition's folder is on the
  // machine of the replica that made it.
  static void Backup(const Served& c, Req req, Res res) {
    auto out = server::BackupFolderParam(req);
    if (!out) return SendError(res, out.error());
    auto done = c.front->Backup(*out);
    if (!done) return SendError(res, done.error());
    nlohmann::json partitions = nlohmann::json::array();
    for (const ClusterFront::PartitionBackup& p : *done) {
      nlohmann::json one = api::BackupToJson(p.out, p.result);
      one["partition"] = p.partition;
      partitions.push_back(std::move(one));
    }
    SendJsonAnswer(res, 200, {{"out", *out}, {"partitions", std::move(partitions)}});
  }

  static void RefreshStatistics(const Served& c, Res res) {
    auto refreshed = c.front->RefreshStatistics();
    if (!refreshed) return SendError(res, refreshed.error());
    SendJsonAnswer(res, 200, {{"images", refreshed->images}, {"partitions", refreshed->partitions},
                              {"replicas", refreshed->replicas}, {"ms", refreshed->ms}});
  }

  // GET /v1/collections/{name} and the list's entries (api::CollectionToJson): the stats are the sums
  // over the partitions; disk_bytes counts the index bytes the partitions report.
  static Result<nlohmann::json> Describe(const Served& c, bool with_stats) {
    auto stats = c.front->Stats();
    if (!stats) return std::unexpected(stats.error());
    api::CollectionInfo info;
    info.name = c.front->collection();
    info.settings = c.settings;
    info.stats = *stats;
    info.disk_bytes = stats->index.postings_bytes + stats->index.geometry_bytes + stats->index.other_bytes;
    info.descriptor = sift::DescriptorKindName(c.front->vocabulary().descriptor_kind());
    info.hamming = c.front->vocabulary().has_hamming();
    nlohmann::json out = api::CollectionToJson(info, with_stats);
    out["partitions"] = c.front->num_partitions();
    return out;
  }

  void ListCollections(Req req, Res res) const {
    const auto shown = server::CollectionListFilter(req, options.http.api_key, keys.get());
    nlohmann::json list = nlohmann::json::array();
    for (const auto& [name, c] : collections) {
      if (!shown(name, c.settings.is_public)) continue;
      auto one = Describe(c, false);
      if (!one) return SendError(res, one.error());
      list.push_back(std::move(*one));
    }
    SendJsonAnswer(res, 200, {{"collections", std::move(list)}});
  }

  // Per shard replica of each collection, after the HTTP metrics.
  std::string ShardMetrics() const {
    std::ostringstream out;
    struct Row {
      std::string collection;
      ReplicaMetrics m;
    };
    std::vector<Row> rows;
    for (const auto& [name, c] : collections)
      for (ReplicaMetrics& m : c.front->Metrics()) rows.push_back({name, std::move(m)});
    const auto labels = [](const Row& r) {
      return "{partition=\"" + std::to_string(r.m.partition) + "\",replica=\"" + r.m.address + "\",collection=\"" +
             r.collection + "\"}";
    };
    const auto family = [&](const char* name, const char* type, const char* help, auto value) {
      out << "# HELP " << name << " " << help << "\n# TYPE " << name << " " << type << "\n";
      for (const Row& r : rows) out << name << labels(r) << " " << value(r.m) << "\n";
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
    // Each route for the collection "default" (/v1/...) and for every collection (/v1/collections/{name}/...).
    const auto both = [&server](const std::string& method, const std::string& pattern, const httplib::Server::Handler& h) {
      for (const std::string& p : {pattern, "/v1/collections/[^/]+" + pattern.substr(3)}) {
        if (method == "GET") server.Get(p, h);
        else if (method == "POST") server.Post(p, h);
        else server.Delete(p, h);
      }
    };
    both("POST", "/v1/search", Route(Access::kRead, [this](const Served& c, Req req, Res res) { Search(c, req, res); }));
    server.Post("/v1/match", [this](Req req, Res res) { Match(req, res); });
    both("GET", "/v1/stats", Route(Access::kRead, [](const Served& c, Req, Res res) { Stats(c, res); }));
    both("GET", "/v1/images", Route(Access::kRead, [](const Served& c, Req req, Res res) { List(c, req, res); }));
    both("POST", "/v1/images", Route(Access::kWrite, [](const Served& c, Req req, Res res) { Add(c, req, res); }));
    both("POST", "/v1/images/batch",
         Route(Access::kWrite, [this](const Served& c, Req req, Res res) { AddBatch(c, req, res); }));
    both("GET", R"(/v1/images/(.+))",
         Route(Access::kRead, [this](const Served& c, Req req, Res res) { GetImageOrSubresource(c, req, res); }));
    both("DELETE", R"(/v1/images/(.+))", Route(Access::kWrite, [](const Served& c, Req req, Res res) { Delete(c, req, res); }));
    both("POST", "/v1/admin/refresh-statistics",
         Route(Access::kWrite, [](const Served& c, Req, Res res) { RefreshStatistics(c, res); }));
    server.Post("/v1/admin/backup", Route(Access::kAdmin, [](const Served& c, Req req, Res res) { Backup(c, req, res); }));
    server.Post(R"(/v1/collections/[^/]+/backup)",
                Route(Access::kAdmin, [](const Served& c, Req req, Res res) { Backup(c, req, res); }));
    // Collections: those of cluster.json; keys when it names a key file.
    server.Get(R"(/v1/collections/?)", [this](Req req, Res res) { ListCollections(req, res); });
    server.Get(R"(/v1/collections/[^/]+)", Route(Access::kRead, [](const Served& c, Req, Res res) {
                 auto described = Describe(c, true);
                 if (!described) return SendError(res, described.error());
                 SendJsonAnswer(res, 200, *described);
               }));
    const auto not_here = [this](Req req, Res res) {
      if (auto refused = server::AuthorizeCollection(req, options.http.api_key, keys.get(), "", std::nullopt, Access::kAdmin))
        return server::SendJsonError(res, *refused);
      SendError(res, {ErrorCode::kIncompatible, "a cluster's collections are those its cluster.json names "
                                                "(\"collections\"): create the collection on every shard "
                                                "(`oxbow serve --data`), name it there and restart the front"});
    };
    server.Post(R"(/v1/collections/?)", not_here);
    server.Delete(R"(/v1/collections/[^/]+)", not_here);
    const auto with_keys = [this](auto serve) {
      return Route(Access::kAdmin, [this, serve](const Served& c, Req req, Res res) {
        if (!keys) {
          return SendError(res, {ErrorCode::kIncompatible, "this cluster has no collection keys: name a key file in "
                                                           "cluster.json (\"collection_keys\")"});
        }
        serve(*keys, c.front->collection(), req, res);
      });
    };
    server.Post(R"(/v1/collections/[^/]+/keys)", with_keys([](api::AccessKeys& k, const std::string& name, Req req, Res res) {
                  server::ServeCreateKey(k, name, req, res);
                }));
    server.Get(R"(/v1/collections/[^/]+/keys)", with_keys([](api::AccessKeys& k, const std::string& name, Req, Res res) {
                 server::ServeListKeys(k, name, res);
               }));
    server.Delete(R"(/v1/collections/[^/]+/keys/([^/]+))",
                  with_keys([](api::AccessKeys& k, const std::string& name, Req req, Res res) {
                    server::ServeDeleteKey(k, name, req.matches[1], res);
                  }));
  }

  FrontHttpOptions options;
  std::map<std::string, Served> collections;
  std::unique_ptr<api::AccessKeys> keys;     // null: none
  std::unique_ptr<server::HttpServer> http;  // last: its routes use the members above
};

Result<std::unique_ptr<FrontHttpServer>> FrontHttpServer::Create(std::shared_ptr<const ClusterFront> front,
                                                                  const FrontHttpOptions& options) {
  return Create({{std::move(front), {}}}, nullptr, options);
}

Result<std::unique_ptr<FrontHttpServer>> FrontHttpServer::Create(std::vector<FrontCollection> collections,
                                                                  std::unique_ptr<api::AccessKeys> keys,
                                                                  const FrontHttpOptions& options) {
  if (auto message = options.service.Check()) return Fail(ErrorCode::kInvalidArgument, "front options: " + *message);
  if (collections.empty()) return Fail(ErrorCode::kInvalidArgument, "a front serves at least one collection");
  auto impl = std::make_unique<Impl>(options);
  for (FrontCollection& c : collections) {
    auto extractor = ExtractorOf(c.front->vocabulary(), options.service.threads_per_request);
    if (!extractor) return std::unexpected(extractor.error());
    const std::string name = c.front->collection();
    if (impl->collections.contains(name)) return Fail(ErrorCode::kInvalidArgument, "collection '" + name + "' given twice");
    impl->collections[name] = Impl::Served{std::move(c.front), c.settings,
                                           std::make_unique<api::Extractions>(*extractor, options.service.Extraction())};
  }
  impl->keys = std::move(keys);
  Impl* i = impl.get();
  i->http = std::make_unique<server::HttpServer>(
      options.http, server::CustomRoutes{[i](httplib::Server& http) { i->Register(http); },
                                         [i] { return i->ShardMetrics(); },
                                         {{"/v1/admin/refresh-statistics", "/v1/admin/refresh-statistics", "POST"},
                                          {"/v1/collections/{name}/admin/refresh-statistics",
                                           "/v1/collections/[^/]+/admin/refresh-statistics", "POST"}}});
  return std::unique_ptr<FrontHttpServer>(new FrontHttpServer(std::move(impl)));
}

FrontHttpServer::FrontHttpServer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
FrontHttpServer::~FrontHttpServer() = default;

Result<int> FrontHttpServer::Bind() { return impl_->http->Bind(); }

void FrontHttpServer::Run() { impl_->http->Run(); }

void FrontHttpServer::Shutdown() {
  for (auto& [name, c] : impl_->collections) c.extractions->Stop();
  impl_->http->Shutdown();
}

}  // namespace oxbow::cluster
