// `oxbow serve`: the HTTP JSON server over an index (server/http_server.h, api/service.h).
#include <pthread.h>
#include <signal.h>

#include <atomic>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>

#include "api/collections.h"
#include "api/service.h"
#include "index/image_index.h"
#include "index/storage/folder_lock.h"
#include "server/cli/cli.h"
#include "server/cli/common_flags.h"
#include "server/cli/modules/cluster_api.h"
#include "server/http/http_server.h"
#include "server/cli/search_flags.h"
#include "sift/base/log.h"

namespace oxbow::cli {
namespace {

struct ServeFlags {
  std::string index_dir;
  std::string data_dir;  // --data: a folder of collections instead of one index
  std::string vocab_path;
  server::HttpServerOptions http;
  api::ServiceOptions service;
  // The server's own defaults, in the flags' units.
  double max_upload_mb = static_cast<double>(server::HttpServerOptions{}.max_body_bytes) / (1 << 20);
  double max_inflight_upload_mb = static_cast<double>(server::HttpServerOptions{}.max_inflight_body_bytes) / (1 << 20);
  int max_header_kb = static_cast<int>(server::HttpServerOptions{}.max_head_bytes / 1024);
  int processing_timeout_s = api::ServiceOptions{}.processing_timeout_ms / 1000;
  double shutdown_grace_s = api::ServiceOptions{}.shutdown_grace_ms / 1000.0;
  ImageFlags image;
  int index_threads = 0;
  index::IndexOptions index_options;  // scoring options (--max-df, ...); num_threads from --index-threads
  std::string log_format = "text";
  int grpc_port = -1;  // -1: no gRPC (not a cluster shard)
  std::string cluster_key;  // the key of front <-> shard calls; "" = --api-key's
  cluster::ShardSecurity shard_security;  // --grpc-tls-* (the key from cluster_key)
  std::string cluster_file;  // the front of a cluster instead of an index
  cluster::FrontOptions front;
};

// `serve --cluster`: the front (server/cluster/front_http.h) over the shards cluster.json names, served
// by the cluster module (modules/cluster_api.h).
void ServeFront(const ServeFlags& flags, const server::HttpServerOptions& http,
                const api::ServiceOptions& service_options, const sigset_t& signals) {
  FrontArgs args;
  args.cluster_file = flags.cluster_file;
  args.cluster_key = flags.cluster_key;
  args.front = flags.front;
  args.http = http;
  args.service = service_options;
  Cluster().serve_front(args, signals);
}

// `serve --grpc-port`: the shard's gRPC API (cluster module), started before the index is loaded; null
// without --grpc-port.
std::unique_ptr<ShardApi> StartShard(const ServeFlags& flags, const server::HttpServerOptions& http) {
  if (flags.grpc_port < 0) return nullptr;
  cluster::ShardSecurity security = flags.shard_security;
  security.key = flags.cluster_key.empty() ? http.api_key : flags.cluster_key;
  std::unique_ptr<ShardApi> shard = Cluster().new_shard();
  // The largest upload, and room for an add's id, metadata and source name.
  const int grpc_port = ValueOrExit(shard->Start(http.host, flags.grpc_port, security, http.max_body_bytes + (1 << 20)));
  // Printed before the HTTP line, which tests and scripts wait for.
  std::printf("shard listening on grpc://%s:%d\n", http.host.c_str(), grpc_port);
  OXBOW_LOG(kInfo) << "cluster shard API (gRPC) on " << http.host << ":" << grpc_port
                   << (security.key.empty() ? "" : ", cluster key required") << (security.tls() ? ", TLS" : "")
                   << (security.tls_client_ca_file.empty() ? "" : " with client certificates");
  return shard;
}

void Serve(const ServeFlags& flags) {
  log::Format log_format = log::Format::kText;
  if (!log::ParseFormat(flags.log_format, &log_format)) throw CommandError(2, "--log-format must be text or json");
  log::SetFormat(log_format);
  server::HttpServerOptions http = flags.http;
  api::ServiceOptions service_options = flags.service;
  if (!(flags.max_upload_mb > 0 && flags.max_upload_mb <= 4096)) {
    throw CommandError(2, "--max-upload-mb must be in (0, 4096]");
  }
  const sift::DecodeOptions decode = flags.image.ToDecodeOptions();
  http.max_body_bytes = static_cast<uint64_t>(flags.max_upload_mb * 1024 * 1024);
  if (!(flags.max_inflight_upload_mb >= flags.max_upload_mb && flags.max_inflight_upload_mb <= 1024 * 1024)) {
    throw CommandError(2, "--max-inflight-upload-mb must be in [--max-upload-mb, 1048576]");
  }
  http.max_inflight_body_bytes = static_cast<uint64_t>(flags.max_inflight_upload_mb * 1024 * 1024);
  http.max_head_bytes = static_cast<size_t>(flags.max_header_kb) * 1024;
  service_options.max_image_bytes = http.max_body_bytes;
  service_options.max_pixels = decode.max_pixels;
  service_options.max_image_side_px = decode.max_image_side_px;
  service_options.processing_timeout_ms = flags.processing_timeout_s * 1000;
  service_options.shutdown_grace_ms = static_cast<int>(std::lround(flags.shutdown_grace_s * 1000));
  if (auto message = http.Check()) throw CommandError(2, *message);
  if (auto message = service_options.Check()) throw CommandError(2, *message);
  if (auto message = flags.index_options.Check()) throw CommandError(2, *message);
  if (auto ok = flags.shard_security.Check(); !ok) throw CommandError(2, ok.error().message);
  if ((flags.shard_security.tls() || !flags.shard_security.tls_client_ca_file.empty()) && flags.grpc_port < 0)
    throw CommandError(2, "--grpc-tls-cert, --grpc-tls-key and --grpc-tls-client-ca secure --grpc-port: give it too");
  // Before anything listens (cluster::ShardServer::Start checks it too).
  if (flags.grpc_port >= 0 && !cluster::IsLoopbackHost(http.host) && flags.cluster_key.empty() && http.api_key.empty()) {
    throw CommandError(2, "--grpc-port on " + http.host + " would take writes from anyone who reaches it: give "
                          "--cluster-key (or --api-key), or bind --host to loopback");
  }
  if (http.host != "127.0.0.1" && http.host != "localhost" && http.host != "::1" && http.api_key.empty()) {
    OXBOW_LOG(kWarning) << "serving on " << http.host << " without --api-key: anyone who can reach it may add and delete images";
  }

  // SIGINT/SIGTERM are handled by one thread (sigwait) so that no handler runs on a worker mid-request.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGHUP);  // --data and --cluster: re-read the collections' key file
  if (flags.cluster_file.empty() + flags.index_dir.empty() + flags.data_dir.empty() != 2) {
    throw CommandError(2, "give one of --index, --data and --cluster");
  }
  if (!flags.cluster_file.empty()) {
    pthread_sigmask(SIG_BLOCK, &signals, nullptr);
    return ServeFront(flags, http, service_options, signals);
  }
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);  // inherited by every thread started below

