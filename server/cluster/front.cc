// The cluster front (front.h): a query's stages over the shards' gRPC API (shard.proto).
#include "server/cluster/front.h"

#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <set>
#include <thread>

#include <nlohmann/json.hpp>

#include "server/cluster/shard.grpc.pb.h"
#include "vocab/vocabulary.h"

namespace oxbow::cluster {
namespace {

using Clock = std::chrono::steady_clock;

std::vector<index::QueryTerm> TermsFrom(const google::protobuf::RepeatedPtrField<Term>& terms) {
  std::vector<index::QueryTerm> out;
  out.reserve(static_cast<size_t>(terms.size()));
  for (const Term& t : terms) out.push_back({t.word(), t.weight()});
  return out;
}

void PutTerms(std::span<const index::QueryTerm> terms, google::protobuf::RepeatedPtrField<Term>* out) {
  for (const index::QueryTerm& t : terms) {
    Term* term = out->Add();
    term->set_word(t.word);
    term->set_weight(t.weight);
  }
}

// The partitions that failed during one query, with the first error.
class Failures {
 public:
  void Record(uint32_t partition, const Status& status) {
    if (status) return;
    if (!error_) error_ = status.error();
    failed_.insert(partition);
  }
  bool Contains(uint32_t partition) const { return failed_.contains(partition); }
  const std::set<uint32_t>& partitions() const { return failed_; }
  const std::optional<Error>& error() const { return error_; }

 private:
  std::set<uint32_t> failed_;
  std::optional<Error> error_;
};

// One shard image of a merged ranking.
struct Candidate {
  std::string id;
  float score = 0;
  uint32_t partition = 0;
  index::ImageRecord record;
};

Candidate FromScored(const Scored& s, uint32_t partition) {
  Candidate c{s.id(), s.score(), partition, {}};
  c.record.id = s.id();
  c.record.width = s.width();
  c.record.height = s.height();
  c.record.num_features = s.num_features();
  c.record.metadata_json = s.metadata_json();
  c.record.source_path = s.source_path();
  c.record.added_unix_ms = s.added_unix_ms();
  return c;
}

}  // namespace

Result<ClusterConfig> ClusterConfig::Read(const std::string& path) {
  std::ifstream in(path);
  if (!in) return Fail(ErrorCode::kNotFound, "cannot read the cluster file " + path);
  const nlohmann::json json = nlohmann::json::parse(in, nullptr, /*allow_exceptions=*/false);
  const auto invalid = [&](const std::string& why) { return Fail(ErrorCode::kInvalidArgument, path + ": " + why); };
  if (!json.is_object() || !json.contains("vocabulary") || !json["vocabulary"].is_string())
    return invalid("expected {\"vocabulary\": PATH, \"partitions\": [{\"replicas\": [HOST:PORT, ...]}, ...]}");
  ClusterConfig config;
  config.vocabulary = json["vocabulary"].get<std::string>();
  if (std::filesystem::path(config.vocabulary).is_relative())
    config.vocabulary = (std::filesystem::path(path).parent_path() / config.vocabulary).string();
  if (!json.contains("partitions") || !json["partitions"].is_array() || json["partitions"].empty())
    return invalid("\"partitions\" must be a non-empty array");
  for (const auto& partition : json["partitions"]) {
    if (!partition.is_object() || !partition.contains("replicas") || !partition["replicas"].is_array() ||
        partition["replicas"].empty())
      return invalid("every partition needs a non-empty \"replicas\" array");
    std::vector<std::string> replicas;
    for (const auto& replica : partition["replicas"]) {
      if (!replica.is_string() || replica.get<std::string>().empty())
        return invalid("a replica is a \"host:port\" string");
      replicas.push_back(replica.get<std::string>());
    }
    config.partitions.push_back(std::move(replicas));
  }
  return config;
}

class ClusterFront::Impl {
 public:
  struct Replica {
    uint32_t partition = 0;
    std::string address;
    std::unique_ptr<Shard::Stub> stub;
    std::atomic<uint64_t> calls{0};
    std::atomic<uint64_t> errors{0};
    std::atomic<uint64_t> total_us{0};
  };

