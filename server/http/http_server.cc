#include "server/http/http_server.h"

#include <httplib.h>
#include <malloc.h>
#include <poll.h>
#include <sys/socket.h>

#include <chrono>
#include <cstdio>
#include <functional>
#include <random>
#include <regex>
#include <set>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "server/http/errors.h"
#include "api/duplicate_jobs.h"
#include "api/json.h"
#include "api/params.h"
#include "server/http/web_assets.h"
#include "server/http/request_guard.h"
#include "sift/base/log.h"

namespace oxbow::server {

// This API's OpenAPI description (openapi.json), defined by the openapi_data.cc that
// cmake/EmbedFiles.cmake generates (server/http/CMakeLists.txt).
std::span<const EmbeddedFile> OpenApiFiles();

namespace {

using Clock = std::chrono::steady_clock;
using nlohmann::json;

// What the log line and the metrics need to know about the request this thread is serving. httplib
// handles a request start to finish on one worker thread (pre-routing handler, route handler, error
// handler, logger), so a thread-local carries it; the logger resets it.
struct RequestContext {
  bool active = false;
  std::string id;
  Clock::time_point start;
  std::string route = "unmatched";
  std::string collection;          // the collection addressed, once its route checked it ("" outside one)
  std::optional<api::CollectionRef> held;  // that collection, for the route's body
  std::vector<std::pair<const char*, double>> stages;  // {"extract", 12.1 ms}, ... for the log line
};
thread_local RequestContext t_request;

std::string NewRequestId() {
  thread_local std::mt19937_64 rng(std::random_device{}() ^
                                   std::hash<std::thread::id>{}(std::this_thread::get_id()));
  char buf[17];
  std::snprintf(buf, sizeof buf, "%016llx", static_cast<unsigned long long>(rng()));
  return buf;
}

bool IsSaneRequestId(const std::string& id) {
  if (id.empty() || id.size() > 64) return false;
  for (char c : id) {
    if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '_' || c == '-')) return false;
  }
  return true;
}

// A path safe to print on one log line (no control characters, bounded length).
std::string LoggablePath(const std::string& path) {
  std::string out;
  for (size_t i = 0; i < path.size() && i < 200; ++i) {
    const unsigned char c = static_cast<unsigned char>(path[i]);
    out += (c < 0x20 || c == 0x7f) ? '?' : static_cast<char>(c);
  }
  if (path.size() > 200) out += "...";
  return out;
}

void SendJson(httplib::Response& res, int status, const json& body) {
  res.status = status;
  // Bodies echo client bytes (paths, ids, parameter values) that need not be UTF-8; the strict default
  // would throw (-> 500) where the client's error deserves its 4xx: invalid bytes become U+FFFD.
  res.set_content(body.dump(-1, ' ', false, json::error_handler_t::replace) + "\n", "application/json");
}

void SendError(httplib::Response& res, const HttpError& error) {
  if (error.status == 401) res.set_header("WWW-Authenticate", "Bearer");
  SendJson(res, error.status, ErrorBody(error, t_request.id));
}

void SendError(httplib::Response& res, const Error& error) { SendError(res, ToHttpError(error)); }

// Slow-client protection (server/request_guard.h). A request whose body does not fit the upload budget
// is answered 503 before its body is read.
httplib::Server::HandlerResponse RefuseOverUploadBudget(const httplib::Request& req, httplib::Response& res,
                                                        UploadBudget* budget, uint64_t max_body_bytes) {
  if (ReserveUploadForThisRequest(req, budget, max_body_bytes)) return httplib::Server::HandlerResponse::Unhandled;
  res.set_header("Retry-After", "1");
  res.set_header("Connection", "close");
  CloseConnectionAfterResponse();  // the body stays unread
  SendError(res, Error{ErrorCode::kResourceExhausted,
                       "uploads in progress fill the server's budget of " + std::to_string(budget->capacity()) +
                           " bytes; retry later (oxbow serve --max-inflight-upload-mb)"});
  return httplib::Server::HandlerResponse::Handled;
}

// A request whose headers + body did not arrive within the request timeout, or whose body stopped
// arriving for a whole read timeout.
httplib::Server::HandlerResponse AnswerRequestTimeout(httplib::Response& res, bool stalled) {
  res.set_header("Connection", "close");
  CloseConnectionAfterResponse();
  SendError(res, HttpError{408, "request_timeout",
                           stalled ? "the request body stopped arriving: no byte came within the server's read "
                                     "timeout (oxbow serve --read-timeout-s)"
                                   : "the request did not arrive within the server's request timeout (oxbow serve "
                                     "--request-timeout-s)"});
  return httplib::Server::HandlerResponse::Handled;
}

}  // namespace

std::string ImageLocation(std::string_view prefix, std::string_view id) {
  static constexpr char kHex[] = "0123456789ABCDEF";
  std::string location(prefix);
  location += "/images/";
  for (const char c : id) {
    const auto b = static_cast<unsigned char>(c);
    const bool unreserved = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '-' ||
                            c == '.' || c == '_' || c == '~';
    if (unreserved) {
      location += c;
    } else {
      location += '%';
      location += kHex[b >> 4];
      location += kHex[b & 15];
    }
  }
  return location;
}

// W3C Server Timing.
void RecordStages(httplib::Response& res, const std::vector<std::pair<const char*, double>>& stages) {
  std::string header;
  for (const auto& [name, ms] : stages) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "%s;dur=%.2f", name, ms);
    if (!header.empty()) header += ", ";
    header += buf;
  }
  if (!header.empty()) res.set_header("Server-Timing", header);
  t_request.stages = stages;
}

api::Params CollectParams(const httplib::Request& req, const std::vector<std::string>& file_fields) {
  api::Params params(req.params.begin(), req.params.end());
  for (const auto& [name, part] : req.files) {
    if (std::find(file_fields.begin(), file_fields.end(), name) == file_fields.end()) {
      params.emplace(name, part.content);
    } else if (req.files.count(name) > 1) {
      params.emplace(name, "");
    }
  }
  return params;
}

Result<std::string_view> RequestImage(const httplib::Request& req, const std::string& field,
                                      const std::string& alt_field, std::string* filename) {
  if (req.is_multipart_form_data()) {
    for (const auto* name : {&field, &alt_field}) {
      auto it = req.files.find(*name);
      if (it != req.files.end()) {
        if (it->second.content.empty()) {
          return Fail(ErrorCode::kInvalidImage, "multipart part '" + *name + "' is empty");
        }
        *filename = it->second.filename;
        return std::string_view(it->second.content);
      }
    }
    return Fail(ErrorCode::kInvalidArgument, "multipart request without a '" + field + "' part holding the image");
  }
  const std::string type = req.get_header_value("Content-Type");
  if (type.rfind("application/json", 0) == 0 || type.rfind("text/", 0) == 0) {
    return Fail(ErrorCode::kUnsupportedFormat,
                "Content-Type '" + type + "' is not an image: send the image bytes (e.g. curl --data-binary @photo.jpg "
                "-H 'Content-Type: image/jpeg') or multipart/form-data with a '" + field + "' part");
  }
  if (req.body.empty()) return Fail(ErrorCode::kInvalidImage, "empty request body: send the image bytes");
  return std::string_view(req.body);
}

std::span<const uint8_t> Bytes(std::string_view text) {
  return {reinterpret_cast<const uint8_t*>(text.data()), text.size()};
}

api::AddImageRequest AddImageRequestOf(const api::AddParams& params, std::string_view image, const std::string& filename) {
  api::AddImageRequest add;
  add.id = params.id;
  add.image = Bytes(image);
  add.metadata_json = params.metadata_json;
  add.replace = params.replace;
  add.source_name = filename.empty() ? "http" : "http:" + filename;
  return add;
}

