// Shard side of shard.proto over api::Service's index (see shard_server.h).
#include "server/cluster/shard_server.h"

#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/resource_quota.h>

#include <filesystem>
#include <limits>
#include <mutex>
#include <system_error>

#include "index/backup.h"
#include "server/cluster/proto_convert.h"
#include "server/cluster/shard.grpc.pb.h"
#include "sift/base/log.h"

namespace oxbow::cluster {
namespace {

std::array<float, 4> Box(const google::protobuf::RepeatedField<float>& v) {
  return {v[0], v[1], v[2], v[3]};
}

// The front reads the ErrorCode back from the details (shard.proto) and answers as a single node would.
grpc::Status ToGrpc(const Error& e) {
  const grpc::StatusCode code = e.code == ErrorCode::kNotFound          ? grpc::StatusCode::NOT_FOUND
                                : e.code == ErrorCode::kInvalidArgument ? grpc::StatusCode::INVALID_ARGUMENT
                                : e.code == ErrorCode::kAlreadyExists   ? grpc::StatusCode::ALREADY_EXISTS
                                                                        : grpc::StatusCode::INTERNAL;
  return {code, e.message, std::string(ErrorCodeName(e.code))};
}

}  // namespace

class ShardServer::Impl final : public Shard::Service {
 public:
  explicit Impl(std::string key) : key_(std::move(key)) {}

  void SetService(std::shared_ptr<api::Service> service) {
    std::lock_guard<std::mutex> lock(mutex_);
    service_ = std::move(service);
  }

  grpc::Status Score(grpc::ServerContext* context, const ScoreRequest* request, ScoreReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    const index::ImageIndex& idx = service->index();
    if (request->words_size() != request->tf_size())
      return {grpc::StatusCode::INVALID_ARGUMENT, "one tf per word"};
    std::vector<index::QueryTerm> terms;
    if (request->words_size() > 0) {
      terms = idx.TermsOf({request->words().data(), static_cast<size_t>(request->words_size())},
                          {request->tf().data(), static_cast<size_t>(request->tf_size())});
    } else {
      for (const Term& t : request->terms()) terms.push_back({t.word(), t.weight()});
    }
    uint64_t candidates = 0;
    for (const auto& s : idx.ScoreTerms(terms, request->max_results(), &candidates, request->max_postings())) {
      Scored* out = reply->add_images();
      out->set_id(s.id);
      out->set_score(s.score);
      if (auto record = idx.Get(s.id)) {
        out->set_width(record->width);
        out->set_height(record->height);
        out->set_num_features(record->num_features);
        out->set_metadata_json(record->metadata_json);
        out->set_source_path(record->source_path);
        out->set_added_unix_ms(record->added_unix_ms);
      }
    }
    reply->set_candidates(candidates);
    PutTerms(terms, reply->mutable_terms());
    return grpc::Status::OK;
  }

  grpc::Status Verify(grpc::ServerContext* context, const VerifyRequest* request, VerifyReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    return VerifyOne(*service, *request, reply);
  }

  grpc::Status VerifyBatch(grpc::ServerContext* context, const VerifyBatchRequest* request,
                           VerifyBatchReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    for (const VerifyRequest& one : request->requests()) {
      if (grpc::Status status = VerifyOne(*service, one, reply->add_replies()); !status.ok()) return status;
    }
    return grpc::Status::OK;
  }

  grpc::Status ScoreAmong(grpc::ServerContext* context, const ScoreAmongRequest* request,
                          ScoreAmongReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    std::vector<std::vector<uint32_t>> queries;
    queries.reserve(static_cast<size_t>(request->queries_size()));
    for (const WordList& q : request->queries()) queries.emplace_back(q.words().begin(), q.words().end());
    const std::vector<std::string> ids(request->ids().begin(), request->ids().end());
    auto scores = service->index().ScoreAmong(queries, ids);
    if (!scores) return ToGrpc(scores.error());
    for (const std::vector<float>& row : *scores) reply->add_rows()->mutable_scores()->Add(row.begin(), row.end());
    return grpc::Status::OK;
  }

