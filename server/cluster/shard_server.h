// The gRPC side of a cluster shard (shard.proto): an `oxbow serve --index CLUSTER/partition-k` (or
// `--data DIR`, whose DIR/<name>/ holds partition k of collection <name>) started with --grpc-port also
// answers the front's calls (Score, Verify, RegionTerms for a search; Get, List,
// Stats, Features for reads; Ping, Add, Delete for writes, which go to its api::Service and its checks
// as its own HTTP API's do), plus the standard gRPC health check (grpc.health.v1.Health, "" and
// "oxbow.cluster.Shard": SERVING once the index is loaded, NOT_SERVING before and while stopping).
// Every call but the health check needs the cluster key when one is set, and the port may speak TLS
// (transport_security.h).
#pragma once

#include <memory>
#include <string>

#include "api/collections.h"
#include "api/service.h"
#include "server/cluster/transport_security.h"
#include "sift/base/error.h"

namespace grpc {
class Server;
}

namespace oxbow::cluster {

struct ShardServerOptions {
  ShardSecurity security;
  // The largest message a call may carry, bytes: an Add holds the image, so the shard's largest upload
  // (serve --max-upload-mb) plus room for the id and metadata. Larger calls fail with
  // RESOURCE_EXHAUSTED before they reach the index.
  uint64_t max_message_bytes = 64ull << 20;
};

class ShardServer {
 public:
  ShardServer();
  ~ShardServer();  // stops serving
  ShardServer(const ShardServer&) = delete;
  ShardServer& operator=(const ShardServer&) = delete;

  // Listens on host:port (0 picks a free port) and returns the bound port; calls fail with UNAVAILABLE
  // until SetService. kIoError when the address cannot be bound; kInvalidArgument for a host beyond
  // loopback without a cluster key, or for unusable security options (a TLS file: kNotFound).
  [[nodiscard]] Result<int> Start(const std::string& host, int port, const ShardServerOptions& options = {});
  // The index finished loading: serve it as the collection "default".
  void SetService(std::shared_ptr<api::Service> service);
  // The collections finished loading (serve --data): serve them; a call names its collection in its
  // metadata (kCollectionKey in proto_convert.h; "default" when it names none). A collection this shard
  // does not hold is refused as not found.
  void SetCollections(std::shared_ptr<api::Collections> collections);
  // Stops accepting calls and waits for those running. Idempotent.
  void Shutdown();

  class Impl;

 private:
  std::unique_ptr<Impl> impl_;
  std::unique_ptr<grpc::Server> server_;
};

}  // namespace oxbow::cluster
