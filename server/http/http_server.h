// The HTTP JSON server: cpp-httplib routes over api::Service (see server/README.md, "HTTP API",
// for every route, parameter and response).
//
// Behaviour:
//  - Requests are handled by `threads` workers fed from a bounded queue of accepted connections. When
//    `max_queued_connections` connections already wait, or the client's address already has
//    `max_connections_per_client` open, a new one is answered 503 (JSON, Retry-After) by a separate
//    shedding thread instead of queueing without bound (server/http/request_guard.h).
//  - Request heads are checked before httplib parses them (header count and bytes, strict framing, no
//    compressed bodies); a refused request is answered at once and its connection closed.
//  - The index is opened in the background (SetService); until then /healthz answers 200 and /readyz
//    and the /v1 routes answer 503, so a supervisor sees the process alive while a large index loads.
//  - Searches never wait for writes (ImageIndex snapshots); this class adds no lock around the index.
//  - Every response to an error has the body {"error": {"code", "message", "request_id"}}, including
//    unknown routes (404), wrong methods (405), oversized bodies (413) and exceptions (500).
//  - Every request gets an id (the client's X-Request-Id when it is 1..64 of [A-Za-z0-9._-], else a new
//    random one), echoed in the X-Request-Id response header, and one log line (sift/log.h):
//      http <id> <method> <path> route=<pattern> status=<code> ms=<latency> [stage timings]
//  - Collections (api/collections.h): every image and search route also exists under
//    /v1/collections/{name}/..., acting on that collection; the routes without the prefix act on the
//    collection "default". /v1/collections manages them (create, list, describe, delete, keys, backup).
//  - Keys, in `Authorization: Bearer KEY` or `X-API-Key: KEY` (compared in constant time). With an admin
//    key (options.api_key): it grants everything; a collection's write key (api/access_keys.h) grants
//    its image writes and reads, a read key its reads; reads of a public collection need no key. A
//    request without the key it needs -> 401; with a key that does not grant it -> 403, with the same
//    answer whether or not the collection exists (only the admin key gets 404 for an unknown
//    collection). Every refusal is logged with its request id. Without an admin key every image and
//    search route is open, and the routes that create or delete collections or keys or write a backup
//    are refused (403): they write on the server's machine.
//  - An add to a collection at its limits (images, bytes on disk) -> 507.
//  - POST /v1/collections/{name}/duplicates (write access) starts a duplicate search as a background job
//    (api/duplicate_jobs.h): 202 with its id; GET /v1/jobs/{job} (read access to its collection) its
//    progress and result, DELETE cancels it.
//  - Shutdown() (from the SIGTERM/SIGINT handler) stops accepting, lets in-flight requests finish but
//    abandons decodes and extractions still running after the service's shutdown grace (their requests
//    get 503, nothing stored: api::Service::StopExtractions), and returns from Run(); the index's state
//    is durable after every acknowledged write.
//  - A search, add or match whose client closes its connection is abandoned at the extractor's next
//    check (its extraction slot freed for others, nothing stored).
//
// Thread safety: SetService, Shutdown, port and ready may be called from any thread; Run from one.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include <nlohmann/json_fwd.hpp>

#include "server/http/errors.h"
#include "server/http/metrics.h"
#include "api/collections.h"
#include "api/params.h"
#include "api/service.h"
#include "sift/base/error.h"
#include "sift/sift.h"

namespace httplib {
class Server;
struct Request;
struct Response;
}

namespace oxbow::api {
class DuplicateJobs;
}

namespace oxbow::server {
class UploadBudget;
struct RefusedRequest;
}

