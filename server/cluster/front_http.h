// The HTTP side of a cluster front (`oxbow serve --cluster cluster.json`): the public API over a
// ClusterFront (front.h), with a single node's parameters (api/params.h) and answers (api/json.h):
//   POST /v1/search, GET /v1/images/{id}/similar: plus allow_partial=true|false, default true: with a
//     partition down the answer is 200 with "partial": true, else 503; every answer has "partial" and
//     "shards": {"total", "ok", "failed": [partition, ...]}. The image as the raw body or the multipart
//     part "file"/"image".
//   GET /v1/images/{id}, GET /v1/images (list), GET /v1/stats (sums over the partitions).
//   POST /v1/images, DELETE /v1/images/{id}: on every replica of the owner partition, or 503 (front.h);
//     the API key (FrontHttpOptions::api_key) as a single node asks for it.
//   GET /healthz, GET /readyz, GET /metrics (per shard replica: calls, errors, latency).
// Every other /v1 route (batch add, thumbnails, match, backup) answers 501
// {"error": {"code": "not_implemented", ...}} (README "Serving a cluster").
#pragma once

#include <memory>
#include <string>

#include "api/service.h"
#include "index/image_index.h"
#include "server/cluster/front.h"
#include "sift/base/error.h"
#include "sift/image.h"

namespace httplib {
class Server;
}

namespace oxbow::cluster {

struct FrontHttpOptions {
  std::string host = "127.0.0.1";
  int port = 8080;                      // 0 picks a free one
  int threads = 8;                      // requests served at once
  uint64_t max_body_bytes = 32ull << 20;  // larger uploads: 413
  sift::DecodeOptions decode;           // limits of the uploaded image
  int threads_per_request = api::ServiceOptions{}.threads_per_request;  // extraction threads; 0 = all cores
  index::QueryOptions default_query;    // a search's own parameters override these
  std::string api_key;                  // when set, writes need it (server::CheckApiKey)
};

class FrontHttpServer {
 public:
  // Extracts queries as the cluster's vocabulary was made (its extractor settings). kInvalidArgument
  // for settings it cannot read.
  [[nodiscard]] static Result<std::unique_ptr<FrontHttpServer>> Create(std::shared_ptr<const ClusterFront> front,
                                                                       const FrontHttpOptions& options);
  ~FrontHttpServer();
  FrontHttpServer(const FrontHttpServer&) = delete;
  FrontHttpServer& operator=(const FrontHttpServer&) = delete;

  [[nodiscard]] Result<int> Bind();  // the bound port; kIoError when the address cannot be bound
  void Run();                        // until Shutdown()
  void Shutdown();

  class Impl;

 private:
  explicit FrontHttpServer(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace oxbow::cluster