  Impl(vocab::Vocabulary v, const FrontOptions& o) : vocabulary(std::move(v)), options(o) {}

  // Calls `call` on the partition's replicas in turn (starting with the next one round-robin) until one
  // answers; the last failure otherwise.
  template <typename Reply>
  Result<Reply> Call(uint32_t partition,
                     const std::function<grpc::Status(Shard::Stub&, grpc::ClientContext&, Reply*)>& call) const {
    const std::vector<std::unique_ptr<Replica>>& replicas = partitions[partition];
    const size_t start = next[partition]->fetch_add(1) % replicas.size();
    std::string failures;
    for (size_t k = 0; k < replicas.size(); ++k) {
      Replica& replica = *replicas[(start + k) % replicas.size()];
      grpc::ClientContext context;
      context.set_deadline(std::chrono::system_clock::now() + std::chrono::milliseconds(options.shard_deadline_ms));
      Reply reply;
      const auto t0 = Clock::now();
      const grpc::Status status = call(*replica.stub, context, &reply);
      replica.calls.fetch_add(1);
      replica.total_us.fetch_add(
          static_cast<uint64_t>(std::chrono::duration_cast<std::chrono::microseconds>(Clock::now() - t0).count()));
      if (status.ok()) return reply;
      replica.errors.fetch_add(1);
      // A shard that answered with its own error (not found, invalid) would answer the same elsewhere.
      if (status.error_code() == grpc::StatusCode::NOT_FOUND || status.error_code() == grpc::StatusCode::INVALID_ARGUMENT)
        return Fail(ErrorCode::kInternal, "shard " + replica.address + ": " + status.error_message());
      failures += (failures.empty() ? "" : "; ") + replica.address + ": " + status.error_message();
    }
    return Fail(ErrorCode::kResourceExhausted,
                "partition " + std::to_string(partition) + " did not answer (" + failures + ")");
  }

  // fn(i) for i in [0, n), all at once; every call's status.
  static std::vector<Status> ForEach(size_t n, const std::function<Status(uint32_t)>& fn) {
    std::vector<Status> statuses(n, Ok());
    std::vector<std::thread> threads;
    threads.reserve(n);
    for (uint32_t i = 0; i < n; ++i) threads.emplace_back([&, i] { statuses[i] = fn(i); });
    for (std::thread& t : threads) t.join();
    return statuses;
  }

  // Scores `request` on every partition that has not failed yet; the best `depth` over them, best first
  // (ties: smaller id). A partition that fails joins `failed`.
  std::vector<Candidate> Scatter(ScoreRequest request, size_t depth, std::vector<index::QueryTerm>* terms,
                                 uint64_t* candidates, Failures& failed) const {
    request.set_max_results(static_cast<uint32_t>(depth));
    std::vector<ScoreReply> replies(partitions.size());
    const std::vector<Status> statuses = ForEach(partitions.size(), [&](uint32_t p) -> Status {
      if (failed.Contains(p)) return Ok();
      auto reply = Call<ScoreReply>(p, [&](Shard::Stub& stub, grpc::ClientContext& context, ScoreReply* out) {
        return stub.Score(&context, request, out);
      });
      if (!reply) return std::unexpected(reply.error());
      replies[p] = std::move(*reply);
      return Ok();
    });
    for (uint32_t p = 0; p < statuses.size(); ++p) failed.Record(p, statuses[p]);
    std::vector<Candidate> merged;
    if (candidates) *candidates = 0;
    for (uint32_t p = 0; p < replies.size(); ++p) {
      if (failed.Contains(p)) continue;
      if (candidates) *candidates += replies[p].candidates();
      for (const Scored& scored : replies[p].images()) merged.push_back(FromScored(scored, p));
    }
    // Every partition made the same vector from the cluster's statistics; one that holds no image makes
    // none, so take the longest.
    if (terms) {
      terms->clear();
      for (const ScoreReply& reply : replies)
        if (static_cast<size_t>(reply.terms_size()) > terms->size()) *terms = TermsFrom(reply.terms());
    }
    std::sort(merged.begin(), merged.end(), [](const Candidate& a, const Candidate& b) {
      return a.score != b.score ? a.score > b.score : a.id < b.id;
    });
    if (merged.size() > depth) merged.resize(depth);
    return merged;
  }