namespace {

// Whether the request's If-None-Match fields name `etag`: "*", or a comma-separated list of entity tags
// compared weakly (RFC 9110 sec. 13.1.2: W/"x" matches "x"), as caches and proxies send them.
bool IfNoneMatchNames(const httplib::Request& req, std::string_view etag) {
  const size_t fields = req.get_header_value_count("If-None-Match");
  for (size_t f = 0; f < fields; ++f) {
    const std::string value = req.get_header_value("If-None-Match", f);
    size_t pos = 0;
    while (pos <= value.size()) {
      size_t end = value.find(',', pos);
      if (end == std::string::npos) end = value.size();
      std::string_view tag = std::string_view(value).substr(pos, end - pos);
      while (!tag.empty() && (tag.front() == ' ' || tag.front() == '\t')) tag.remove_prefix(1);
      while (!tag.empty() && (tag.back() == ' ' || tag.back() == '\t')) tag.remove_suffix(1);
      if (tag == "*") return true;
      if (tag.starts_with("W/")) tag.remove_prefix(2);
      if (!tag.empty() && tag == etag) return true;
      pos = end + 1;
    }
  }
  return false;
}

// Bytes with a strong ETag: 304 without a body when the client already holds them (If-None-Match).
void SendCacheable(const httplib::Request& req, httplib::Response& res, std::string_view content,
                   const std::string& content_type, const std::string& etag, const char* cache_control) {
  res.set_header("ETag", etag);
  res.set_header("Cache-Control", cache_control);
  res.set_header("X-Content-Type-Options", "nosniff");
  if (IfNoneMatchNames(req, etag)) {
    res.status = 304;
    return;
  }
  res.status = 200;
  res.set_content(content.data(), content.size(), content_type.c_str());
}

// The web page's files (server/web_assets.h): revalidated on every use (cheap 304s), so a new binary's
// page is never mixed with an old cached script. The policy keeps the page on this server only.
void SendWebAsset(const httplib::Request& req, httplib::Response& res, std::string_view path) {
  const WebAsset* asset = FindWebAsset(path);
  if (asset == nullptr) return SendError(res, RouteNotFound(req.method, LoggablePath(req.path)));
  res.set_header("Content-Security-Policy",
                 "default-src 'self'; img-src 'self' blob: data:; connect-src 'self'; frame-ancestors 'none'; "
                 "base-uri 'none'; form-action 'none'");
  SendCacheable(req, res, asset->content, asset->content_type, asset->etag, "no-cache");
}

constexpr std::string_view kCollectionsPrefix = "/v1/collections/";

// The collection a /v1 path addresses: the name after /v1/collections/, else "default".
std::string CollectionNameOfPath(std::string_view path) {
  if (!path.starts_with(kCollectionsPrefix)) return api::kDefaultCollection;
  path.remove_prefix(kCollectionsPrefix.size());
  return std::string(path.substr(0, path.find('/')));
}

// The route of the default collection that a collection's route mirrors: "/v1/collections/paris/images/x"
// -> "/v1/images/x" (other paths unchanged).
std::string UnprefixedPath(std::string_view path) {
  if (!path.starts_with(kCollectionsPrefix)) return std::string(path);
  const size_t slash = path.find('/', kCollectionsPrefix.size());
  return slash == std::string_view::npos ? std::string() : "/v1" + std::string(path.substr(slash));
}

// "/v1/collections/{name}" for a path under a collection, else "/v1": where the request's routes live.
std::string RoutePrefixOf(std::string_view path) {
  if (!path.starts_with(kCollectionsPrefix)) return "/v1";
  return "/v1/collections/" + CollectionNameOfPath(path);
}

// The key the request presents (X-API-Key, else Authorization: Bearer), whole: httplib's get_header_value
// stops at a NUL byte ("KEY\0junk" would pass).
std::string PresentedKey(const httplib::Request& req) {
  std::string key = FullHeaderValue(req, "X-API-Key");
  const std::string auth = FullHeaderValue(req, "Authorization");
  if (key.empty() && auth.rfind("Bearer ", 0) == 0) key = auth.substr(7);
  return key;
}

}  // namespace

std::string CollectionOfPath(std::string_view path) { return CollectionNameOfPath(path); }

void NoteCollection(const std::string& collection) {
  if (t_request.active) t_request.collection = collection;
}

bool ConstantTimeEquals(const std::string& given, const std::string& expected) {
  // Compare every byte of the longer string so the time does not reveal the matching prefix.
  const size_t n = std::max(given.size(), expected.size());
  unsigned char diff = given.size() == expected.size() ? 0 : 1;
  for (size_t i = 0; i < n; ++i) {
    const unsigned char a = i < given.size() ? static_cast<unsigned char>(given[i]) : 0;
    const unsigned char b = i < expected.size() ? static_cast<unsigned char>(expected[i]) : 0;
    diff |= static_cast<unsigned char>(a ^ b);
  }
  return diff == 0;
}

// The Request is owned (non-const) by httplib's connection loop; this hook runs before the body is read.
void TakeFormEncodedBodyAsImage(const httplib::Request& req) {
  const std::string path = UnprefixedPath(req.path);
  if (req.method != "POST" || (path != "/v1/images" && path != "/v1/search")) return;
  auto& headers = const_cast<httplib::Request&>(req).headers;
  auto it = headers.find("Content-Type");
  if (it != headers.end() && it->second.rfind("application/x-www-form-urlencoded", 0) == 0) {
    it->second = "application/octet-stream";
  }
}

std::string RequestIdFor(const httplib::Request& req) {
  const std::string given = req.get_header_value("X-Request-Id");
  return IsSaneRequestId(given) ? given : NewRequestId();
}

std::optional<HttpError> CheckApiKey(const httplib::Request& req, const std::string& api_key) {
  if (api_key.empty()) return std::nullopt;
  const std::string key = PresentedKey(req);
  if (key.empty()) {
    return ToHttpError(
        {ErrorCode::kUnauthenticated, "this route needs the API key: header 'Authorization: Bearer KEY' or 'X-API-Key: KEY'"});
  }
  if (!ConstantTimeEquals(key, api_key)) return PermissionDenied("wrong API key");
  return std::nullopt;
}

std::optional<std::string> HttpServerOptions::Check() const {
  if (host.empty()) return "host must not be empty";
  if (port < 0 || port > 65535) return "port must be in [0, 65535]";
  if (threads < 1 || threads > 1024) return "threads must be in [1, 1024]";
  if (max_queued_connections < 1 || max_queued_connections > 100000) return "max_queued_connections must be in [1, 100000]";
  if (max_body_bytes < 1 || max_body_bytes > (1ull << 32)) return "max_body_bytes must be in [1, 2^32]";
  if (read_timeout_s < 1 || read_timeout_s > 3600) return "read_timeout_s must be in [1, 3600]";
  if (write_timeout_s < 1 || write_timeout_s > 3600) return "write_timeout_s must be in [1, 3600]";
  if (keep_alive_timeout_s < 1 || keep_alive_timeout_s > 3600) return "keep_alive_timeout_s must be in [1, 3600]";
  if (keep_alive_max_requests < 1 || keep_alive_max_requests > 100000) return "keep_alive_max_requests must be in [1, 100000]";
  if (request_timeout_s < 1 || request_timeout_s > 3600) return "request_timeout_s must be in [1, 3600]";
  if (max_header_count < 1 || max_header_count > 10000) return "max_header_count must be in [1, 10000]";
  if (max_head_bytes < 1024 || max_head_bytes > (1u << 24)) return "max_head_bytes must be in [1024, 2^24]";
  if (max_connections_per_client < 1 || max_connections_per_client > 100000) {
    return "max_connections_per_client must be in [1, 100000]";
  }
  if (max_batch_images < 1 || max_batch_images > 10000) return "max_batch_images must be in [1, 10000]";
  if (max_inflight_body_bytes < max_body_bytes || max_inflight_body_bytes > (1ull << 40)) {
    return "max_inflight_body_bytes must be in [max_body_bytes, 2^40] (at least one largest upload must fit)";
  }
  return std::nullopt;
}

// Route patterns with their methods, for 405 answers and the route label of unmatched requests.
struct HttpServer::RouteTable {
  struct Route {
    std::string label;     // "/v1/images/{id}"
    std::regex pattern;    // full-path match
    std::string methods;   // "GET, DELETE"
  };
  std::vector<Route> routes;

  const Route* Find(const std::string& path) const {
    for (const auto& r : routes) {
      if (std::regex_match(path, r.pattern)) return &r;
    }
    return nullptr;
  }
};

