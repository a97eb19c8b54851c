// The HTTP side of a cluster front (`oxbow serve --cluster cluster.json`): the public API over a
// ClusterFront (front.h) per collection, served by server::HttpServer (its CustomRoutes), so that the
// front has the single node's guards (request timeout, upload budget, connection limits, strict request
// heads), request ids, log lines, HTTP metrics, error bodies and status routes, and the single node's
// parameters (api/params.h), answers (api/json.h) and key rules (server::AuthorizeCollection):
//   Every route below exists for the collection "default" (/v1/...) and for each collection of
//   cluster.json (/v1/collections/{name}/...); an unknown collection is 404 (to the admin key; others
//   get the 401/403 of a private collection).
//   POST /v1/search, GET /v1/images/{id}/similar: plus allow_partial=true|false, default true: with a
//     partition down the answer is 200 with "partial": true, else 503; every answer has "partial" and
//     "shards": {"total", "ok", "failed": [partition, ...]}. The image as the raw body or the multipart
//     part "file"/"image". The front decodes and extracts it under api::Extractions (slots, processing
//     deadline, client gone, shutdown grace) with the collection's extractor settings, as a single node does.
//   POST /v1/match: at the front (it needs no index), under the same extraction limits.
//   GET /v1/images/{id}, {id}/thumbnail: asked of the owner partition.
//   GET /v1/images (list), GET /v1/stats (sums over the partitions).
//   POST /v1/images, POST /v1/images/batch, DELETE /v1/images/{id}: on every replica of the owner
//     partition, or 503 (front.h); a batch's images one at a time per partition. The collection's limits
//     (cluster.json "max_images", "max_bytes": over every partition) answer 507 before anything is sent.
//   POST /v1/admin/backup, /v1/collections/{name}/backup: every partition into out/partition-k on its
//     replica's machine (front.h).
//   POST /v1/admin/refresh-statistics (front only).
//   GET /v1/collections (those the caller may read), GET /v1/collections/{name} (settings and the
//     partitions' summed stats); POST/GET /v1/collections/{name}/keys, DELETE .../keys/{id} (admin key;
//     cluster.json "collection_keys"). POST /v1/collections and DELETE /v1/collections/{name} answer
//     409: a cluster's collections are those cluster.json names.
//   GET /metrics: the HTTP metrics (with a collection label) plus, per collection and shard replica,
//     calls, errors, latency, write sequence and whether it is behind.
#pragma once

#include <memory>
#include <vector>

#include "api/access_keys.h"
#include "api/collections.h"
#include "api/service.h"
#include "server/cluster/front.h"
#include "server/http/http_server.h"
#include "sift/base/error.h"

namespace oxbow::cluster {

struct FrontHttpOptions {
  server::HttpServerOptions http;  // address, workers, guards, API key: as a single node's
  // Extraction limits and threads (ServiceOptions::Extraction, threads_per_request), the upload limits
  // and the default query: as a single node's. Index-only fields (thumbnails, add_nice) are not used.
  api::ServiceOptions service;
};

// One collection of the front: its ClusterFront (front->collection() names it) and settings.
struct FrontCollection {
  std::shared_ptr<const ClusterFront> front;
  api::CollectionSettings settings;
};

class FrontHttpServer {
 public:
  // Serves `collections` (at least one; each extracts queries as its vocabulary was made, its extractor
  // settings) with the collection keys `keys` (null: none). kInvalidArgument for settings it cannot read,
  // a collection given twice, or invalid options.
  [[nodiscard]] static Result<std::unique_ptr<FrontHttpServer>> Create(std::vector<FrontCollection> collections,
                                                                       std::unique_ptr<api::AccessKeys> keys,
                                                                       const FrontHttpOptions& options);
  // One collection ("default" for a front opened so), public, without keys.
  [[nodiscard]] static Result<std::unique_ptr<FrontHttpServer>> Create(std::shared_ptr<const ClusterFront> front,
                                                                       const FrontHttpOptions& options);
  ~FrontHttpServer();
  FrontHttpServer(const FrontHttpServer&) = delete;
  FrontHttpServer& operator=(const FrontHttpServer&) = delete;

  [[nodiscard]] Result<int> Bind();  // the bound port; kIoError when the address cannot be bound
  void Run();                        // until Shutdown()
  void Shutdown();                   // also stops extractions after the shutdown grace (503)

  class Impl;

 private:
  explicit FrontHttpServer(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace oxbow::cluster
