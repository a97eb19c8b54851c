// The gRPC side of a cluster shard (shard.proto): an `oxbow serve --index CLUSTER/partition-k` started
// with --grpc-port also answers the front's calls (Score, Verify, RegionTerms for a search; Get, List,
// Stats, Features for reads; Ping, Add, Delete for writes, which go to its api::Service as its own HTTP
// API's do, without its API key: the gRPC port is for the cluster's network only), plus the
// standard gRPC health check (grpc.health.v1.Health, "" and "oxbow.cluster.Shard": SERVING once the
// index is loaded, NOT_SERVING before and while stopping).
#pragma once

#include <memory>
#include <string>

#include "api/service.h"
#include "sift/base/error.h"

namespace grpc {
class Server;
}

namespace oxbow::cluster {

class ShardServer {
 public:
  ShardServer();
  ~ShardServer();  // stops serving
  ShardServer(const ShardServer&) = delete;
  ShardServer& operator=(const ShardServer&) = delete;

  // Listens on host:port (0 picks a free port) and returns the bound port; calls fail with UNAVAILABLE
  // until SetService. kIoError when the address cannot be bound.
  [[nodiscard]] Result<int> Start(const std::string& host, int port);
  // The index finished loading: serve it.
  void SetService(std::shared_ptr<api::Service> service);
  // Stops accepting calls and waits for those running. Idempotent.
  void Shutdown();

  class Impl;

 private:
  std::unique_ptr<Impl> impl_;
  std::unique_ptr<grpc::Server> server_;
};

}  // namespace oxbow::cluster