namespace {
// The single node's routes; a server of CustomRoutes adds its own before them (HttpServer::routes_).
const HttpServer::RouteTable& Routes() {
  static const HttpServer::RouteTable table = {{
      {"/", std::regex("/"), "GET"},
      {"/static/{file}", std::regex("/static/.+"), "GET"},
      {"/v1", std::regex("/v1/?"), "GET"},
      {"/v1/openapi.json", std::regex("/v1/openapi\\.json"), "GET"},
      {"/healthz", std::regex("/healthz"), "GET"},
      {"/readyz", std::regex("/readyz"), "GET"},
      {"/metrics", std::regex("/metrics"), "GET"},
      {"/v1/stats", std::regex("/v1/stats"), "GET"},
      {"/v1/images", std::regex("/v1/images"), "GET, POST"},
      // Before {id}: "batch" is refused as a new image's id (api::CheckNewImageId).
      {"/v1/images/batch", std::regex("/v1/images/batch"), "POST"},
      {"/v1/images/{id}/similar", std::regex("/v1/images/.+/similar"), "GET"},
      {"/v1/images/{id}/thumbnail", std::regex("/v1/images/.+/thumbnail"), "GET"},
      {"/v1/images/{id}", std::regex("/v1/images/.+"), "GET, DELETE"},
      {"/v1/search", std::regex("/v1/search"), "POST"},
      {"/v1/match", std::regex("/v1/match"), "POST"},
      {"/v1/admin/backup", std::regex("/v1/admin/backup"), "POST"},
      {"/v1/duplicates", std::regex("/v1/duplicates"), "POST"},
      {"/v1/jobs/{job}", std::regex("/v1/jobs/[^/]+"), "GET, DELETE"},
      {"/v1/collections", std::regex("/v1/collections/?"), "GET, POST"},
      {"/v1/collections/{name}/stats", std::regex("/v1/collections/[^/]+/stats"), "GET"},
      {"/v1/collections/{name}/images", std::regex("/v1/collections/[^/]+/images"), "GET, POST"},
      {"/v1/collections/{name}/images/batch", std::regex("/v1/collections/[^/]+/images/batch"), "POST"},
      {"/v1/collections/{name}/images/{id}/similar", std::regex("/v1/collections/[^/]+/images/.+/similar"), "GET"},
      {"/v1/collections/{name}/images/{id}/thumbnail", std::regex("/v1/collections/[^/]+/images/.+/thumbnail"), "GET"},
      {"/v1/collections/{name}/images/{id}", std::regex("/v1/collections/[^/]+/images/.+"), "GET, DELETE"},
      {"/v1/collections/{name}/search", std::regex("/v1/collections/[^/]+/search"), "POST"},
      {"/v1/collections/{name}/keys", std::regex("/v1/collections/[^/]+/keys"), "GET, POST"},
      {"/v1/collections/{name}/keys/{id}", std::regex("/v1/collections/[^/]+/keys/[^/]+"), "DELETE"},
      {"/v1/collections/{name}/backup", std::regex("/v1/collections/[^/]+/backup"), "POST"},
      {"/v1/collections/{name}/duplicates", std::regex("/v1/collections/[^/]+/duplicates"), "POST"},
      {"/v1/collections/{name}", std::regex("/v1/collections/[^/]+"), "GET, DELETE"},
  }};
  return table;
}

// ---- Route handlers (run by HttpServer::ServiceRoute once the service is available)

// The routes, and the limits a client sizes its requests by (the Python client's add_many chunks its
// batches by max_batch_images).
void DescribeApi(const HttpServerOptions& options, const HttpServer::RouteTable& table, httplib::Response& res) {
  json routes = json::array();
  for (const auto& r : table.routes) routes.push_back({{"route", r.label}, {"methods", r.methods}});
  const json limits = {{"max_batch_images", options.max_batch_images}, {"max_upload_bytes", options.max_body_bytes}};
  SendJson(res, 200, {{"service", "oxbow"}, {"api_version", "v1"}, {"routes", routes}, {"limits", limits}});
}

// The document is fixed at build time; clients revalidate with its ETag (304).
void ServeOpenApi(const httplib::Request& req, httplib::Response& res) {
  const std::string_view document = OpenApiFiles().front().content;
  static const std::string etag = StrongEtag(document);
  SendCacheable(req, res, document, "application/json", etag, "no-cache");
}

// Answers 507 when adding `adding` images would pass the limits of the request's collection.
bool RefusedWhenFull(httplib::Response& res, uint64_t adding) {
  if (!t_request.held) return false;
  auto full = api::Collections::CheckRoom(*t_request.held, adding);
  if (!full) return false;
  SendError(res, CollectionFull(*full));
  return true;
}

void PostImage(api::Service& s, const httplib::Request& req, httplib::Response& res) {
  auto params = api::ParseAddParams(CollectParams(req, {"file", "image"}));
  if (!params) return SendError(res, params.error());
  if (RefusedWhenFull(res, params->replace ? 0 : 1)) return;
  std::string filename;
  auto image = RequestImage(req, "file", "image", &filename);
  if (!image) return SendError(res, image.error());
  api::AddImageRequest add = AddImageRequestOf(*params, *image, filename);
  add.client_gone = ClientGone();
  auto added = s.AddImage(add);
  if (!added) return SendError(res, added.error());
  RecordStages(res, {{"decode_extract", added->decode_extract_ms}, {"add", added->add_ms}});
  res.set_header("Location", ImageLocation(RoutePrefixOf(req.path), added->record.id));
  SendJson(res, added->replaced ? 200 : 201, api::AddImageResponseToJson(*added));
}

void ListImages(api::Service& s, const httplib::Request& req, httplib::Response& res) {
  auto params = api::ParseListParams(CollectParams(req, {}));
  if (!params) return SendError(res, params.error());
  auto list = s.ListImages(params->offset, params->limit);
  if (!list) return SendError(res, list.error());
  SendJson(res, 200, api::ListResponseToJson(*list));
}

void GetSimilar(api::Service& s, const std::string& id, const httplib::Request& req, httplib::Response& res) {
  auto options = api::ParseQueryParams(CollectParams(req, {}), s.options().default_query);
  if (!options) return SendError(res, options.error());
  auto found = s.SearchSimilar(id, *options);
  if (!found) return SendError(res, found.error());
  const auto& t = found->index.timings;
  RecordStages(res, {{"quantize", t.quantize_ms}, {"score", t.score_ms}, {"verify", t.verify_ms}, {"qe", t.qe_ms}});
  SendJson(res, 200, api::SearchResponseToJson(*found));
}

void GetThumbnail(api::Service& s, const std::string& id, const httplib::Request& req, httplib::Response& res) {
  auto size = ThumbnailSizeParam(req);
  if (!size) return SendError(res, size.error());
  auto found = s.GetThumbnail(id, *size);
  if (!found) return SendError(res, found.error());
  SendThumbnail(req, res, found->thumbnail.jpeg);
}

void GetImage(api::Service& s, const std::string& id, httplib::Response& res) {
  auto record = s.GetImage(id);
  if (!record) return SendError(res, record.error());
  SendJson(res, 200, api::ImageRecordToJson(*record));
}

void GetImageOrSubresource(api::Service& s, const httplib::Request& req, httplib::Response& res) {
  const ImagePath path = ImagePathOf(req);
  const std::string prefix = req.path.starts_with(kCollectionsPrefix) ? "/v1/collections/{name}" : "/v1";
  t_request.route = prefix + (path.sub.empty() ? "/images/{id}" : "/images/{id}/" + path.sub);
  if (path.sub == "similar") return GetSimilar(s, path.id, req, res);
  if (path.sub == "thumbnail") return GetThumbnail(s, path.id, req, res);
  GetImage(s, path.id, res);
}

void DeleteImage(api::Service& s, const httplib::Request& req, httplib::Response& res) {
  const std::string id = req.matches[1];
  if (auto removed = s.DeleteImage(id); !removed) return SendError(res, removed.error());
  SendJson(res, 200, {{"id", id}, {"deleted", true}});
}

void PostSearch(api::Service& s, const httplib::Request& req, httplib::Response& res) {
  auto options = api::ParseQueryParams(CollectParams(req, {"file", "image"}), s.options().default_query);
  if (!options) return SendError(res, options.error());
  std::string filename;
  auto image = RequestImage(req, "file", "image", &filename);
  if (!image) return SendError(res, image.error());
  auto found = s.Search(Bytes(*image), *options, ClientGone());
  if (!found) return SendError(res, found.error());
  const auto& t = found->index.timings;
  RecordStages(res, {{"decode_extract", found->decode_extract_ms}, {"quantize", t.quantize_ms},
                     {"score", t.score_ms}, {"verify", t.verify_ms}, {"qe", t.qe_ms}});
  SendJson(res, 200, api::SearchResponseToJson(*found));
}

void PostMatch(api::Service& s, const httplib::Request& req, httplib::Response& res) {
  ServeMatch(req, res, [&](std::span<const uint8_t> a, std::span<const uint8_t> b, const api::PairMatchOptions& options) {
    return s.Match(a, b, options, ClientGone());
  });
}

void PostImageBatch(api::Service& s, const httplib::Request& req, httplib::Response& res, int max_images) {
  if (RefusedWhenFull(res, req.files.count("image"))) return;
  ServeImageBatch(req, res, max_images, [&](api::AddBatchRequest& batch) { return s.AddImages(batch); });
}

void PostBackup(api::Service& s, const httplib::Request& req, httplib::Response& res) {
  auto out = BackupFolderParam(req);
  if (!out) return SendError(res, out.error());
  auto done = s.Backup(*out);
  if (!done) return SendError(res, done.error());
  SendJson(res, 200, api::BackupToJson(*out, *done));
}
}  // namespace

void SendJsonAnswer(httplib::Response& res, int status, const nlohmann::json& body) { SendJson(res, status, body); }
void SendJsonError(httplib::Response& res, const HttpError& error) { SendError(res, error); }

// A client that only half-closes its sending side counts as gone too. Called by the service on its
// extraction thread while the handler waits, hence the socket captured here.
sift::StopRequested ClientGone() {
  const int sock = CurrentConnectionSocket();
  return [sock] {
    pollfd p{sock, POLLRDHUP, 0};
    return sock >= 0 && ::poll(&p, 1, 0) > 0 && (p.revents & (POLLRDHUP | POLLHUP | POLLERR)) != 0;
  };
}

