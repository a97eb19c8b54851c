// Shard side of shard.proto over api::Service's index (see shard_server.h).
#include "server/cluster/shard_server.h"

#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>

#include <mutex>

#include "server/cluster/shard.grpc.pb.h"

namespace oxbow::cluster {
namespace {

std::array<float, 4> Box(const google::protobuf::RepeatedField<float>& v) {
  return {v[0], v[1], v[2], v[3]};
}

void PutTerms(const std::vector<index::QueryTerm>& terms, google::protobuf::RepeatedPtrField<Term>* out) {
  for (const index::QueryTerm& t : terms) {
    Term* term = out->Add();
    term->set_word(t.word);
    term->set_weight(t.weight);
  }
}

grpc::Status ToGrpc(const Error& e) {
  const grpc::StatusCode code = e.code == ErrorCode::kNotFound          ? grpc::StatusCode::NOT_FOUND
                                : e.code == ErrorCode::kInvalidArgument ? grpc::StatusCode::INVALID_ARGUMENT
                                                                        : grpc::StatusCode::INTERNAL;
  return {code, e.ToString()};
}

}  // namespace

class ShardServer::Impl final : public Shard::Service {
 public:
  void SetService(std::shared_ptr<const api::Service> service) {
    std::lock_guard<std::mutex> lock(mutex_);
    service_ = std::move(service);
  }

  grpc::Status Score(grpc::ServerContext* /*context*/, const ScoreRequest* request, ScoreReply* reply) override {
    const auto service = Current();
    if (!service) return NotReady();
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
    for (const auto& s : idx.ScoreTerms(terms, request->max_results(), &candidates)) {
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

  grpc::Status Verify(grpc::ServerContext* /*context*/, const VerifyRequest* request, VerifyReply* reply) override {
    const auto service = Current();
    if (!service) return NotReady();
    if (request->keypoints_size() != request->words_size() || request->region_size() != 4)
      return {grpc::StatusCode::INVALID_ARGUMENT, "one word per keypoint and a region of 4 values"};
    std::vector<sift::Keypoint> keypoints;
    keypoints.reserve(static_cast<size_t>(request->keypoints_size()));
    for (const Keypoint& k : request->keypoints()) {
      sift::Keypoint p;
      p.x = k.x();
      p.y = k.y();
      p.scale = k.scale();
      p.orientation = k.orientation();
      keypoints.push_back(p);
    }
    index::QueryOptions options;
    options.max_pairs_per_word = request->max_pairs_per_word();
    options.verify.min_inliers = request->min_inliers();
    if (auto message = options.Check()) return {grpc::StatusCode::INVALID_ARGUMENT, *message};
    const std::vector<std::string> ids(request->ids().begin(), request->ids().end());
    auto verified = service->index().VerifyImages(
        keypoints, {request->words().data(), static_cast<size_t>(request->words_size())}, Box(request->region()), ids,
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

  grpc::Status RegionTerms(grpc::ServerContext* /*context*/, const RegionTermsRequest* request,
                           RegionTermsReply* reply) override {
    const auto service = Current();
    if (!service) return NotReady();
    if (request->region_size() != 4) return {grpc::StatusCode::INVALID_ARGUMENT, "a region of 4 values"};
    auto terms = service->index().RegionTerms(request->id(), Box(request->region()));
    if (!terms) return ToGrpc(terms.error());
    PutTerms(*terms, reply->mutable_terms());
    return grpc::Status::OK;
  }

 private:
  std::shared_ptr<const api::Service> Current() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return service_;
  }
  static grpc::Status NotReady() { return {grpc::StatusCode::UNAVAILABLE, "the index is still loading"}; }

  mutable std::mutex mutex_;
  std::shared_ptr<const api::Service> service_;
};

ShardServer::ShardServer() : impl_(std::make_unique<Impl>()) {}

ShardServer::~ShardServer() { Shutdown(); }

Result<int> ShardServer::Start(const std::string& host, int port) {
  grpc::EnableDefaultHealthCheckService(true);
  grpc::ServerBuilder builder;
  int bound = 0;
  builder.AddListeningPort(host + ":" + std::to_string(port), grpc::InsecureServerCredentials(), &bound);
  builder.RegisterService(impl_.get());
  server_ = builder.BuildAndStart();
  if (!server_ || bound == 0)
    return Fail(ErrorCode::kIoError, "cannot listen for gRPC on " + host + ":" + std::to_string(port));
  server_->GetHealthCheckService()->SetServingStatus(false);
  return bound;
}

void ShardServer::SetService(std::shared_ptr<const api::Service> service) {
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
