// liboxbow_cluster.so: cluster_api.h over server/cluster (gRPC). Loaded by serve_command.cc.
#include <pthread.h>

#include <csignal>
#include <cstdio>
#include <string>
#include <thread>
#include <vector>

#include "server/cli/cli.h"
#include "server/cli/modules/cluster_api.h"
#include "server/cluster/front_http.h"
#include "server/cluster/shard_server.h"
#include "sift/base/log.h"

namespace oxbow::cli {
namespace {

void ServeFront(const FrontArgs& args, const sigset_t& signals) {
  cluster::ClusterConfig config = ValueOrExit(cluster::ClusterConfig::Read(args.cluster_file));
  // The key sent to the shards: --cluster-key, else cluster.json's "key_file", else --api-key.
  if (!args.cluster_key.empty()) {
    config.security.key = args.cluster_key;
  } else if (config.security.key.empty()) {
    config.security.key = args.http.api_key;
  }
  // One front per collection of cluster.json, each naming its collection on every shard call.
  std::vector<cluster::FrontCollection> collections;
  std::string names;
  for (const cluster::ClusterCollection& c : config.collections) {
    std::shared_ptr<const cluster::ClusterFront> front =
        ValueOrExit(cluster::ClusterFront::Open(config, args.front, c.name));
    collections.push_back({std::move(front), c.settings});
    names += (names.empty() ? "" : ", ") + c.name;
  }
  std::unique_ptr<api::AccessKeys> keys;
  if (!config.collection_keys.empty()) keys = ValueOrExit(api::AccessKeys::Open(config.collection_keys));
  api::AccessKeys* const key_file = keys.get();  // owned by the server, which outlives the signal thread
  cluster::FrontHttpOptions options;
  options.http = args.http;
  options.service = args.service;
  auto server = ValueOrExit(cluster::FrontHttpServer::Create(std::move(collections), std::move(keys), options));
  const int port = ValueOrExit(server->Bind());
  std::printf("listening on http://%s:%d\n", args.http.host.c_str(), port);
  std::fflush(stdout);
  OXBOW_LOG(kInfo) << "cluster front on http://" << args.http.host << ":" << port << " over " << config.partitions.size()
                   << " partitions, collections " << names << " (" << args.cluster_file << ")";
  std::thread signal_waiter([&] {
    int signal_number = 0;
    sigwait(&signals, &signal_number);
    while (signal_number == SIGHUP) {  // re-read cluster.json's "collection_keys", as a single node its keys.json
      if (key_file == nullptr) {
        OXBOW_LOG(kInfo) << "received SIGHUP: nothing to re-read (cluster.json names no collection_keys)";
      } else if (auto s = key_file->Reload(); !s) {
        OXBOW_LOG(kError) << "received SIGHUP: the key file was not re-read, the keys stay as they were: " << s.error().ToString();
      } else {
        OXBOW_LOG(kInfo) << "received SIGHUP: re-read the collections' key file";
      }
      sigwait(&signals, &signal_number);
    }
    OXBOW_LOG(kInfo) << "received a stop signal: finishing in-flight requests";
    server->Shutdown();
  });
  server->Run();
  pthread_kill(signal_waiter.native_handle(), SIGTERM);  // NOLINT(bugprone-bad-signal-to-kill-thread)
  signal_waiter.join();
  OXBOW_LOG(kInfo) << "stopped";
}

class Shard final : public ShardApi {
 public:
  Result<int> Start(const std::string& host, int port, const cluster::ShardSecurity& security,
                    uint64_t max_message_bytes) override {
    cluster::ShardServerOptions options;
    options.security = security;
    options.max_message_bytes = max_message_bytes;
    return server_.Start(host, port, options);
  }
  void SetService(std::shared_ptr<api::Service> service) override { server_.SetService(std::move(service)); }
  void SetCollections(std::shared_ptr<api::Collections> collections) override {
    server_.SetCollections(std::move(collections));
  }
  void Shutdown() override { server_.Shutdown(); }

 private:
  cluster::ShardServer server_;
};

std::unique_ptr<ShardApi> NewShard() { return std::make_unique<Shard>(); }

constexpr ClusterApi kApi{kClusterApiVersion, ServeFront, NewShard};

}  // namespace
}  // namespace oxbow::cli

extern "C" __attribute__((visibility("default"))) const oxbow::cli::ClusterApi* oxbow_cluster_api(int version) {
  return version == oxbow::cli::kClusterApiVersion ? &oxbow::cli::kApi : nullptr;
}