  grpc::Status RegionTerms(grpc::ServerContext* context, const RegionTermsRequest* request,
                           RegionTermsReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    if (request->region_size() != 4) return {grpc::StatusCode::INVALID_ARGUMENT, "a region of 4 values"};
    auto terms = service->index().RegionTerms(request->id(), Box(request->region()));
    if (!terms) return ToGrpc(terms.error());
    PutTerms(*terms, reply->mutable_terms());
    return grpc::Status::OK;
  }

  grpc::Status Get(grpc::ServerContext* context, const ImageRequest* request, Record* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    auto record = service->GetImage(request->id());
    if (!record) return ToGrpc(record.error());
    PutRecord(*record, reply);
    return grpc::Status::OK;
  }

  grpc::Status List(grpc::ServerContext* context, const ListRequest* request, ListReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    auto list = service->ListImages(request->offset(), request->limit());
    if (!list) return ToGrpc(list.error());
    for (const index::ImageRecord& record : list->images) PutRecord(record, reply->add_images());
    reply->set_total(list->total);
    return grpc::Status::OK;
  }

  grpc::Status Stats(grpc::ServerContext* context, const StatsRequest* /*request*/, StatsReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    const api::ServiceStats stats = service->Stats();
    reply->set_images(stats.index.num_images);
    reply->set_features(stats.index.num_features);
    reply->set_postings_bytes(stats.index.postings_bytes);
    reply->set_geometry_bytes(stats.index.geometry_bytes);
    reply->set_other_bytes(stats.index.other_bytes);
    reply->set_segments(stats.index.num_segments);
    reply->set_rss_bytes(stats.rss_bytes);
    reply->set_extractions_in_flight(stats.extractions_in_flight);
    reply->set_max_concurrent_extractions(stats.max_concurrent_extractions);
    return grpc::Status::OK;
  }

  grpc::Status Features(grpc::ServerContext* context, const ImageRequest* request, FeaturesReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    auto record = service->GetImage(request->id());
    if (!record) return ToGrpc(record.error());
    auto features = service->index().FeaturesOf(request->id());
    if (!features) return ToGrpc(features.error());
    PutRecord(*record, reply->mutable_record());
    for (const sift::Keypoint& k : features->keypoints) PutKeypoint(k, reply->add_keypoints());
    reply->mutable_words()->Add(features->words.begin(), features->words.end());
    return grpc::Status::OK;
  }

  grpc::Status Ping(grpc::ServerContext* context, const PingRequest* /*request*/, PingReply* /*reply*/) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    return grpc::Status::OK;
  }

  grpc::Status Add(grpc::ServerContext* context, const AddRequest* request, AddReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    api::AddImageRequest add;
    add.id = request->id();
    add.image = {reinterpret_cast<const uint8_t*>(request->image().data()), request->image().size()};
    add.metadata_json = request->metadata_json();
    add.source_name = request->source_name();
    add.replace = request->replace();
    auto added = service->AddImage(add);
    Stamp(context, *service);
    if (!added) return ToGrpc(added.error());
    PutRecord(added->record, reply->mutable_record());
    reply->set_replaced(added->replaced);
    reply->set_decode_extract_ms(added->decode_extract_ms);
    reply->set_add_ms(added->add_ms);
    return grpc::Status::OK;
  }