  index::IndexOptions index_options = flags.index_options;
  index_options.num_threads = flags.index_threads;
  const std::optional<std::string> vocab = flags.vocab_path.empty() ? std::nullopt : std::optional(flags.vocab_path);
  // What takes no time to open or refuse is opened before the port is bound: a folder without an index
  // (created with --vocab, refused without), a data folder that does not exist yet, a path that is a
  // file, a folder another process holds. A script waiting for 'listening on' then finds a server, not
  // one about to exit. A large index still loads behind the listening port (/readyz says when).
  std::shared_ptr<api::Service> opened_service;
  std::shared_ptr<api::Collections> opened_collections;
  std::error_code ec;
  if (!flags.index_dir.empty()) {
    if (!index::ImageIndex::Exists(flags.index_dir)) {
      opened_service = std::shared_ptr<api::Service>(
          ValueOrExit(api::Service::Open(flags.index_dir, vocab, service_options, index_options)));
    } else {
      ValueOrExit(index::FolderLock::Acquire(flags.index_dir));  // released here; the load takes it again
    }
  } else if (!flags.data_dir.empty() && !std::filesystem::is_directory(flags.data_dir, ec)) {
    opened_collections = ValueOrExit(api::Collections::Open(flags.data_dir, vocab, service_options, index_options));
  }

