// The functions of liboxbow_cluster.so (cluster_module.cc): `serve --cluster` (a cluster's front) and
// `serve --grpc-port` (a shard's gRPC API), the only commands that need gRPC and protobuf, so that the
// binary does not link them (module_loader.h says why). The module resolves oxbow's own functions in the
// binary that loads it (the binary exports them), so the types below cross the boundary as they are.
#pragma once

#include <signal.h>

#include <memory>
#include <string>

#include "api/collections.h"
#include "api/service.h"
#include "server/cluster/front.h"
#include "server/cluster/transport_security.h"
#include "server/http/http_server.h"
#include "sift/base/error.h"

namespace oxbow::cli {

// Bumped whenever a member changes: a module of another version is refused.
inline constexpr int kClusterApiVersion = 2;

// `serve --cluster`: what the command line gives the front.
struct FrontArgs {
  std::string cluster_file;  // cluster.json
  std::string cluster_key;   // --cluster-key; "" = cluster.json's key_file, else http.api_key
  cluster::FrontOptions front;
  server::HttpServerOptions http;
  api::ServiceOptions service;
};

// A shard's gRPC server (cluster::ShardServer).
class ShardApi {
 public:
  virtual ~ShardApi() = default;
  // Listens on host:port and returns the bound port (cluster::ShardServer::Start).
  [[nodiscard]] virtual Result<int> Start(const std::string& host, int port, const cluster::ShardSecurity& security,
                                          uint64_t max_message_bytes) = 0;
  virtual void SetService(std::shared_ptr<api::Service> service) = 0;
  // serve --data: every collection, each call naming its own (cluster::ShardServer::SetCollections).
  virtual void SetCollections(std::shared_ptr<api::Collections> collections) = 0;
  virtual void Shutdown() = 0;  // idempotent
};

struct ClusterApi {
  int version;
  // Serves the front until a signal of `signals` (blocked in every thread) arrives; a failure to start is
  // thrown as CommandError.
  void (*serve_front)(const FrontArgs& args, const sigset_t& signals);
  std::unique_ptr<ShardApi> (*new_shard)();
};

using ClusterApiEntry = const ClusterApi* (*)(int version);
inline constexpr const char* kClusterApiEntry = "oxbow_cluster_api";

// The module's table, loaded on first use; throws CommandError when it cannot be loaded.
const ClusterApi& Cluster();

}  // namespace oxbow::cli