namespace oxbow::server {

struct HttpServerOptions {
  // Address to bind. The loopback default keeps the server private; use 0.0.0.0 to expose it
  // (then set an API key).
  std::string host = "127.0.0.1";
  // TCP port, [0, 65535]; 0 picks a free port (Bind returns it).
  int port = 8080;
  // Worker threads serving connections (each handles one request at a time), [1, 1024].
  int threads = 8;
  // Accepted connections waiting for a worker at most; beyond it new connections get 503. [1, 100000].
  int max_queued_connections = 64;
  // The admin key; when non-empty, writes require it or a collection's write key (see the file comment).
  std::string api_key;
  // Largest request body, bytes (multipart included); over it -> 413. [1, 2^32].
  uint64_t max_body_bytes = 32ull << 20;
  // Socket read / write timeouts per operation, seconds, [1, 3600]: a client that stops sending or
  // reading for this long is disconnected.
  int read_timeout_s = 30;
  int write_timeout_s = 30;
  // Idle keep-alive connections are closed after this many seconds, [1, 3600]; and after
  // keep_alive_max_requests requests, [1, 100000].
  int keep_alive_timeout_s = 5;
  int keep_alive_max_requests = 1000;
  // Slow-client protection (server/request_guard.h). A request's headers and body must arrive within this
  // many seconds of its first byte, however slowly they trickle; a body that misses it is answered 408,
  // headers that miss it get the connection closed. [1, 3600].
  int request_timeout_s = 60;
  // Request bodies held in memory by all requests together, bytes: a request reserves its Content-Length
  // before its body is read; one that does not fit is answered 503 (Retry-After) without reading it.
  // [max_body_bytes, 2^40].
  uint64_t max_inflight_body_bytes = 256ull << 20;
  // Request headers at most, [1, 10000], and request line + headers, bytes, [1024, 2^24]; over -> 431.
  int max_header_count = 100;
  size_t max_head_bytes = 64u << 10;
  // Open connections from one client address at most (served, queued or being refused); over -> 503.
  // [1, 100000].
  int max_connections_per_client = 64;
  // Images in one POST /v1/images/batch at most; more -> 413, nothing stored. [1, 10000]. The whole
  // request also counts against max_body_bytes.
  int max_batch_images = 64;

  std::optional<std::string> Check() const;
};

// A route known to the server's route table: the label of its requests in log lines and metrics
// (route=...), and the methods of a 405 answer and of GET /v1's list. A request matching no route of
// the table is labelled "unmatched".
struct RouteInfo {
  std::string label;    // "/v1/images/{id}"
  std::string pattern;  // ECMAScript regex matching the whole decoded path: "/v1/images/.+"
  std::string methods;  // "GET, DELETE"
};

// The /v1 routes of a server that is not one index (the cluster front, server/cluster/front_http.h),
// served by HttpServer in place of the single node's, behind the same guards (request timeout, upload
// budget, connection limits, strict request heads), request ids, log lines, HTTP metrics, JSON error
// bodies and status routes (/healthz, /readyz, /metrics, /v1, the web page). Such a server has no
// api::Service: it is ready from the start.
// What a route needs of the collection it addresses (the file comment). kOpen: no collection (match),
// any key; kAdmin: the admin key, refused when the server has none.
enum class CollectionAccess { kOpen, kRead, kWrite, kAdmin };

struct CustomRoutes {
  // Registers the routes, /v1/stats included. Handlers answer errors with SendJsonError (below).
  std::function<void(httplib::Server&)> add;
  // More Prometheus text for /metrics (HELP/TYPE lines included); may be empty.
  std::function<std::string()> metrics;
  // The routes `add` registers beyond the single node's (which the table always holds), matched first.
  std::vector<RouteInfo> more_routes;
};

class HttpServer {
 public:
  explicit HttpServer(const HttpServerOptions& options);
  HttpServer(const HttpServerOptions& options, CustomRoutes routes);
  ~HttpServer();
  HttpServer(const HttpServer&) = delete;
  HttpServer& operator=(const HttpServer&) = delete;

  // Binds the listening socket; returns the bound port. kInvalidArgument for bad options, kIoError
  // when the address cannot be bound.
  [[nodiscard]] Result<int> Bind();
  // Serves until Shutdown(); returns after in-flight requests finished. Call after Bind().
  void Run();
  // Stops accepting and makes Run() return once in-flight requests are done. Idempotent.
  void Shutdown();

  // Makes the service available to the routes as the collection "default" (the index finished loading).
  void SetService(std::shared_ptr<api::Service> service);
  // Makes the collections available to the routes (oxbow serve --data: they finished loading).
  void SetCollections(std::shared_ptr<api::Collections> collections);
  bool ready() const;
  int port() const { return port_; }

  struct RouteTable;

 private:
  using Access = CollectionAccess;
  using Handler = std::function<void(const httplib::Request&, httplib::Response&)>;
  using ServiceHandler = std::function<void(api::Service&, const httplib::Request&, httplib::Response&)>;