  server::HttpServer server(http);
  const int port = ValueOrExit(server.Bind());
  const std::unique_ptr<ShardApi> shard = StartShard(flags, http);
  // Tests and scripts parse this line for the port (it is printed once the socket accepts connections).
  std::printf("listening on http://%s:%d\n", http.host.c_str(), port);
  std::fflush(stdout);
  OXBOW_LOG(kInfo) << "listening on http://" << http.host << ":" << port << " (" << http.threads << " workers, queue "
                   << http.max_queued_connections << ", max body " << http.max_body_bytes << " bytes"
                   << (http.api_key.empty() ? "" : ", API key required for writes") << ")";

  std::optional<Error> load_error;
  std::shared_ptr<api::Collections> collections;  // --data, once loaded (for SIGHUP)
  std::mutex collections_mutex;
  std::thread loader([&] {
    const auto start = std::chrono::steady_clock::now();
    auto fail = [&](const Error& error, const char* what) {
      load_error = error;
      OXBOW_LOG(kError) << "cannot open the " << what << ": " << error.ToString();
      server.Shutdown();
    };
    if (!flags.data_dir.empty()) {
      Result<std::shared_ptr<api::Collections>> opened = opened_collections;
      if (!opened_collections) opened = api::Collections::Open(flags.data_dir, vocab, service_options, index_options);
      if (!opened) return fail(opened.error(), "data folder");
      OXBOW_LOG(kInfo) << "data folder " << flags.data_dir << " ready: " << (*opened)->Names().size()
                       << " collections, loaded in "
                       << std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() << " s";
      {
        std::lock_guard<std::mutex> lock(collections_mutex);
        collections = *opened;
      }
      if (shard) shard->SetCollections(*opened);
      server.SetCollections(std::move(*opened));
      return;
    }
    std::shared_ptr<api::Service> shared = opened_service;
    if (!shared) {
      auto service = api::Service::Open(flags.index_dir, vocab, service_options, index_options);
      if (!service) return fail(service.error(), "index");
      shared = std::move(*service);
    }
    const auto stats = shared->Stats();
    OXBOW_LOG(kInfo) << "index " << flags.index_dir << " ready: " << stats.index.num_images << " images, "
                     << stats.index.num_features << " features, " << stats.index.vocabulary_size << " words, loaded in "
                     << std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() << " s";
    if (shard) shard->SetService(shared);
    server.SetService(std::move(shared));
  });

  std::atomic<bool> stopped_itself{false};  // the server stopped without a signal (the index failed to load)
  std::thread signal_waiter([&] {
    int signal_number = 0;
    sigwait(&signals, &signal_number);
    while (signal_number == SIGHUP) {
      std::shared_ptr<api::Collections> set;
      {
        std::lock_guard<std::mutex> lock(collections_mutex);
        set = collections;
      }
      if (set == nullptr || set->keys() == nullptr) {
        OXBOW_LOG(kInfo) << "received SIGHUP: nothing to re-read ("
                         << (flags.data_dir.empty() ? "--index has no collection keys" : "the data folder is still loading")
                         << ")";
      } else if (auto s = set->keys()->Reload(); !s) {
        OXBOW_LOG(kError) << "received SIGHUP: the key file was not re-read, the keys stay as they were: " << s.error().ToString();
      } else {
        OXBOW_LOG(kInfo) << "received SIGHUP: re-read the collections' key file";
      }
      sigwait(&signals, &signal_number);
    }
    if (stopped_itself) return;
    OXBOW_LOG(kInfo) << "received " << (signal_number == SIGINT ? "SIGINT" : "SIGTERM")
                     << ": no new connections, finishing in-flight requests (extractions still running after "
                     << flags.shutdown_grace_s << " s are stopped)";
    server.Shutdown();
  });