  grpc::Status Delete(grpc::ServerContext* context, const ImageRequest* request, DeleteReply* /*reply*/) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    const Status removed = service->DeleteImage(request->id());
    Stamp(context, *service);
    if (!removed) return ToGrpc(removed.error());
    return grpc::Status::OK;
  }

  grpc::Status Counts(grpc::ServerContext* context, const CountsRequest* /*request*/, CountsReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    const index::ImageIndex::LiveCounts counts = service->index().CountLive();
    reply->set_images(counts.num_images);
    reply->mutable_document_frequency()->Add(counts.document_frequency.begin(), counts.document_frequency.end());
    reply->set_vocabulary_fingerprint(service->index().vocabulary().fingerprint());
    return grpc::Status::OK;
  }

  grpc::Status PinStatistics(grpc::ServerContext* context, const PinRequest* request, PinReply* /*reply*/) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    api::GlobalFrequencies frequencies;
    frequencies.num_partitions = request->num_partitions();
    frequencies.partition = request->partition();
    frequencies.vocabulary_fingerprint = request->vocabulary_fingerprint();
    frequencies.num_images = request->images();
    frequencies.document_frequency.assign(request->document_frequency().begin(), request->document_frequency().end());
    const Status stored = service->StoreClusterStatistics(frequencies);
    Stamp(context, *service);
    if (!stored) return ToGrpc(stored.error());
    return grpc::Status::OK;
  }

  grpc::Status Thumbnail(grpc::ServerContext* context, const ThumbnailRequest* request, ThumbnailReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    auto found = service->GetThumbnail(request->id(), request->max_side_px());
    if (!found) return ToGrpc(found.error());
    reply->set_jpeg(std::move(found->thumbnail.jpeg));
    return grpc::Status::OK;
  }

  // A cluster backup (the front's POST /v1/admin/backup) puts every partition in its own folder of
  // `out`'s parent, which the first partition to get there creates.
  grpc::Status Backup(grpc::ServerContext* context, const BackupRequest* request, BackupReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    const std::filesystem::path out(request->out());
    if (!out.is_absolute() || !out.has_parent_path() || !out.filename().string().starts_with("partition-"))
      return ToGrpc({ErrorCode::kInvalidArgument, "a cluster backup goes to an absolute FOLDER/partition-K"});
    // FOLDER is new, or holds only the partition folders of this backup (the partitions on this machine
    // make theirs at once); never a folder with other contents, never through a symbolic link.
    const std::filesystem::path folder = out.parent_path();
    std::error_code error;
    if (std::filesystem::is_symlink(folder, error))
      return ToGrpc({ErrorCode::kInvalidArgument, "the backup folder " + folder.string() + " is a symbolic link"});
    if (std::filesystem::is_directory(folder, error)) {
      for (const auto& entry : std::filesystem::directory_iterator(folder, error)) {
        if (!entry.path().filename().string().starts_with("partition-"))
          return ToGrpc({ErrorCode::kAlreadyExists, "the backup folder " + folder.string() +
                                                        " exists and holds other files: give a new folder"});
      }
    } else if (std::filesystem::exists(folder, error)) {
      return ToGrpc({ErrorCode::kAlreadyExists, "the backup folder " + folder.string() + " exists and is not a folder"});
    } else {
      // A new FOLDER passes the single node's checks (its parent exists; no '..', link or control
      // character; not the served folder) before it is made; BackupIndex checks FOLDER/partition-K.
      if (auto ok = index::CheckBackupFolder(service->index().directory(), folder.string()); !ok)
        return ToGrpc(ok.error());
      std::filesystem::create_directory(folder, error);
    }
    auto done = service->Backup(out.string());
    if (!done) return ToGrpc(done.error());
    reply->set_images(done->images);
    reply->set_generation(done->generation);
    reply->set_bytes(done->bytes);
    reply->set_attempts(done->attempts);
    return grpc::Status::OK;
  }

 private:
  static grpc::Status VerifyOne(const api::Service& service, const VerifyRequest& request, VerifyReply* reply) {
    if (request.keypoints_size() != request.words_size() || request.region_size() != 4)
      return {grpc::StatusCode::INVALID_ARGUMENT, "one word per keypoint and a region of 4 values"};
    std::vector<sift::Keypoint> keypoints;
    keypoints.reserve(static_cast<size_t>(request.keypoints_size()));
    for (const Keypoint& k : request.keypoints()) keypoints.push_back(FromProto(k));
    index::QueryOptions options;
    options.max_pairs_per_word = request.max_pairs_per_word();
    options.verify.min_inliers = request.min_inliers();
    if (auto message = options.Check()) return {grpc::StatusCode::INVALID_ARGUMENT, *message};
    const std::vector<std::string> ids(request.ids().begin(), request.ids().end());
    auto verified = service.index().VerifyImages(
        keypoints, {request.words().data(), static_cast<size_t>(request.words_size())}, Box(request.region()), ids,
        options);
    if (!verified) return ToGrpc(verified.error());
    for (const sift::VerificationResult& v : *verified) {
      Verification* out = reply->add_results();
      out->set_verified(v.verified);
      out->set_inliers(v.num_inliers);
      for (double m : v.db_from_query.m) out->add_db_from_query(m);
      for (float b : v.db_region) out->add_db_region(b);
    }
    return grpc::Status::OK;
  }

  // Every call's first step: the cluster key (transport_security.h), then the loaded index.
  grpc::Status Admit(const grpc::ServerContext& context, std::shared_ptr<api::Service>* service) const {
    if (grpc::Status refused = Authorize(context, key_); !refused.ok()) return refused;
    std::lock_guard<std::mutex> lock(mutex_);
    *service = service_;
    if (!*service) return NotReady();
    return grpc::Status::OK;
  }
  // Reads stamp the sequence before they read: a value at or above the front's floor then guarantees
  // the answer holds every write the floor counts (front.h).
  static void Stamp(grpc::ServerContext* context, const api::Service& service) {
    context->AddInitialMetadata(kWriteSequenceKey, std::to_string(service.index().write_sequence()));
  }
  static grpc::Status NotReady() { return {grpc::StatusCode::UNAVAILABLE, "the index is still loading"}; }

  const std::string key_;  // the cluster key; "" = none
  mutable std::mutex mutex_;  // guards service_
  std::shared_ptr<api::Service> service_;
};