  void RegisterRoutes();
  void RegisterRequestHooks();   // request id, load shedding, upload budget; the log line and metrics
  void RegisterErrorHandlers();  // JSON error bodies for unhandled statuses and exceptions
  void RegisterStatusRoutes();   // health, readiness, metrics, stats, API description, web page
  void RegisterImageRoutes();
  void RegisterSearchRoutes();
  // Wraps a route body: catches everything, answers 503 while the index loads, checks the key against
  // the collection the path names, answers 404 for an unknown one.
  Handler ServiceRoute(Access access, ServiceHandler body);
  // Registers `handler` for `pattern` ("/v1/images...") and for the same under /v1/collections/{name}.
  void Both(const std::string& method, const std::string& pattern, const Handler& handler);
  // Why the request may not have `access` to `collection` (an unknown one is refused as a private one
  // unless the caller holds the admin key); nullopt when it may. Logs refusals.
  std::optional<HttpError> Authorize(const httplib::Request& req, const std::string& collection, Access access) const;
  void RegisterCollectionRoutes();
  void RegisterDuplicateRoutes();  // duplicate searches as jobs (api/duplicate_jobs.h)
  void ServeMetrics(httplib::Response& res) const;
  // The JSON answer, log line and metrics of a request refused before httplib parsed it.
  void AnswerRefusal(const RefusedRequest& refused, httplib::Response& res);
  // The one log line and the metrics of a request: "http <id> <method> <path> route=<r> status=<s> ms=<ms>
  // <stage>=<ms>...", or "... refused: <refusal>" for one refused before it was read.
  void LogRequest(const std::string& id, const std::string& method, const std::string& path, const std::string& route,
                  int status, double seconds, const std::vector<std::pair<const char*, double>>& stages,
                  const std::string& refusal);
  std::shared_ptr<api::Collections> collections() const;