void ServeMatch(const httplib::Request& req, httplib::Response& res, const PairMatcher& match_pair) {
  if (!req.is_multipart_form_data()) {
    return SendError(res, Error{ErrorCode::kUnsupportedFormat,
                                "POST /v1/match takes multipart/form-data with image parts 'a' and 'b'"});
  }
  auto params = api::ParseMatchParams(CollectParams(req, {"a", "b"}));
  if (!params) return SendError(res, params.error());
  std::string name_a, name_b;
  auto a = RequestImage(req, "a", "a", &name_a);
  if (!a) return SendError(res, a.error());
  auto b = RequestImage(req, "b", "b", &name_b);
  if (!b) return SendError(res, b.error());
  api::PairMatchOptions options;
  options.model = params->model;
  options.match = params->match;
  options.min_inliers = params->min_inliers;
  options.correspondences = params->correspondences;
  auto matched = match_pair(Bytes(*a), Bytes(*b), options);
  if (!matched) return SendError(res, matched.error());
  RecordStages(res, {{"decode_extract_a", matched->decode_extract_a_ms},
                     {"decode_extract_b", matched->decode_extract_b_ms},
                     {"match", matched->match.match_ms}, {"verify", matched->match.verify_ms}});
  SendJson(res, 200, api::MatchResponseToJson(*matched));
}

// One image of a batch add's answer: {"id", "status": 201, "image": record} or {"id", "status", "error"}.
namespace {
json BatchResultToJson(const std::string& id, const Result<index::ImageRecord>& result) {
  if (result) return {{"id", id}, {"status", 201}, {"image", api::ImageRecordToJson(*result)}};
  const HttpError error = ToHttpError(result.error());
  return {{"id", id}, {"status", error.status}, {"error", ErrorBody(error, t_request.id)["error"]}};
}
}  // namespace

// httplib keeps the parts of one name in the order sent.
void ServeImageBatch(const httplib::Request& req, httplib::Response& res, int max_images, const BatchAdder& add) {
  const auto start = Clock::now();
  if (!req.is_multipart_form_data()) {
    return SendError(res, Error{ErrorCode::kUnsupportedFormat,
                                "POST /v1/images/batch takes multipart/form-data: parts 'image' (the images), 'id' "
                                "(one per image, in the same order) and optionally 'metadata'"});
  }
  std::vector<std::string_view> images;
  std::vector<std::string> filenames, ids, metadata;
  api::Params others(req.params.begin(), req.params.end());
  for (const auto& [name, part] : req.files) {
    if (name == "image") {
      images.push_back(part.content);
      filenames.push_back(part.filename);
    } else if (name == "id") {
      ids.push_back(part.content);
    } else if (name == "metadata") {
      metadata.push_back(part.content);
    } else {
      others.emplace(name, part.content);
    }
  }
  if (images.size() > static_cast<size_t>(max_images)) {
    return SendError(res, HttpError{413, "payload_too_large",
                                         std::to_string(images.size()) + " images in one request, over the server's "
                                         "limit of " + std::to_string(max_images) +
                                         " (oxbow serve --max-batch-images); nothing was added"});
  }
  auto items = api::ParseBatchAddParams(ids, metadata, images.size(), others);
  if (!items) return SendError(res, items.error());

  std::vector<Result<index::ImageRecord>> results(images.size(), Fail(ErrorCode::kInternal, "not processed"));
  api::AddBatchRequest batch;
  std::vector<size_t> position;  // of each image of `batch` in the request
  for (size_t i = 0; i < images.size(); ++i) {
    auto& item = (*items)[i];
    if (!item.status) {
      results[i] = std::unexpected(item.status.error());
    } else if (images[i].empty()) {
      results[i] = Fail(ErrorCode::kInvalidImage, "multipart part 'image' number " + std::to_string(i + 1) + " is empty");
    } else {
      batch.images.push_back({std::move(item.id), Bytes(images[i]), std::move(item.metadata_json),
                              filenames[i].empty() ? "http" : "http:" + filenames[i]});
      position.push_back(i);
    }
  }
  batch.client_gone = ClientGone();
  auto added = add(batch);
  for (size_t b = 0; b < position.size(); ++b) {
    if (added) {
      results[position[b]] = std::move(added->results[b]);
    } else {
      results[position[b]] = std::unexpected(added.error());
    }
  }
  json body = json::object();
  json list = json::array();
  size_t ok = 0;
  for (size_t i = 0; i < results.size(); ++i) {
    ok += results[i].has_value() ? 1 : 0;
    list.push_back(BatchResultToJson(ids[i], results[i]));
  }
  int status = 200;
  if (!added) {
    const HttpError error = ToHttpError(added.error());
    status = error.status;
    body = ErrorBody(error, t_request.id);
  } else {
    RecordStages(res, {{"decode_extract", added->decode_extract_ms}, {"add", added->add_ms}});
    body["timings_ms"] = {{"decode_extract", added->decode_extract_ms}, {"add", added->add_ms},
                          {"total", std::chrono::duration<double, std::milli>(Clock::now() - start).count()}};
  }
  body["results"] = std::move(list);
  body["added"] = ok;
  body["failed"] = results.size() - ok;
  SendJson(res, status, body);
}

// The folder is named by the client but written by the server, on its machine: absolute, so that it
// does not depend on the server's working directory.
Result<std::string> BackupFolderParam(const httplib::Request& req) {
  std::string out;
  if (req.get_header_value("Content-Type").rfind("application/json", 0) == 0) {
    const json body = json::parse(req.body, nullptr, false);
    if (body.is_object() && body.contains("out") && body["out"].is_string()) out = body["out"].get<std::string>();
  } else if (auto params = CollectParams(req, {}); params.count("out") == 1) {
    out = params.find("out")->second;
  }
  if (out.empty() || out.front() != '/') {
    return Fail(ErrorCode::kInvalidArgument,
                "POST /v1/admin/backup needs 'out', the absolute path of a new folder on the server's "
                "machine: JSON {\"out\": \"/backups/index-1\"} or the form or query parameter out");
  }
  return out;
}

// httplib matches routes on the decoded path, where the id "a/similar" sent as a%2Fsimilar would read as
// the similar images of "a". A slash sent encoded belongs to the id (RFC 3986 2.2), so an id stored
// before ParseAddParams refused such ids stays reachable.
ImagePath ImagePathOf(const httplib::Request& req) {
  // Matched by the route's pattern: /v1/images/... or /v1/collections/{name}/images/...
  const size_t kPrefix = req.path.size() - UnprefixedPath(req.path).size() + std::string_view("/v1/images/").size();
  const std::string_view path(req.path);
  const std::string_view target = std::string_view(req.target).substr(0, req.target.find('?'));
  const std::string last = httplib::detail::decode_url(std::string(target.substr(target.rfind('/') + 1)), false);
  // Decoding never joins bytes across a literal '/', so the decoded path ends in "/" + last.
  const size_t id_size = path.size() - kPrefix - std::min(path.size() - kPrefix, last.size() + 1);
  if ((last == "similar" || last == "thumbnail") && id_size > 0) return {std::string(path.substr(kPrefix, id_size)), last};
  return {std::string(path.substr(kPrefix)), ""};
}

Result<int> ThumbnailSizeParam(const httplib::Request& req) {
  const api::Params params = CollectParams(req, {});
  if (auto known = api::CheckKnownParams(params, {"size"}); !known) return std::unexpected(known.error());
  int size = 256;  // a larger size than the server stores gets the stored one
  if (auto it = params.find("size"); it != params.end()) {
    auto parsed = api::ParseInt("size", it->second, api::kMinThumbnailPx, api::kMaxThumbnailPx);
    if (!parsed) return std::unexpected(parsed.error());
    size = static_cast<int>(*parsed);
  }
  return size;
}

void SendThumbnail(const httplib::Request& req, httplib::Response& res, const std::string& jpeg) {
  SendCacheable(req, res, jpeg, "image/jpeg", StrongEtag(jpeg), "private, max-age=60");
}


HttpServer::HttpServer(const HttpServerOptions& options) : HttpServer(options, CustomRoutes{}) {}