  server.Run();  // returns after Shutdown(), once in-flight requests are done
  loader.join();
  if (shard) shard->Shutdown();
  // Wake the signal thread if the server stopped for another reason (index failed to load).
  // The waiter blocks SIGTERM and consumes it in sigwait(): this wakes it, it does not terminate anything.
  stopped_itself = true;
  pthread_kill(signal_waiter.native_handle(), SIGTERM);  // NOLINT(bugprone-bad-signal-to-kill-thread)
  signal_waiter.join();
  if (load_error) throw CommandError(*load_error);
  OXBOW_LOG(kInfo) << "stopped";
}

void SetUpServe(CLI::App& app) {
  auto flags = std::make_shared<ServeFlags>();
  CLI::App* cmd = app.add_subcommand(
      "serve",
      "Serve an index over HTTP (JSON API under /v1, the search page at /; see the README).\n"
      "  oxbow serve --index idx --vocab vocab.oxvoc        # creates idx if it holds no index yet\n"
      "  oxbow serve --data collections --api-key KEY       # every collections/NAME/ is a collection\n"
      "  curl -s --data-binary @photo.jpg 'http://127.0.0.1:8080/v1/search?top_k=5'\n"
      "A cluster (`index build --mpi --partitions P`): one shard per partition and a front:\n"
      "  oxbow serve --index cluster/partition-0 --port 9101 --grpc-port 9001      # ... one per partition\n"
      "  oxbow serve --cluster cluster.json --port 8080\n"
      "Prints 'listening on http://HOST:PORT' on stdout once bound. SIGINT/SIGTERM stop it gracefully; SIGHUP "
      "re-reads the collections' key file (--data; with --cluster, cluster.json's \"collection_keys\").");
  cmd->add_option("--index", flags->index_dir, "index folder (created when empty and --vocab is given); served as the "
                                             "collection \"default\"");
  cmd->add_option("--data", flags->data_dir,
                  "a folder of collections instead of one index: each sub-folder is an index folder served under "
                  "/v1/collections/NAME (created with POST /v1/collections and the admin key); the routes without "
                  "that prefix act on the collection \"default\", which --vocab creates when missing. The "
                  "collections' keys are in DIR/keys.json, re-read on SIGHUP (server/README.md, \"Collections\")");
  cmd->add_option("--cluster", flags->cluster_file,
                  "serve as the front of a cluster instead of an index: cluster.json names the vocabulary and each "
                  "partition's shard replicas (`serve --grpc-port`); serves the public API with the same limits and "
                  "options as an index (writes on every replica of the image's partition, a backup per partition "
                  "on its shard's machine); with \"collections\" it serves each under /v1/collections/NAME, the shards "
                  "holding their partition of each (`serve --data --grpc-port`; server/README.md, \"Operating a "
                  "cluster\")")
      ->check(CLI::ExistingFile);
  cmd->add_option("--shard-deadline-ms", flags->front.shard_deadline_ms,
                  "--cluster: a call to one shard replica fails after this long; the partition's next replica is asked")
      ->capture_default_str()
      ->check(CLI::Range(1, 600000));
  cmd->add_option("--replica-check-ms", flags->front.replica_check_ms,
                  "--cluster: how often every replica is asked for its write sequence; a replica behind its "
                  "partition's (it missed writes) is kept out of reads and its partition refuses writes until it "
                  "catches up (server/README.md, \"Operating a cluster\")")
      ->capture_default_str()
      ->check(CLI::Range(10, 3600000));
  cmd->add_option("--refresh-fraction", flags->front.refresh_fraction,
                  "--cluster: refresh the cluster's statistics (idf) by itself once the writes through this front "
                  "since the last refresh reach this fraction of its images; 0: only on demand "
                  "(POST /v1/admin/refresh-statistics)")
      ->capture_default_str()
      ->check(NumberIn(0, 1));
  cmd->add_option("--vocab", flags->vocab_path, "vocabulary file; needed only to create a new index (--index), or the collection \"default\" (--data)")
      ->check(CLI::ExistingFile);
  cmd->add_option("--grpc-port", flags->grpc_port,
                  "also serve the cluster shard API (gRPC, for a front: `serve --cluster`) on this port of --host; "
                  "0 picks a free one (printed as 'shard listening on grpc://HOST:PORT'); off when not given. "
                  "A partition of `index build --partitions` scores with the cluster's global-frequencies.oxdf. With --data, "
                  "DIR/NAME/ is this shard's partition of collection NAME (cluster.json's \"collections\")")
      ->check(CLI::Range(0, 65535));
  cmd->add_option("--cluster-key", flags->cluster_key,
                  "the key of a cluster's internal calls: a shard (--grpc-port) refuses every gRPC call without it, "
                  "a front (--cluster) sends it on every call (over cluster.json's \"key_file\"); default: "
                  "--api-key. A shard beyond loopback refuses to start without one. Also read from "
                  "$OXBOW_CLUSTER_KEY")
      ->envname("OXBOW_CLUSTER_KEY");
  cmd->add_option("--grpc-tls-cert", flags->shard_security.tls_cert_file,
                  "--grpc-port over TLS: this PEM certificate chain (with --grpc-tls-key); the front names the CA "
                  "in cluster.json's \"tls\"")
      ->check(CLI::ExistingFile);
  cmd->add_option("--grpc-tls-key", flags->shard_security.tls_key_file, "the PEM private key of --grpc-tls-cert")
      ->check(CLI::ExistingFile);
  cmd->add_option("--grpc-tls-client-ca", flags->shard_security.tls_client_ca_file,
                  "mutual TLS on --grpc-port: only clients presenting a certificate signed by a CA of this PEM "
                  "file are served (cluster.json's \"tls\" \"cert\" and \"key\" on the front)")
      ->check(CLI::ExistingFile);
  cmd->add_option("--host", flags->http.host, "address to bind (loopback by default; 0.0.0.0 exposes it)")
      ->capture_default_str();
  cmd->add_option("--port", flags->http.port, "TCP port; 0 picks a free one (printed)")
      ->capture_default_str()
      ->check(CLI::Range(0, 65535));
  cmd->add_option("--http-workers", flags->http.threads, "HTTP worker threads: requests served at once")
      ->capture_default_str()
      ->check(CLI::Range(1, 1024));
  cmd->add_option("--queue", flags->http.max_queued_connections,
                  "connections waiting for a worker at most; beyond it new ones get 503")
      ->capture_default_str()
      ->check(CLI::Range(1, 100000));
  cmd->add_option("--api-key", flags->http.api_key,
                  "the admin key: required for writes (Authorization: Bearer KEY or X-API-Key: KEY), for "
                  "creating and deleting collections and their keys, and for backups; reads of a public collection "
                  "need no key. Also read from $OXBOW_API_KEY")
      ->envname("OXBOW_API_KEY");
  cmd->add_option("--max-upload-mb", flags->max_upload_mb, "largest request body and image file, MiB (413 above)")
      ->capture_default_str();
  cmd->add_option("--max-batch-images", flags->http.max_batch_images,
                  "images in one POST /v1/images/batch at most (413 above); the request also counts against "
                  "--max-upload-mb")
      ->capture_default_str()
      ->check(CLI::Range(1, 10000));
  AddImageFlags(cmd, &flags->image);  // over --max-megapixels: 413
  cmd->add_option("--extractions", flags->service.max_concurrent_extractions,
                  "decode+extract operations at once (bounds memory); 0 = CPU cores")
      ->capture_default_str()
      ->check(CLI::Range(0, 1024));
  cmd->add_option("--extraction-wait-ms", flags->service.extraction_wait_ms,
                  "how long a request waits for an extraction slot before 503")
      ->capture_default_str()
      ->check(CLI::Range(0, 600000));
  cmd->add_option("--processing-timeout-s", flags->processing_timeout_s,
                  "an add, search or match still decoding or extracting after this many seconds is stopped (503); "
                  "so is one whose client hung up")
      ->capture_default_str()
      ->check(CLI::Range(1, 3600));
  cmd->add_option("--shutdown-grace-s", flags->shutdown_grace_s,
                  "on SIGTERM/SIGINT, decodes and extractions still running after this many seconds are stopped "
                  "(their requests get 503); 0 stops them at once")
      ->capture_default_str()
      ->check(NumberIn(0, 3600));
  cmd->add_option("--threads-per-request", flags->service.threads_per_request,
                  "threads inside one search's extraction and one match, 0 = all cores (lowest latency; concurrent "
                  "requests share them); adds at --add-nice extract on one thread")
      ->capture_default_str()
      ->check(CLI::Range(0, 256));
  cmd->add_option("--thumbnail-px", flags->service.thumbnails.stored_side_px,
                  "longest side of the thumbnail stored with each added image (the page's match view uses it)")
      ->capture_default_str()
      ->check(CLI::Range(32, 2048));
  cmd->add_option("--thumbnail-quality", flags->service.thumbnails.jpeg_quality, "JPEG quality of thumbnails")
      ->capture_default_str()
      ->check(CLI::Range(1, 100));
  cmd->add_option("--add-nice", flags->service.add_nice,
                  "nice value of the threads extracting added images, so searches get the CPU first; 0 = off")
      ->capture_default_str()
      ->check(CLI::Range(0, 19));
  cmd->add_option("--index-threads", flags->index_threads, "threads for loading the index and re-ranking; 0 = all cores")
      ->capture_default_str()
      ->check(CLI::Range(0, 256));
  cmd->add_option("--checkpoint-changes", flags->index_options.checkpoint_changes,
                  "write a checkpoint of the index (index/README.md, \"An index folder\") in the background once "
                  "more than max(N, 10% of the images) images were added or removed since the last; a restart "
                  "replays at most that many images")
      ->capture_default_str()
      ->check(CLI::Range(uint64_t{1}, (uint64_t{1} << 32) - 1));
  cmd->add_option("--log-format", flags->log_format,
                  "stderr log lines: text, or json (one object per line; fields in server/README.md, \"Logging\")")
      ->capture_default_str();
  cmd->add_option("--read-timeout-s", flags->http.read_timeout_s, "socket read timeout, seconds: a request body with no byte for this long gets 408")
      ->capture_default_str()
      ->check(CLI::Range(1, 3600));
  cmd->add_option("--write-timeout-s", flags->http.write_timeout_s, "socket write timeout, seconds")
      ->capture_default_str()
      ->check(CLI::Range(1, 3600));
  cmd->add_option("--request-timeout-s", flags->http.request_timeout_s,
                  "a request's headers and body must arrive within this many seconds, however slowly they trickle "
                  "(408 or closed after it)")
      ->capture_default_str()
      ->check(CLI::Range(1, 3600));
  cmd->add_option("--max-inflight-upload-mb", flags->max_inflight_upload_mb,
                  "request bodies held in memory by all requests together, MiB; an upload that does not fit gets 503")
      ->capture_default_str();
  cmd->add_option("--max-header-count", flags->http.max_header_count, "request headers at most (431 above)")
      ->capture_default_str()
      ->check(CLI::Range(1, 10000));
  cmd->add_option("--max-header-kb", flags->max_header_kb, "request line + headers, KiB at most (431 above)")
      ->capture_default_str()
      ->check(CLI::Range(1, 16384));
  cmd->add_option("--max-connections-per-client", flags->http.max_connections_per_client,
                  "open connections from one client address at most (served, queued or refused); beyond it 503")
      ->capture_default_str()
      ->check(CLI::Range(1, 100000));
  cmd->add_option("--top-k", flags->service.default_query.top_k, "default top_k of searches")
      ->capture_default_str()
      ->check(CLI::Range(1, 10000));
  cmd->add_option("--rerank", flags->service.default_query.rerank_depth,
                  "default spatial re-ranking depth of searches (0 = off)")
      ->capture_default_str()
      ->check(CLI::Range(0, 10000));
  // Query expansion is on by default (index::QueryOptions); a search with rerank=0 runs without it.
  cmd->add_flag("--qe,!--no-qe", flags->service.default_query.query_expansion,
                "average query expansion in searches by default (on; --no-qe turns it off; a search's qe parameter overrides)");
  // Defaults of the other search parameters (a search's own parameters override them) and the index's
  // scoring options.
  AddSearchFlags(cmd, &flags->service.default_query);
  AddIndexScoringFlags(cmd, &flags->index_options);
  cmd->callback([flags] { Serve(*flags); });
}

const bool registered_serve = RegisterCommand({"serve", 60, &SetUpServe});

}  // namespace
}  // namespace oxbow::cli