  vocab::Vocabulary vocabulary;
  FrontOptions options;
  std::vector<std::vector<std::unique_ptr<Replica>>> partitions;
  std::vector<std::unique_ptr<std::atomic<uint64_t>>> next;  // per partition: round-robin position
};

Result<std::unique_ptr<ClusterFront>> ClusterFront::Open(const ClusterConfig& config, const FrontOptions& options) {
  if (options.shard_deadline_ms < 1 || options.shard_deadline_ms > 600000)
    return Fail(ErrorCode::kInvalidArgument, "the shard deadline must be in [1, 600000] ms");
  auto vocabulary = vocab::Vocabulary::Read(config.vocabulary);
  if (!vocabulary) return std::unexpected(vocabulary.error());
  auto impl = std::make_unique<Impl>(std::move(*vocabulary), options);
  for (uint32_t p = 0; p < config.partitions.size(); ++p) {
    std::vector<std::unique_ptr<Impl::Replica>> replicas;
    for (const std::string& address : config.partitions[p]) {
      auto replica = std::make_unique<Impl::Replica>();
      replica->partition = p;
      replica->address = address;
      replica->stub = Shard::NewStub(grpc::CreateChannel(address, grpc::InsecureChannelCredentials()));
      replicas.push_back(std::move(replica));
    }
    impl->partitions.push_back(std::move(replicas));
    impl->next.push_back(std::make_unique<std::atomic<uint64_t>>(0));
  }
  return std::unique_ptr<ClusterFront>(new ClusterFront(std::move(impl)));
}

ClusterFront::ClusterFront(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
ClusterFront::~ClusterFront() = default;

size_t ClusterFront::num_partitions() const { return impl_->partitions.size(); }
const vocab::Vocabulary& ClusterFront::vocabulary() const { return impl_->vocabulary; }

std::vector<ReplicaMetrics> ClusterFront::Metrics() const {
  std::vector<ReplicaMetrics> out;
  for (const auto& replicas : impl_->partitions)
    for (const auto& r : replicas)
      out.push_back({r->partition, r->address, r->calls.load(), r->errors.load(), static_cast<double>(r->total_us.load()) / 1000});
  return out;
}

Result<index::QueryResponse> ClusterFront::Query(const sift::FeatureSet& query, const index::QueryOptions& options,
                                                 bool allow_partial, Coverage* coverage) const {
  const auto t0 = Clock::now();
  const auto ms_since = [](Clock::time_point t) { return std::chrono::duration<double, std::milli>(Clock::now() - t).count(); };
  if (auto e = options.Check()) return Fail(ErrorCode::kInvalidArgument, "query options: " + *e);
  if (options.query_assignments != 1)
    return Fail(ErrorCode::kInvalidArgument, "query_assignments > 1 is not served by a cluster front yet");
  // Refused rather than ignored: an unfiltered or differently scored answer would look like a valid one.
  if (options.filter) return Fail(ErrorCode::kInvalidArgument, "filter is not served by a cluster front yet");
  if (options.hamming) return Fail(ErrorCode::kInvalidArgument, "hamming is not served by a cluster front yet");
  if (query.kind != impl_->vocabulary.descriptor_kind())
    return Fail(ErrorCode::kIncompatible, "the query's descriptors are not of the vocabulary's kind");
  index::QueryResponse response;
  Failures failed;
  const size_t num_partitions = impl_->partitions.size();
  // After each stage: with failures, the answer is partial (allowed) or none.
  const auto check = [&]() -> Status {
    if (failed.partitions().empty()) return Ok();
    if (!allow_partial || failed.partitions().size() == num_partitions) return std::unexpected(*failed.error());
    return Ok();
  };

  // Quantise the features inside the region once, as ImageIndex::Query does.
  std::vector<sift::Keypoint> keypoints;
  std::vector<float> descriptors;
  index::SelectInRegion(query, options.region, &keypoints, &descriptors);
  std::vector<uint32_t> words(keypoints.size());
  vocab::QuantizerOptions quantizer = index::IndexOptions{}.quantizer;
  quantizer.num_probes = options.quantizer_probes;
  quantizer.num_threads = impl_->options.num_threads;
  impl_->vocabulary.Quantize(descriptors, words, quantizer);
  response.query_features = static_cast<uint32_t>(words.size());
  response.timings.quantize_ms = ms_since(t0);

  // 1. TF-IDF scoring on every partition.
  auto t = Clock::now();
  const index::BagOfWords bag = index::BagOfWords::FromWords(words);
  ScoreRequest score;
  for (size_t k = 0; k < bag.words.size(); ++k) {
    score.add_words(bag.words[k]);
    score.add_tf(static_cast<float>(bag.counts[k]));
  }
  const size_t depth = std::max<size_t>(static_cast<size_t>(options.top_k), static_cast<size_t>(options.rerank_depth));
  std::vector<index::QueryTerm> terms;
  std::vector<Candidate> scored = impl_->Scatter(score, depth, &terms, &response.candidates, failed);
  if (auto s = check(); !s) return std::unexpected(s.error());
  response.timings.score_ms = ms_since(t);
  std::vector<index::QueryResult> results(scored.size());
  std::map<std::string, uint32_t> owner;
  for (size_t i = 0; i < scored.size(); ++i) {
    results[i].id = scored[i].id;
    results[i].score = scored[i].score;
    results[i].record = std::move(scored[i].record);
    owner[results[i].id] = scored[i].partition;
  }

  // 2. Spatial re-ranking of the top R, each candidate on its own shard.
  t = Clock::now();
  size_t rerank = std::min(results.size(), static_cast<size_t>(options.rerank_depth));
  size_t num_verified = 0;
  if (rerank > 0) {
    const std::array<float, 4> region =
        options.region ? *options.region
                       : std::array<float, 4>{0, 0, static_cast<float>(query.image_width), static_cast<float>(query.image_height)};
    VerifyRequest verify;
    for (size_t i = 0; i < keypoints.size(); ++i) {
      Keypoint* k = verify.add_keypoints();
      k->set_x(keypoints[i].x);
      k->set_y(keypoints[i].y);
      k->set_scale(keypoints[i].scale);
      k->set_orientation(keypoints[i].orientation);
      verify.add_words(words[i]);
    }
    for (float v : region) verify.add_region(v);
    verify.set_max_pairs_per_word(options.max_pairs_per_word);
    verify.set_min_inliers(options.verify.min_inliers);
    std::vector<std::vector<size_t>> positions(num_partitions);  // per partition: its candidates
    for (size_t c = 0; c < rerank; ++c) positions[owner[results[c].id]].push_back(c);
    const std::vector<Status> statuses = Impl::ForEach(num_partitions, [&](uint32_t p) -> Status {
      if (positions[p].empty()) return Ok();
      VerifyRequest request = verify;
      for (size_t c : positions[p]) request.add_ids(results[c].id);
      auto reply = impl_->Call<VerifyReply>(p, [&](Shard::Stub& stub, grpc::ClientContext& context, VerifyReply* out) {
        return stub.Verify(&context, request, out);
      });
      if (!reply) return std::unexpected(reply.error());
      if (static_cast<size_t>(reply->results_size()) != positions[p].size())
        return Fail(ErrorCode::kInternal, "a shard verified another number of images than asked");
      for (size_t i = 0; i < positions[p].size(); ++i) {
        const Verification& v = reply->results(static_cast<int>(i));
        index::QueryResult& r = results[positions[p][i]];
        r.inliers = v.inliers();
        if (v.verified() && v.db_from_query_size() == 6 && v.db_region_size() == 4) {
          r.verified = true;
          std::copy(v.db_from_query().begin(), v.db_from_query().end(), r.db_from_query.m.begin());
          std::copy(v.db_region().begin(), v.db_region().end(), r.db_region.begin());
        }
      }
      return Ok();
    });
    for (uint32_t p = 0; p < num_partitions; ++p) failed.Record(p, statuses[p]);
    if (auto s = check(); !s) return std::unexpected(s.error());
    // A partition that failed here has no place in a partial answer: its images go.
    std::erase_if(results, [&](const index::QueryResult& r) { return failed.Contains(owner[r.id]); });
    rerank = 0;
    for (uint32_t p = 0; p < num_partitions; ++p) rerank += failed.Contains(p) ? 0 : positions[p].size();
    index::SortVerifiedFirst(std::span(results).first(rerank));
    for (size_t c = 0; c < rerank; ++c) num_verified += results[c].verified ? 1 : 0;
  }
  response.timings.verify_ms = ms_since(t);

  // 3. Average query expansion: the region vectors come from their owners, the sum is the single node's.
  if (options.query_expansion && num_verified > 0) {
    t = Clock::now();
    const size_t used = std::min(num_verified, static_cast<size_t>(options.qe_images));
    std::vector<std::vector<index::QueryTerm>> region_terms(used);
    const std::vector<Status> statuses = Impl::ForEach(used, [&](uint32_t c) -> Status {
      RegionTermsRequest request;
      request.set_id(results[c].id);
      for (float v : results[c].db_region) request.add_region(v);
      auto reply = impl_->Call<RegionTermsReply>(
          owner[results[c].id], [&](Shard::Stub& stub, grpc::ClientContext& context, RegionTermsReply* out) {
            return stub.RegionTerms(&context, request, out);
          });
      if (!reply) return std::unexpected(reply.error());
      region_terms[c] = TermsFrom(reply->terms());
      return Ok();
    });
    for (size_t c = 0; c < used; ++c) failed.Record(owner[results[c].id], statuses[c]);
    if (auto s = check(); !s) return std::unexpected(s.error());
    const std::vector<index::QueryTerm> expanded = index::ExpandedQuery(terms, region_terms);
    const size_t expanded_depth =
        static_cast<size_t>(std::max(options.top_k, options.transitive_depth > 0 ? options.transitive_depth : 0));
    ScoreRequest rescore;
    PutTerms(expanded, rescore.mutable_terms());
    const std::vector<Candidate> rescored = impl_->Scatter(rescore, expanded_depth + num_verified, nullptr, nullptr, failed);
    if (auto s = check(); !s) return std::unexpected(s.error());
    std::vector<index::QueryResult> merged;
    for (size_t c = 0; c < num_verified; ++c)
      if (!failed.Contains(owner[results[c].id])) merged.push_back(results[c]);
    std::map<std::string, const index::QueryResult*> first_stage;
    for (const index::QueryResult& r : results) first_stage[r.id] = &r;
    for (const Candidate& c : rescored) {
      const auto it = first_stage.find(c.id);
      if (it != first_stage.end() && it->second->verified) continue;
      index::QueryResult r;
      if (it != first_stage.end()) r = *it->second;
      r.id = c.id;
      r.score = c.score;
      r.record = c.record;
      merged.push_back(std::move(r));
    }
    results = std::move(merged);
    response.timings.qe_ms = ms_since(t);
  }

  if (results.size() > static_cast<size_t>(options.top_k)) results.resize(static_cast<size_t>(options.top_k));
  response.results = std::move(results);
  response.timings.total_ms = ms_since(t0);
  if (coverage) {
    coverage->total = static_cast<uint32_t>(num_partitions);
    coverage->failed.assign(failed.partitions().begin(), failed.partitions().end());
    coverage->ok = coverage->total - static_cast<uint32_t>(coverage->failed.size());
  }
  return response;
}

}  // namespace oxbow::cluster