HttpServer::HttpServer(const HttpServerOptions& options, CustomRoutes routes)
    : options_(options),
      custom_routes_(std::move(routes)),
      upload_budget_(std::make_unique<UploadBudget>(options.max_inflight_body_bytes)) {
  auto table = std::make_unique<RouteTable>();
  for (const RouteInfo& r : custom_routes_.more_routes) table->routes.push_back({r.label, std::regex(r.pattern), r.methods});
  for (const auto& r : Routes().routes) {
    // A server of custom routes (a cluster front) runs no duplicate jobs.
    if (custom_routes_.add && (r.label.ends_with("/duplicates") || r.label.starts_with("/v1/jobs"))) {
      continue;
    }
    table->routes.push_back(r);
  }
  routes_ = std::move(table);
  GuardOptions guard;
  guard.request_timeout = std::chrono::seconds(options_.request_timeout_s);
  guard.threads = options_.threads;
  guard.max_queued = options_.max_queued_connections;
  guard.max_connections_per_client = options_.max_connections_per_client;
  guard.head.max_header_count = static_cast<size_t>(options_.max_header_count);
  guard.head.max_head_bytes = options_.max_head_bytes;
  guard.head.max_body_bytes = options_.max_body_bytes;
  guard.budget = upload_budget_.get();
  guard.refusal_writer = [this](const RefusedRequest& refused, httplib::Response& res) { AnswerRefusal(refused, res); };
  http_ = std::make_unique<GuardedHttpServer>(std::move(guard));
  http_->set_payload_max_length(static_cast<size_t>(options_.max_body_bytes));
  http_->set_read_timeout(options_.read_timeout_s, 0);
  http_->set_write_timeout(options_.write_timeout_s, 0);
  http_->set_keep_alive_timeout(options_.keep_alive_timeout_s);
  http_->set_keep_alive_max_count(static_cast<size_t>(options_.keep_alive_max_requests));
  // httplib writes the headers and the body separately; with Nagle's algorithm the body then waits for
  // the client's delayed ACK (40 ms on Linux) on every response of a keep-alive connection.
  http_->set_tcp_nodelay(true);
  // httplib's default sets SO_REUSEPORT, with which a second server binds the same port and the kernel
  // splits the connections between both. SO_REUSEADDR alone still allows a restart while the old
  // connections linger in TIME_WAIT, and a port in use is refused (Bind's error).
  http_->set_socket_options([](socket_t sock) {
    int yes = 1;
    (void)setsockopt(sock, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof(yes));
  });
  // glibc raises its mmap threshold to the largest block freed (up to 32 MiB), after which request
  // bodies and decoded images come from the per-thread arenas, where a freed block stays resident: a
  // burst of 20 MB uploads would leave ~800 MiB resident for good. A fixed
  // threshold keeps every block of 1 MiB and more in mmap, handed back to the system when freed.
  mallopt(M_MMAP_THRESHOLD, 1 << 20);
  // Below that threshold, freed memory at the top of a malloc arena is kept up to 64 MiB (glibc's default
  // with a fixed mmap threshold: 128 KiB) instead of handed back and faulted in again by the next
  // search: a search's shortlist copies (about 18 MB at 1000 candidates) and many smaller tables come
  // from there, and a first touch costs about 18 us a page on the 2-core test VM. Large blocks (request
  // bodies, decoded images) still go back to the system when freed.
  mallopt(M_TRIM_THRESHOLD, 64 << 20);
  jobs_ = std::make_unique<api::DuplicateJobs>();
  RegisterRoutes();
}

HttpServer::~HttpServer() = default;

std::shared_ptr<api::Collections> HttpServer::collections() const {
  std::lock_guard<std::mutex> lock(service_mutex_);
  return collections_;
}

void HttpServer::SetService(std::shared_ptr<api::Service> service) { SetCollections(api::Collections::Single(std::move(service))); }

void HttpServer::SetCollections(std::shared_ptr<api::Collections> collections) {
  std::lock_guard<std::mutex> lock(service_mutex_);
  collections_ = std::move(collections);
}

bool HttpServer::ready() const { return (custom_routes_.add || collections() != nullptr) && !shutting_down_.load(); }

Result<int> HttpServer::Bind() {
  if (auto message = options_.Check()) return Fail(ErrorCode::kInvalidArgument, "server options: " + *message);
  if (options_.port == 0) {
    port_ = http_->bind_to_any_port(options_.host);
    if (port_ <= 0) return Fail(ErrorCode::kIoError, "cannot bind " + options_.host + " on any port");
  } else {
    if (!http_->bind_to_port(options_.host, options_.port)) {
      return Fail(ErrorCode::kIoError, "cannot bind " + options_.host + ":" + std::to_string(options_.port) +
                                           " (in use, or not an address of this machine?)");
    }
    port_ = options_.port;
  }
  return port_;
}

void HttpServer::Run() {
  if (shutting_down_.load()) return;
  // httplib's stop() does nothing until listen has started, so a Shutdown() that comes before (a fast
  // failing index load, an early SIGTERM) would be lost. This watcher waits until the server runs, then
  // repeats the stop if a shutdown was asked meanwhile; a later Shutdown() stops the running server itself.
  std::atomic<bool> listen_returned{false};
  std::thread watcher([&] {
    while (!http_->is_running() && !listen_returned.load()) std::this_thread::sleep_for(std::chrono::milliseconds(1));
    if (shutting_down_.load()) http_->stop();
  });
  http_->listen_after_bind();
  listen_returned.store(true);
  watcher.join();
}

void HttpServer::Shutdown() {
  shutting_down_.store(true);  // before stop(): Run's watcher reads it after the server started
  // Extractions still running after the service's shutdown grace are abandoned (503) rather than
  // waited for: stop() returns once the requests in flight end.
  if (auto set = collections()) set->StopExtractions();
  http_->stop();
}

void HttpServer::RegisterRoutes() {
  RegisterRequestHooks();
  RegisterErrorHandlers();
  RegisterStatusRoutes();
  if (custom_routes_.add) {
    custom_routes_.add(*http_);
    return;
  }
  Both("GET", "/v1/stats", ServiceRoute(Access::kRead, [](api::Service& s, const httplib::Request&, httplib::Response& res) {
         SendJson(res, 200, api::StatsToJson(s.Stats()));
       }));
  RegisterImageRoutes();
  RegisterSearchRoutes();
  RegisterCollectionRoutes();
  RegisterDuplicateRoutes();
}

void HttpServer::RegisterRequestHooks() {
  // Every request starts here (after its headers are read, before its body is).
  http_->set_pre_routing_handler([this](const httplib::Request& req, httplib::Response& res) {
    t_request = RequestContext{};
    t_request.active = true;
    t_request.start = Clock::now();
    t_request.id = RequestIdFor(req);
    res.set_header("X-Request-Id", t_request.id);
    if (const auto* route = routes_->Find(req.path)) t_request.route = route->label;
    TakeFormEncodedBodyAsImage(req);
    return RefuseOverUploadBudget(req, res, upload_budget_.get(), options_.max_body_bytes);
  });

  http_->set_logger([this](const httplib::Request& req, const httplib::Response& res) {
    const double seconds = t_request.active ? std::chrono::duration<double>(Clock::now() - t_request.start).count() : 0;
    LogRequest(t_request.active ? t_request.id : "-", req.method, LoggablePath(req.path),
               t_request.active ? t_request.route : "unmatched", res.status, seconds, t_request.stages, "");
    t_request = RequestContext{};
  });
}

void HttpServer::LogRequest(const std::string& id, const std::string& method, const std::string& path,
                            const std::string& route, int status, double seconds,
                            const std::vector<std::pair<const char*, double>>& stages, const std::string& refusal) {
  metrics_.Observe(route, method, status, seconds, t_request.active ? t_request.collection : "");
  if (log::Level::kInfo < log::GetLevel()) return;
  log::Line line(log::Level::kInfo);
  // The same facts as the text, as fields for --log-format json (server/README.md, "Logging").
  line.Field("request_id", id).Field("method", method).Field("path", path).Field("route", route);
  line.Field("status", status).Field("latency_ms", seconds * 1000).Field("stages_ms", stages);
  if (t_request.active && !t_request.collection.empty()) line.Field("collection", t_request.collection);
  line << "http " << id << " " << method << " " << path << " route=" << route << " status=" << status << " ";
  if (!refusal.empty()) {
    line.Field("refused", refusal);
    line << "refused: " << refusal;
    return;
  }
  line << "ms=" << seconds * 1000;
  for (const auto& [name, ms] : stages) {
    char buf[64];
    std::snprintf(buf, sizeof buf, " %s=%.2f", name, ms);
    line << buf;
  }
}

void HttpServer::AnswerRefusal(const RefusedRequest& refused, httplib::Response& res) {
  const std::string id = IsSaneRequestId(refused.request_id) ? refused.request_id : NewRequestId();
  const std::string path = refused.target.substr(0, refused.target.find('?'));
  const auto* route = path.empty() ? nullptr : routes_->Find(path);
  const std::string route_label = route != nullptr ? route->label : "unmatched";
  // Only the standard methods become a metrics label (a client's invented ones would add series).
  static const std::set<std::string> kMethods = {"GET", "HEAD", "POST", "PUT", "DELETE", "CONNECT", "OPTIONS", "TRACE", "PATCH"};
  const std::string method = kMethods.contains(refused.method) ? refused.method : "-";
  res.set_header("X-Request-Id", id);
  if (refused.refusal.status == 503) res.set_header("Retry-After", "1");
  const HttpError error{refused.refusal.status, refused.refusal.code, refused.refusal.message};
  SendJson(res, error.status, ErrorBody(error, id));
  LogRequest(id, method, path.empty() ? "-" : LoggablePath(path), route_label, res.status, 0, {},
             refused.refusal.message);
}

namespace {

// A form-encoded body: the HTTP library reads at most 8 KiB of one and answers 413 beyond. A
// Content-Length over the server's limit never reaches it (the request guard refuses it unread).
bool IsFormEncoded(const httplib::Request& req) {
  return req.get_header_value("Content-Type").rfind("application/x-www-form-urlencoded", 0) == 0;
}

// What the HTTP library could not read of a request it refused with `status` (the head was checked
// before it, so the body).
std::string UnreadBodyReason(const httplib::Request& req, int status) {
  const std::string suffix = " (status " + std::to_string(status) + ")";
  if (status == 400 && req.is_multipart_form_data()) {
    return "the multipart/form-data body could not be read: a part or the closing boundary is malformed or "
           "missing, or the body ended early" + suffix;
  }
  if (status == 400 && req.get_header_value("Transfer-Encoding") == "chunked") {
    return "the chunked body could not be read: a chunk size is malformed, or the body ended early" + suffix;
  }
  if (status == 400 && req.has_header("Content-Length")) {
    return "the request body could not be read: it was cut short, or is not in the form its Content-Type names" + suffix;
  }
  return "the HTTP request could not be processed" + suffix;
}

}  // namespace

