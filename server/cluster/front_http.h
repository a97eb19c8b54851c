// The HTTP side of a cluster front (`oxbow serve --cluster cluster.json`): the public API's search over
// a ClusterFront (front.h). Served so far: POST /v1/search (the image as the raw body, or the multipart
// part "file"/"image"; the same parameters as a single node, api/params.h, plus allow_partial=true|false,
// default true: with a partition down the answer is 200 with "partial": true, else 503; every answer has
// "partial" and "shards": {"total", "ok", "failed": [partition, ...]}), GET /healthz, GET /readyz
// and GET /metrics (per shard replica: calls, errors, latency). Every other /v1 route answers 501
// {"error": {"code": "not_implemented", ...}}: writes, get, list and stats through a front are not
// served yet (README "Serving a cluster").
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