  HttpServerOptions options_;
  CustomRoutes custom_routes_;  // set: serves these instead of a service's routes
  std::unique_ptr<const RouteTable> routes_;  // custom_routes_.more_routes, then the single node's
  std::unique_ptr<UploadBudget> upload_budget_;  // declared before http_, which uses it
  std::unique_ptr<httplib::Server> http_;
  Metrics metrics_;
  mutable std::mutex service_mutex_;           // guards collections_ (pointer copy only)
  std::shared_ptr<api::Collections> collections_;
  std::unique_ptr<api::DuplicateJobs> jobs_;  // declared after collections_: destroyed (joined) first
  std::atomic<bool> shutting_down_{false};
  int port_ = 0;
};

// ---- For route handlers, the single node's and CustomRoutes' (the request is the one this thread serves).
// A JSON answer, and an error body ({"error": {"code", "message", "request_id"}}, WWW-Authenticate on a 401).
void SendJsonAnswer(httplib::Response& res, int status, const nlohmann::json& body);
void SendJsonError(httplib::Response& res, const HttpError& error);
// Stage timings, ms: a Server-Timing header and the request's log line.
void RecordStages(httplib::Response& res, const std::vector<std::pair<const char*, double>>& stages);
// Query-string parameters plus multipart text parts (every part but `file_fields`), every occurrence, so
// that the api/params.h parsers refuse a name given twice; a repeated image part enters as a repeated
// parameter without its bytes.
api::Params CollectParams(const httplib::Request& req, const std::vector<std::string>& file_fields);
// The image of a request: the multipart part `field` (or `alt_field`; its file name in `filename`), else
// the raw body. 415 for a JSON or text body, 400 for an empty one or a multipart request without it.
Result<std::string_view> RequestImage(const httplib::Request& req, const std::string& field,
                                      const std::string& alt_field, std::string* filename);
// A request body's bytes as the api takes them (not owned).
std::span<const uint8_t> Bytes(std::string_view text);
// The add that POST /v1/images asks for, the same on a single node and a cluster front: its parameters,
// the image's bytes (not owned) and, as its source, "http" or "http:" + the multipart file name.
api::AddImageRequest AddImageRequestOf(const api::AddParams& params, std::string_view image,
                                       const std::string& filename);
// GET /v1/images/{id}, {id}/similar and {id}/thumbnail told apart on the request target as the client
// sent it (route pattern /v1/images/(.+)): a slash sent encoded (%2F) belongs to the id. `sub` is "",
// "similar" or "thumbnail".
struct ImagePath {
  std::string id;
  std::string sub;
};
ImagePath ImagePathOf(const httplib::Request& req);
// The Location of an added image: `prefix` + "/images/" + the id with every byte but RFC 3986's unreserved
// ones percent-encoded (a '/', '?', '#', space or non-ASCII byte of the id stays part of it), the path
// ImagePathOf reads back as that id.
std::string ImageLocation(std::string_view prefix, std::string_view id);
// GET .../thumbnail's `size` parameter: [api::kMinThumbnailPx, api::kMaxThumbnailPx], default 256.
Result<int> ThumbnailSizeParam(const httplib::Request& req);
// A JPEG thumbnail with a strong ETag (304 when the client holds it).
void SendThumbnail(const httplib::Request& req, httplib::Response& res, const std::string& jpeg);
// True once the client of the request this thread serves has closed its connection (for an extraction
// to stop at its next check).
sift::StopRequested ClientGone();
// POST /v1/match: multipart parts 'a' and 'b' and api::ParseMatchParams' parameters; `match_pair`
// decodes, extracts and matches the two images.
using PairMatcher = std::function<Result<api::MatchResponse>(std::span<const uint8_t> a, std::span<const uint8_t> b,
                                                             const api::PairMatchOptions& options)>;
void ServeMatch(const httplib::Request& req, httplib::Response& res, const PairMatcher& match_pair);
// POST /v1/images/batch: multipart parts `image` (the images, in order), `id` (one per image, same
// order), `metadata` (none or one per image; api::ParseBatchAddParams), at most `max_images`. `add` gets
// the images that passed those checks (as api::Service::AddImages). 200 with one result per image, or,
// when the whole batch failed (catalogue, client gone, shutdown), that error's status with the error
// body plus the per-image results.
using BatchAdder = std::function<Result<api::AddBatchResponse>(api::AddBatchRequest& batch)>;
void ServeImageBatch(const httplib::Request& req, httplib::Response& res, int max_images, const BatchAdder& add);
// POST /v1/admin/backup's folder: JSON {"out": "/abs/path"} or the parameter out; must be absolute.
Result<std::string> BackupFolderParam(const httplib::Request& req);

// Whether the request may have `access` to `collection` under the file comment's rules (the single node's
// and the cluster front's): nullopt when it may, else the 401 or 403 answer, logged with the request id.
// `admin_key` "" = none; `keys` (may be null) the collections' keys; `is_public` the collection's setting,
// nullopt for a collection that does not exist (refused as a private one: only the admin key passes).
std::optional<HttpError> AuthorizeCollection(const httplib::Request& req, const std::string& admin_key,
                                             const api::AccessKeys* keys, const std::string& collection,
                                             std::optional<bool> is_public, CollectionAccess access);
// Which collections GET /v1/collections shows the request: all with the admin key (or on a server without
// one), else the public ones and the one its key belongs to.
std::function<bool(const std::string& name, bool is_public)> CollectionListFilter(const httplib::Request& req,
                                                                                 const std::string& admin_key,
                                                                                 const api::AccessKeys* keys);
// The admin's key routes of a collection: POST .../keys {"access": "read"|"write"} (201 with the key,
// shown once), GET .../keys, DELETE .../keys/{id}.
void ServeCreateKey(api::AccessKeys& keys, const std::string& collection, const httplib::Request& req,
                    httplib::Response& res);
void ServeListKeys(const api::AccessKeys& keys, const std::string& collection, httplib::Response& res);
void ServeDeleteKey(api::AccessKeys& keys, const std::string& collection, const std::string& id, httplib::Response& res);
// The collection a path addresses: NAME for /v1/collections/NAME/..., else "default".
std::string CollectionOfPath(std::string_view path);
// The collection the request this thread serves acts on: its log line's field and its metrics' label.
void NoteCollection(const std::string& collection);

// True when `given` equals `expected`; the time taken depends only on their lengths.
bool ConstantTimeEquals(const std::string& given, const std::string& expected);
// curl --data-binary @photo.jpg without -H 'Content-Type: ...' labels the photo
// application/x-www-form-urlencoded. httplib 0.11 would then cap the body at 8 KiB (413) and parse it
// as form fields, so on the routes taking raw image bytes (POST /v1/images and /v1/search) such a body
// is relabelled application/octet-stream before it is read: the decoder decides whether it is an image.
// For a pre-routing handler (also the cluster front's).
void TakeFormEncodedBodyAsImage(const httplib::Request& req);
// The request's id: the client's X-Request-Id when 1-64 characters of [A-Za-z0-9._-], else a new one.
std::string RequestIdFor(const httplib::Request& req);
// A write route's key check (also the cluster front's): nullopt when `api_key` is empty or the request
// carries it ('Authorization: Bearer KEY' or 'X-API-Key: KEY'), else 401 without a key, 403 with another.
std::optional<HttpError> CheckApiKey(const httplib::Request& req, const std::string& api_key);

}  // namespace oxbow::server