void HttpServer::RegisterErrorHandlers() {
  // Responses with an error status that no handler filled (unknown route, payload too large, malformed
  // request) get the JSON error shape; an unknown method on a known route becomes 405. Those httplib
  // answers itself, but for 404/405, may leave body bytes unread: their connection closes.
  http_->set_error_handler(httplib::Server::HandlerWithResponse([this](const httplib::Request& req, httplib::Response& res) {
    if (!res.body.empty()) return httplib::Server::HandlerResponse::Unhandled;
    if (RequestDeadlineExpired()) return AnswerRequestTimeout(res, /*stalled=*/false);
    if (RequestReadTimedOut()) return AnswerRequestTimeout(res, /*stalled=*/true);
    if (res.status != 404) {
      res.set_header("Connection", "close");
      CloseConnectionAfterResponse();
    }
    if (ChunkedBodyOverLimit()) res.status = 413;
    if (res.status == 404) {
      if (const auto* route = routes_->Find(req.path)) {
        // HEAD is answered wherever GET is (as GET without a body): Allow says so too.
        const std::string allowed = route->methods.find("GET") != std::string::npos ? route->methods + ", HEAD" : route->methods;
        res.set_header("Allow", allowed);
        SendError(res, MethodNotAllowed(req.method, req.path, allowed));
      } else {
        // Routes take no trailing slash ("/v1/images/" would be the image route with an empty id).
        const std::string trimmed = req.path.size() > 1 && req.path.back() == '/' ? req.path.substr(0, req.path.size() - 1) : "";
        const bool slash_added = !trimmed.empty() && routes_->Find(trimmed) != nullptr;
        SendError(res, RouteNotFound(req.method, LoggablePath(req.path), slash_added ? LoggablePath(trimmed) : ""));
      }
    } else if (res.status == 413 && !ChunkedBodyOverLimit() && IsFormEncoded(req)) {
      // The HTTP library reads at most 8 KiB of a form-encoded body, which no route takes: say what they
      // take instead of naming a size limit the body is under.
      SendError(res, HttpError{415, "unsupported_format",
                               "form-encoded bodies (application/x-www-form-urlencoded, what curl --data sends by "
                               "default) are not read: send an image as the raw body with its type (curl "
                               "--data-binary @photo.jpg -H 'Content-Type: image/jpeg') or as multipart/form-data "
                               "(curl -F image=@photo.jpg), and JSON with Content-Type: application/json"});
    } else if (res.status == 413) {
      SendError(res, HttpError{413, "payload_too_large", "request body over the server's limit of " +
                                                                  std::to_string(options_.max_body_bytes) +
                                                                  " bytes (oxbow serve --max-upload-mb)"});
    } else {
      SendError(res, HttpError{res.status, res.status >= 500 ? "internal" : "bad_request", UnreadBodyReason(req, res.status)});
    }
    return httplib::Server::HandlerResponse::Handled;
  }));

  http_->set_exception_handler([](const httplib::Request&, httplib::Response& res, const std::exception_ptr& ep) {
    std::string what = "unknown exception";
    try {
      if (ep) std::rethrow_exception(ep);
    } catch (const std::exception& e) {
      what = e.what();
    } catch (...) {
    }
    OXBOW_LOG(kError) << "http " << t_request.id << " internal error: " << what;
    SendError(res, HttpError{500, "internal", "internal error: " + what});
  });
}

std::optional<HttpError> AuthorizeCollection(const httplib::Request& req, const std::string& admin_key,
                                             const api::AccessKeys* keys, const std::string& collection,
                                             std::optional<bool> is_public, CollectionAccess access) {
  using Access = CollectionAccess;
  if (admin_key.empty()) {
    if (access != Access::kAdmin) return std::nullopt;
    return PermissionDenied("this route writes on the server's file system and is enabled only with an API key "
                            "(oxbow serve --api-key)");
  }
  const std::string key = PresentedKey(req);
  if (!key.empty() && ConstantTimeEquals(key, admin_key)) return std::nullopt;
  if (access == Access::kOpen) return std::nullopt;
  std::optional<HttpError> refused;
  std::string reason;
  if (access == Access::kAdmin) {
    reason = key.empty() ? "no key for an admin route" : "not the admin key, on an admin route";
    refused = key.empty() ? ToHttpError({ErrorCode::kUnauthenticated, "this route needs the admin API key: header "
                                                                      "'Authorization: Bearer KEY' or 'X-API-Key: KEY'"})
                          : PermissionDenied("this route needs the admin API key");
  } else {
    if (access == Access::kRead && is_public.value_or(false)) return std::nullopt;
    const auto granted = key.empty() || keys == nullptr ? std::nullopt : keys->Find(key);
    if (granted && granted->collection == collection && (access == Access::kRead || granted->access == api::KeyAccess::kWrite)) {
      return std::nullopt;
    }
    const std::string wanted = access == Access::kRead ? "read" : "write";
    if (key.empty()) {
      reason = "no key, to " + wanted + " collection '" + collection + "'";
      refused = ToHttpError({ErrorCode::kUnauthenticated, "this route needs a key that may " + wanted + " collection '" +
                                                              collection + "': header 'Authorization: Bearer KEY' or "
                                                              "'X-API-Key: KEY'"});
    } else {
      reason = granted ? "key " + granted->id + " (" + api::KeyAccessName(granted->access) + ", collection '" +
                             granted->collection + "') to " + wanted + " collection '" + collection + "'"
                       : "an unknown key, to " + wanted + " collection '" + collection + "'";
      refused = PermissionDenied("this key may not " + wanted + " collection '" + collection + "'");
    }
  }
  OXBOW_LOG(kWarning) << "http " << t_request.id << " refused " << req.method << " " << LoggablePath(req.path) << ": " << reason;
  return refused;
}

std::function<bool(const std::string& name, bool is_public)> CollectionListFilter(const httplib::Request& req,
                                                                                 const std::string& admin_key,
                                                                                 const api::AccessKeys* keys) {
  const std::string key = PresentedKey(req);
  const bool all = admin_key.empty() || (!key.empty() && ConstantTimeEquals(key, admin_key));
  const auto granted = all || key.empty() || keys == nullptr ? std::nullopt : keys->Find(key);
  return [all, granted](const std::string& name, bool is_public) {
    return all || is_public || (granted && granted->collection == name);
  };
}

void ServeCreateKey(api::AccessKeys& keys, const std::string& collection, const httplib::Request& req,
                    httplib::Response& res) {
  const json body = json::parse(req.body, nullptr, /*allow_exceptions=*/false);
  const auto access = body.is_object() && body.size() == 1 && body.contains("access") && body["access"].is_string()
                          ? api::ParseKeyAccess(body["access"].get<std::string>())
                          : std::nullopt;
  if (!access) {
    return SendError(res, Error{ErrorCode::kInvalidArgument, "POST .../keys takes {\"access\": \"read\"} or "
                                                             "{\"access\": \"write\"}"});
  }
  auto made = keys.Create(collection, *access);
  if (!made) return SendError(res, made.error());
  OXBOW_LOG(kInfo) << "http " << t_request.id << " made key " << made->info.id << " (" << api::KeyAccessName(*access)
                   << ") of collection '" << collection << "'";
  SendJson(res, 201, {{"key", made->key}, {"id", made->info.id}, {"collection", collection},
                      {"access", api::KeyAccessName(*access)}, {"created", made->info.created}});
}

void ServeListKeys(const api::AccessKeys& keys, const std::string& collection, httplib::Response& res) {
  json list = json::array();
  for (const auto& k : keys.List(collection)) {
    list.push_back({{"id", k.id}, {"access", api::KeyAccessName(k.access)}, {"created", k.created}});
  }
  SendJson(res, 200, {{"keys", list}});
}

void ServeDeleteKey(api::AccessKeys& keys, const std::string& collection, const std::string& id, httplib::Response& res) {
  if (auto s = keys.Delete(collection, id); !s) return SendError(res, s.error());
  OXBOW_LOG(kInfo) << "http " << t_request.id << " revoked key " << LoggablePath(id) << " of collection '" << collection << "'";
  SendJson(res, 200, {{"id", id}, {"deleted", true}});
}

std::optional<HttpError> HttpServer::Authorize(const httplib::Request& req, const std::string& collection,
                                               Access access) const {
  const auto set = collections();
  const auto found = set ? set->Find(collection) : std::nullopt;
  return AuthorizeCollection(req, options_.api_key, set ? set->keys() : nullptr, collection,
                             found ? std::optional(found->settings.is_public) : std::nullopt, access);
}