ShardServer::ShardServer() = default;

ShardServer::~ShardServer() { Shutdown(); }

Result<int> ShardServer::Start(const std::string& host, int port, const ShardServerOptions& options) {
  const ShardSecurity& security = options.security;
  if (!IsLoopbackHost(host) && security.key.empty()) {
    return Fail(ErrorCode::kInvalidArgument,
                "the cluster shard API on " + host + " would take writes from anyone who reaches the port: give "
                "--cluster-key (or --api-key), or bind --host to loopback");
  }
  auto credentials = MakeServerCredentials(security);
  if (!credentials) return std::unexpected(credentials.error());
  if (!IsLoopbackHost(host) && !security.tls()) {
    OXBOW_LOG(kWarning) << "the cluster shard API on " << host
                        << " has no TLS: the cluster key and the images cross the network in clear "
                           "(--grpc-tls-cert, --grpc-tls-key, --grpc-tls-client-ca)";
  }
  if (options.max_message_bytes == 0 || options.max_message_bytes > static_cast<uint64_t>(std::numeric_limits<int>::max()))
    return Fail(ErrorCode::kInvalidArgument, "the largest shard message must be in [1, 2^31) bytes");
  impl_ = std::make_unique<Impl>(security.key);
  grpc::EnableDefaultHealthCheckService(true);
  grpc::ServerBuilder builder;
  int bound = 0;
  builder.AddListeningPort(host + ":" + std::to_string(port), *credentials, &bound);
  // gRPC sets SO_REUSEPORT by default, with which a second shard binds the same port and the kernel
  // splits the front's connections between both; a port in use is refused instead, as for HTTP
  // (server/http/http_server.cc). gRPC keeps SO_REUSEADDR, so a restart on the port still binds.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  // An add carries the image, over gRPC's default 4 MiB; bounded as the HTTP body is.
  builder.SetMaxReceiveMessageSize(static_cast<int>(options.max_message_bytes));
  // gRPC buffers a whole message before it compares its size with that bound: the memory of every
  // call's buffers together is bounded too (room for two of the largest messages and many small ones),
  // so concurrent oversized messages wait or fail instead of growing the shard.
  grpc::ResourceQuota quota("oxbow-shard");
  quota.Resize(static_cast<size_t>(2 * options.max_message_bytes + (64u << 20)));
  builder.SetResourceQuota(quota);
  builder.RegisterService(impl_.get());
  server_ = builder.BuildAndStart();
  if (!server_ || bound == 0)
    return Fail(ErrorCode::kIoError, "cannot listen for gRPC on " + host + ":" + std::to_string(port));
  server_->GetHealthCheckService()->SetServingStatus(false);
  return bound;
}

void ShardServer::SetService(std::shared_ptr<api::Service> service) {
  if (!impl_) return;
  impl_->SetService(std::move(service));
  if (server_) server_->GetHealthCheckService()->SetServingStatus(true);
}

void ShardServer::Shutdown() {
  if (!server_) return;
  server_->GetHealthCheckService()->SetServingStatus(false);
  server_->Shutdown();
  server_.reset();
}

}  // namespace oxbow::cluster