HttpServer::Handler HttpServer::ServiceRoute(Access access, ServiceHandler body) {
  return [this, access, body = std::move(body)](const httplib::Request& req, httplib::Response& res) {
    try {
      const auto set = collections();
      if (!set) {
        res.set_header("Retry-After", "5");
        SendError(res, Unavailable(shutting_down_ ? "shutting down" : "the index is still loading; retry shortly"));
        return;
      }
      // A match needs no collection: it extracts with the default collection's settings (else any one's).
      std::string name = access == Access::kOpen ? std::string(api::kDefaultCollection) : CollectionNameOfPath(req.path);
      if (access == Access::kOpen && !set->Find(name)) {
        const auto names = set->Names();
        if (!names.empty()) name = names.front();
      }
      if (auto refused = Authorize(req, name, access)) return SendError(res, *refused);
      auto found = set->Find(name);
      if (!found) {
        if (access == Access::kOpen) return SendError(res, Unavailable("the server holds no collection to extract with"));
        return SendError(res, ToHttpError({ErrorCode::kNotFound,
                                           "no collection named '" + name + "'" +
                                               (name == api::kDefaultCollection
                                                    ? " (the routes without /v1/collections/{name} act on it)"
                                                    : "")}));
      }
      if (access != Access::kOpen) t_request.collection = name;
      t_request.held = found;
      body(*found->service, req, res);
      t_request.held.reset();
    } catch (const std::exception& e) {
      t_request.held.reset();
      OXBOW_LOG(kError) << "http " << t_request.id << " internal error: " << e.what();
      SendError(res, HttpError{500, "internal", std::string("internal error: ") + e.what()});
    } catch (...) {
      t_request.held.reset();
      SendError(res, HttpError{500, "internal", "internal error"});
    }
  };
}

void HttpServer::Both(const std::string& method, const std::string& pattern, const Handler& handler) {
  // pattern starts with "/v1/"; the collection's route is /v1/collections/{name}/...
  const std::string prefixed = "/v1/collections/[^/]+" + pattern.substr(3);
  for (const std::string& p : {pattern, prefixed}) {
    if (method == "GET") http_->Get(p, handler);
    else if (method == "POST") http_->Post(p, handler);
    else if (method == "DELETE") http_->Delete(p, handler);
  }
}

void HttpServer::RegisterStatusRoutes() {
  auto& http = *http_;
  http.Get("/healthz", [](const httplib::Request&, httplib::Response& res) { SendJson(res, 200, {{"status", "ok"}}); });
  http.Get("/readyz", [this](const httplib::Request&, httplib::Response& res) {
    if (shutting_down_) {
      SendError(res, Unavailable("shutting down"));
    } else if (!ready()) {
      SendError(res, Unavailable("the index is still loading"));
    } else {
      SendJson(res, 200, {{"status", "ready"}});
    }
  });
  // The web page (server/web/), also while the index loads (it shows the 503s the API answers then).
  http.Get("/", [](const httplib::Request& req, httplib::Response& res) { SendWebAsset(req, res, "index.html"); });
  http.Get(R"(/static/(.+))", [](const httplib::Request& req, httplib::Response& res) {
    SendWebAsset(req, res, req.matches[1].str());
  });
  http.Get(R"(/v1/?)", [this](const httplib::Request&, httplib::Response& res) { DescribeApi(options_, *routes_, res); });
  http.Get("/v1/openapi.json", ServeOpenApi);
  http.Get("/metrics", [this](const httplib::Request&, httplib::Response& res) { ServeMetrics(res); });
}

void HttpServer::ServeMetrics(httplib::Response& res) const {
  std::vector<Gauge> gauges = {
      {"oxbow_ready", "1 when the index is loaded and the server is not shutting down.", ready() ? 1.0 : 0.0, ""},
      {"oxbow_process_resident_memory_bytes", "Resident memory of the process.",
       static_cast<double>(api::ResidentMemoryBytes()), ""}};
  if (auto set = collections()) {
    // One series per collection, each family's series together.
    std::vector<std::pair<std::string, api::ServiceStats>> stats;
    for (const std::string& name : set->Names()) {
      if (auto found = set->Find(name)) stats.emplace_back("collection=\"" + EscapeLabelValue(name) + "\"", found->service->Stats());
    }
    auto family = [&](const char* name, const char* help, auto value) {
      for (const auto& [labels, st] : stats) gauges.push_back({name, help, static_cast<double>(value(st)), labels});
    };
    using S = const api::ServiceStats&;
    family("oxbow_index_images", "Live images in the collection's index.", [](S st) { return st.index.num_images; });
    family("oxbow_index_features", "Indexed features.", [](S st) { return st.index.num_features; });
    family("oxbow_index_memory_bytes", "In-memory index (postings + geometry + tables).",
           [](S st) { return st.index.postings_bytes + st.index.geometry_bytes + st.index.other_bytes; });
    family("oxbow_vocabulary_words", "Visual words.", [](S st) { return st.index.vocabulary_size; });
    family("oxbow_extractions_in_flight", "Image decodes + extractions running now.", [](S st) { return st.extractions_in_flight; });
    family("oxbow_uptime_seconds", "Seconds since the index was opened.", [](S st) { return st.uptime_s; });
  }
  res.status = 200;
  std::string text = metrics_.Render(gauges);
  if (custom_routes_.metrics) text += custom_routes_.metrics();
  res.set_content(text, "text/plain; version=0.0.4");
}

void HttpServer::RegisterImageRoutes() {
  Both("POST", "/v1/images", ServiceRoute(Access::kWrite, PostImage));
  Both("POST", "/v1/images/batch", ServiceRoute(Access::kWrite, [this](api::Service& s, const httplib::Request& req,
                                                                     httplib::Response& res) {
         PostImageBatch(s, req, res, options_.max_batch_images);
       }));
  Both("GET", "/v1/images", ServiceRoute(Access::kRead, ListImages));
  Both("GET", R"(/v1/images/(.+))", ServiceRoute(Access::kRead, GetImageOrSubresource));
  Both("DELETE", R"(/v1/images/(.+))", ServiceRoute(Access::kWrite, DeleteImage));
  http_->Post("/v1/admin/backup", ServiceRoute(Access::kAdmin, PostBackup));
}

void HttpServer::RegisterSearchRoutes() {
  Both("POST", "/v1/search", ServiceRoute(Access::kRead, PostSearch));
  http_->Post("/v1/match", ServiceRoute(Access::kOpen, PostMatch));
}

namespace {

// POST .../duplicates's body (JSON, may be empty): the job's options.
Result<api::DuplicateOptions> ParseDuplicateOptions(const httplib::Request& req) {
  api::DuplicateOptions options;
  options.threads = 1;  // beside the server's requests
  if (auto known = api::CheckKnownParams(CollectParams(req, {}), {}); !known) return std::unexpected(known.error());
  if (req.body.empty()) return options;
  if (req.get_header_value("Content-Type").rfind("application/json", 0) != 0) {
    return Fail(ErrorCode::kInvalidArgument, "POST .../duplicates takes its options as a JSON body (Content-Type: "
                                               "application/json), or no body");
  }
  if (api::JsonNestingDepth(req.body) > api::kMaxJsonDepth) return Fail(ErrorCode::kInvalidArgument, "JSON body nests too deep");
  const json body = json::parse(req.body, nullptr, /*allow_exceptions=*/false);
  const std::string shape = "POST .../duplicates takes an empty body or a JSON object with any of \"candidates\" "
                            "(1-1000), \"mirrored\" (bool), \"min_coverage\", \"near_copy_coverage\" (0-1), "
                            "\"threads\" (0-256)";
  if (body.is_discarded() || !body.is_object()) return Fail(ErrorCode::kInvalidArgument, shape);
  for (const auto& [field, value] : body.items()) {
    if (field == "candidates" && value.is_number_integer()) {
      options.candidates = static_cast<int>(std::clamp<int64_t>(value.get<int64_t>(), -1, 100000));
    } else if (field == "mirrored" && value.is_boolean()) {
      options.mirrored = value.get<bool>();
    } else if (field == "min_coverage" && value.is_number()) {
      options.min_coverage = value.get<double>();
    } else if (field == "near_copy_coverage" && value.is_number()) {
      options.near_copy_coverage = value.get<double>();
    } else if (field == "threads" && value.is_number_integer()) {
      options.threads = static_cast<int>(std::clamp<int64_t>(value.get<int64_t>(), -1, 100000));
    } else {
      return Fail(ErrorCode::kInvalidArgument, "field '" + LoggablePath(field) + "' is unknown or of the wrong type; " + shape);
    }
  }
  if (auto message = options.Check()) return Fail(ErrorCode::kInvalidArgument, *message);
  return options;
}

// POST /v1/collections's body.
Result<api::CreateCollectionRequest> ParseCreateCollection(const httplib::Request& req) {
  if (api::JsonNestingDepth(req.body) > api::kMaxJsonDepth) {
    return Fail(ErrorCode::kInvalidArgument, "the JSON body nests deeper than " + std::to_string(api::kMaxJsonDepth) + " levels");
  }
  const json body = json::parse(req.body, nullptr, /*allow_exceptions=*/false);
  const std::string shape = "POST /v1/collections takes a JSON object: {\"name\": \"...\", \"vocabulary\": \"<path of a "
                            "vocabulary file on the server>\" or {\"like\": \"<collection>\"}, \"public\": false, "
                            "\"max_images\": null, \"max_bytes\": null}";
  if (body.is_discarded() || !body.is_object()) return Fail(ErrorCode::kInvalidArgument, shape);
  api::CreateCollectionRequest request;
  for (const auto& [field, value] : body.items()) {
    if (field == "name" && value.is_string()) {
      request.name = value.get<std::string>();
    } else if (field == "vocabulary" && value.is_string()) {
      request.vocabulary_path = value.get<std::string>();
    } else if (field == "vocabulary" && value.is_object() && value.size() == 1 && value.contains("like") &&
               value["like"].is_string()) {
      request.like = value["like"].get<std::string>();
    } else if (field == "public" && value.is_boolean()) {
      request.settings.is_public = value.get<bool>();
    } else if ((field == "max_images" || field == "max_bytes") && (value.is_null() || value.is_number_unsigned())) {
      auto& limit = field == "max_images" ? request.settings.max_images : request.settings.max_bytes;
      if (value.is_number_unsigned()) limit = value.get<uint64_t>();
    } else {
      return Fail(ErrorCode::kInvalidArgument, "field '" + LoggablePath(field) + "' is unknown or of the wrong type; " + shape);
    }
  }
  if (request.name.empty()) return Fail(ErrorCode::kInvalidArgument, shape);
  request.settings.is_public = body.value("public", false);  // created collections are private unless asked
  return request;
}

}  // namespace

void HttpServer::RegisterDuplicateRoutes() {
  Both("POST", "/v1/duplicates", ServiceRoute(Access::kWrite, [this](api::Service&, const httplib::Request& req,
                                                                    httplib::Response& res) {
         auto options = ParseDuplicateOptions(req);
         if (!options) return SendError(res, options.error());
         auto started = jobs_->Start(*t_request.held, *options);
         if (!started) return SendError(res, started.error());
         res.set_header("Location", "/v1/jobs/" + *started);
         SendJson(res, 202, {{"job", *started}, {"collection", t_request.held->name}, {"state", "running"}});
       }));
  // A job answers to the keys of its collection: read to follow it, write to cancel it.
  auto job_route = [this](Access access, std::function<void(const api::JobStatus&, httplib::Response&)> body) -> Handler {
    return [this, access, body = std::move(body)](const httplib::Request& req, httplib::Response& res) {
      const std::string id = req.matches[1];
      // Job ids are 64 random bits: an unknown one is 404 for every caller.
      const auto status = jobs_->Get(id);
      if (!status) return SendError(res, ToHttpError({ErrorCode::kNotFound, "no job with id '" + LoggablePath(id) + "'"}));
      if (auto refused = Authorize(req, status->collection, access)) return SendError(res, *refused);
      const std::string& collection = status->collection;
      t_request.collection = collection;
      body(*status, res);
    };
  };
  http_->Get(R"(/v1/jobs/([^/]+))", job_route(Access::kRead, [](const api::JobStatus& s, httplib::Response& res) {
    json body = {{"job", s.id}, {"collection", s.collection}, {"state", s.state}, {"done", s.done},
                 {"total", s.total}, {"elapsed_s", s.elapsed_s}};
    if (s.result) body["result"] = *s.result;
    if (s.error) body["error"] = ErrorBody(ToHttpError(*s.error), t_request.id)["error"];
    SendJson(res, 200, body);
  }));
  http_->Delete(R"(/v1/jobs/([^/]+))", job_route(Access::kWrite, [this](const api::JobStatus& s, httplib::Response& res) {
    const bool running = s.state == "running";
    jobs_->Cancel(s.id);
    SendJson(res, 200, {{"job", s.id}, {"cancelled", running}, {"deleted", true}});
  }));
}

void HttpServer::RegisterCollectionRoutes() {
  using CollectionHandler = std::function<void(api::Collections&, const std::string& name, const httplib::Request&,
                                               httplib::Response&)>;
  // Loading, the key check against the collection in the path (matches[1]; "" for the list) and errors.
  auto route = [this](Access access, CollectionHandler body) -> Handler {
    return [this, access, body = std::move(body)](const httplib::Request& req, httplib::Response& res) {
      try {
        const auto set = collections();
        if (!set) {
          res.set_header("Retry-After", "5");
          return SendError(res, Unavailable(shutting_down_ ? "shutting down" : "the index is still loading; retry shortly"));
        }
        const std::string name = req.matches.size() > 1 ? req.matches[1].str() : "";
        if (auto refused = Authorize(req, name, access)) return SendError(res, *refused);
        if (!name.empty() && set->Find(name)) t_request.collection = name;
        body(*set, name, req, res);
      } catch (const std::exception& e) {
        OXBOW_LOG(kError) << "http " << t_request.id << " internal error: " << e.what();
        SendError(res, HttpError{500, "internal", std::string("internal error: ") + e.what()});
      }
    };
  };
  auto& http = *http_;
  http.Get(R"(/v1/collections/?)", [this](const httplib::Request& req, httplib::Response& res) {
    const auto set = collections();
    if (!set) return SendError(res, Unavailable(shutting_down_ ? "shutting down" : "the index is still loading; retry shortly"));
    // The collections the caller may read: all with the admin key or on a server without one; else the
    // public ones and the one its key belongs to.
    const auto shown = CollectionListFilter(req, options_.api_key, set->keys());
    json list = json::array();
    for (const std::string& name : set->Names()) {
      auto info = set->Describe(name);
      if (!info) continue;  // deleted meanwhile
      if (shown(name, info->settings.is_public)) list.push_back(api::CollectionToJson(*info, false));
    }
    SendJson(res, 200, {{"collections", list}});
  });
  http.Post(R"(/v1/collections/?)", route(Access::kAdmin, [](api::Collections& set, const std::string&,
                                                              const httplib::Request& req, httplib::Response& res) {
    auto request = ParseCreateCollection(req);
    if (!request) return SendError(res, request.error());
    auto created = set.Create(*request);
    if (!created) return SendError(res, created.error());
    t_request.collection = request->name;
    res.set_header("Location", "/v1/collections/" + request->name);
    SendJson(res, 201, api::CollectionToJson(*created, false));
  }));
  http.Get(R"(/v1/collections/([^/]+))", route(Access::kRead, [](api::Collections& set, const std::string& name,
                                                                 const httplib::Request&, httplib::Response& res) {
    auto info = set.Describe(name);
    if (!info) return SendError(res, info.error());
    SendJson(res, 200, api::CollectionToJson(*info, true));
  }));
  http.Delete(R"(/v1/collections/([^/]+))", route(Access::kAdmin, [this](api::Collections& set, const std::string& name,
                                                                     const httplib::Request&, httplib::Response& res) {
    jobs_->CancelCollection(name);
    if (auto s = set.Delete(name); !s) return SendError(res, s.error());
    SendJson(res, 200, {{"name", name}, {"deleted", true}});
  }));
  // Keys: the admin's. A set without a data folder (--index) has none to manage.
  auto keys_of = [](api::Collections& set, const std::string& name, httplib::Response& res) -> api::AccessKeys* {
    if (set.keys() == nullptr) {
      SendError(res, ToHttpError({ErrorCode::kIncompatible, "this server serves one index folder (--index) and has no "
                                                            "collection keys; start it with --data DIR"}));
      return nullptr;
    }
    if (!set.Find(name)) {
      SendError(res, ToHttpError({ErrorCode::kNotFound, "no collection named '" + name + "'"}));
      return nullptr;
    }
    return set.keys();
  };
  http.Post(R"(/v1/collections/([^/]+)/keys)", route(Access::kAdmin, [keys_of](api::Collections& set, const std::string& name,
                                                                                const httplib::Request& req, httplib::Response& res) {
    api::AccessKeys* keys = keys_of(set, name, res);
    if (keys != nullptr) ServeCreateKey(*keys, name, req, res);
  }));
  http.Get(R"(/v1/collections/([^/]+)/keys)", route(Access::kAdmin, [keys_of](api::Collections& set, const std::string& name,
                                                                               const httplib::Request&, httplib::Response& res) {
    api::AccessKeys* keys = keys_of(set, name, res);
    if (keys != nullptr) ServeListKeys(*keys, name, res);
  }));
  http.Delete(R"(/v1/collections/([^/]+)/keys/([^/]+))", route(Access::kAdmin, [keys_of](api::Collections& set,
                                                                                          const std::string& name,
                                                                                          const httplib::Request& req,
                                                                                          httplib::Response& res) {
    api::AccessKeys* keys = keys_of(set, name, res);
    if (keys != nullptr) ServeDeleteKey(*keys, name, req.matches[2], res);
  }));
  http.Post(R"(/v1/collections/([^/]+)/backup)", route(Access::kAdmin, [](api::Collections& set, const std::string& name,
                                                                         const httplib::Request& req, httplib::Response& res) {
    auto out = BackupFolderParam(req);
    if (!out) return SendError(res, out.error());
    auto done = set.Backup(name, *out);
    if (!done) return SendError(res, done.error());
    SendJson(res, 200, api::BackupToJson(*out, *done));
  }));
}

}  // namespace oxbow::server
