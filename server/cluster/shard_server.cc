// Shard side of shard.proto over api::Service's index (see shard_server.h).
#include "server/cluster/shard_server.h"

#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/resource_quota.h>

#include <algorithm>
#include <chrono>
#include <list>
#include <cmath>
#include <filesystem>
#include <limits>
#include <mutex>
#include <system_error>

#include "api/collections.h"
#include "api/filter.h"
#include "index/storage/backup.h"
#include "index/search/source.h"
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
  // A request's own fault (an image it cannot decode, too large, of a format not served) is an invalid
  // argument, as the others; the front reads the ErrorCode's name in the details either way.
  const bool invalid = e.code == ErrorCode::kInvalidArgument || e.code == ErrorCode::kInvalidImage ||
                       e.code == ErrorCode::kImageTooLarge || e.code == ErrorCode::kUnsupportedFormat;
  const grpc::StatusCode code = e.code == ErrorCode::kNotFound          ? grpc::StatusCode::NOT_FOUND
                                : invalid                               ? grpc::StatusCode::INVALID_ARGUMENT
                                : e.code == ErrorCode::kAlreadyExists   ? grpc::StatusCode::ALREADY_EXISTS
                                : e.code == ErrorCode::kResourceExhausted ? grpc::StatusCode::RESOURCE_EXHAUSTED
                                                                        : grpc::StatusCode::INTERNAL;
  return {code, e.message, std::string(ErrorCodeName(e.code))};
}

}  // namespace

class ShardServer::Impl final : public Shard::Service {
 public:
  explicit Impl(std::string key) : key_(std::move(key)) {}

  void SetCollections(std::shared_ptr<api::Collections> collections) {
    std::lock_guard<std::mutex> lock(mutex_);
    collections_ = std::move(collections);
  }

  grpc::Status Score(grpc::ServerContext* context, const ScoreRequest* request, ScoreReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    const size_t vocabulary_size = service->index().vocabulary().size();
    if (request->tf_size() != 0 && request->words_size() != request->tf_size())
      return Invalid("one tf per word, or none");
    if (!WordsIn(request->words(), vocabulary_size)) return Invalid("a word outside the vocabulary");
    if (request->max_results() > kMaxResults) return Invalid("at most " + std::to_string(kMaxResults) + " results");
    if (request->max_postings() > static_cast<uint64_t>(std::numeric_limits<int>::max()))
      return Invalid("max_postings out of range");
    index::QueryOptions options;
    options.max_scored_postings = static_cast<int>(request->max_postings());
    if (auto message = options.Check()) return Invalid(*message);
    if (!request->filter().empty()) {
      auto filter = api::ParseFilter(request->filter(), "filter");
      if (!filter) return ToGrpc(filter.error());
      options.filter = *filter;
    }
    std::vector<index::QueryTerm> terms;
    index::search::ScoreInput input{.words = {request->words().data(), static_cast<size_t>(request->words_size())},
                                    .tf = {request->tf().data(), static_cast<size_t>(request->tf_size())}};
    if (request->words_size() == 0) {
      for (const Term& t : request->terms()) {
        if (t.word() >= vocabulary_size) return Invalid("a word outside the vocabulary");
        terms.push_back({t.word(), t.weight()});
      }
      input.terms = terms;
    }
    const std::shared_ptr<Search> search = SearchOf(*context, service);
    const std::lock_guard<std::mutex> in_use(search->mutex);
    index::search::Source* source = search->source.get();
    auto scored = source->Score(input, request->max_results(), options);
    if (!scored) return ToGrpc(scored.error());
    std::vector<index::search::ImageRef> refs;
    for (const index::search::ScoredRef& s : scored->best) refs.push_back(s.ref);
    auto records = source->Records(refs);
    if (!records) return ToGrpc(records.error());
    for (size_t i = 0; i < scored->best.size(); ++i) {
      Scored* out = reply->add_images();
      out->set_id(scored->best[i].id);
      out->set_score(scored->best[i].score);
      const index::ImageRecord& record = (*records)[i];
      out->set_width(record.width);
      out->set_height(record.height);
      out->set_num_features(record.num_features);
      out->set_metadata_json(record.metadata_json);
      out->set_source_path(record.source_path);
      out->set_added_unix_ms(record.added_unix_ms);
    }
    reply->set_candidates(scored->candidates);
    PutTerms(scored->terms, reply->mutable_terms());
    return grpc::Status::OK;
  }

  grpc::Status Hamming(grpc::ServerContext* context, const HammingRequest* request, HammingReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    if (request->words_size() != request->signatures_size()) return Invalid("one signature per word");
    if (!WordsIn(request->words(), service->index().vocabulary().size()))
      return Invalid("a word outside the vocabulary");
    index::QueryOptions options;
    options.hamming_threshold = request->threshold();
    options.hamming_sigma = request->sigma();
    options.asmk_weight = request->asmk_weight();
    if (request->has_norm_exponent()) options.hamming_norm_exponent = request->norm_exponent();
    if (auto message = options.Check()) return Invalid(*message);
    const std::shared_ptr<Search> search = SearchOf(*context, service);
    const std::lock_guard<std::mutex> in_use(search->mutex);
    index::search::Source* source = search->source.get();
    std::vector<size_t> positions;
    auto refs = Found(*source, request->ids(), &positions);
    if (!refs) return ToGrpc(refs.error());
    auto scores = source->HammingScores({request->words().data(), static_cast<size_t>(request->words_size())},
                                        {request->signatures().data(), static_cast<size_t>(request->signatures_size())},
                                        *refs, options);
    if (!scores) return ToGrpc(scores.error());
    std::vector<double> out(static_cast<size_t>(request->ids_size()), std::nan(""));
    for (size_t k = 0; k < positions.size(); ++k) out[positions[k]] = (*scores)[k];
    reply->mutable_scores()->Add(out.begin(), out.end());
    return grpc::Status::OK;
  }

  grpc::Status VerifyBatch(grpc::ServerContext* context, const VerifyBatchRequest* request,
                           VerifyBatchReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    const size_t vocabulary_size = service->index().vocabulary().size();
    index::QueryOptions options;
    options.max_pairs_per_word = request->max_pairs_per_word();
    options.verify.min_inliers = request->min_inliers();
    options.hamming_threshold = request->hamming_threshold();
    options.max_tentative_matches = request->max_tentative_matches();
    if (auto message = options.Check()) return Invalid(*message);
    const auto num_geometries = static_cast<size_t>(request->geometries_size());
    std::vector<std::vector<sift::Keypoint>> keypoints(num_geometries);
    std::vector<index::search::GeometryQuery> geometries;
    geometries.reserve(num_geometries);
    for (size_t g = 0; g < num_geometries; ++g) {
      const Geometry& one = request->geometries(static_cast<int>(g));
      if (one.keypoints_size() != one.words_size() * kKeypointValues || one.region_size() != 4 ||
          (one.signatures_size() != 0 && one.signatures_size() != one.words_size()))
        return Invalid("one word (and signature, if any) per keypoint and a region of 4 values");
      if (!WordsIn(one.words(), vocabulary_size)) return Invalid("a word outside the vocabulary");
      keypoints[g] = KeypointsFrom(one.keypoints());
      geometries.push_back({.keypoints = keypoints[g],
                            .words = {one.words().data(), static_cast<size_t>(one.words_size())},
                            .signatures = {one.signatures().data(), static_cast<size_t>(one.signatures_size())},
                            .region = Box(one.region())});
    }
    const std::shared_ptr<Search> search = SearchOf(*context, service);
    const std::lock_guard<std::mutex> in_use(search->mutex);
    index::search::Source* source = search->source.get();
    std::vector<index::search::VerifyTask> tasks;
    std::vector<size_t> positions;  // of the tasks whose image is indexed here
    for (int k = 0; k < request->tasks_size(); ++k) {
      const VerifyTask& task = request->tasks(k);
      if (task.geometries_size() == 0) return Invalid("a task without geometries");
      for (const uint32_t g : task.geometries())
        if (g >= num_geometries) return Invalid("a task names a geometry the batch does not have");
      auto found = source->Find(task.id());
      if (!found) return ToGrpc(found.error());
      const std::optional<index::search::ImageRef>& ref = *found;
      if (!ref) continue;
      tasks.push_back({.ref = *ref, .geometries = {task.geometries().begin(), task.geometries().end()}});
      positions.push_back(static_cast<size_t>(k));
    }
    auto verified = source->Verify(geometries, tasks, options);
    if (!verified) return ToGrpc(verified.error());
    std::vector<VerifyOutcome*> outcomes(static_cast<size_t>(request->tasks_size()));
    for (VerifyOutcome*& outcome : outcomes) outcome = reply->add_outcomes();
    for (size_t k = 0; k < positions.size(); ++k) {
      const index::search::Verified& v = (*verified)[k];
      VerifyOutcome* outcome = outcomes[positions[k]];
      outcome->set_found(true);
      outcome->set_geometry(v.geometry);
      Verification* r = outcome->mutable_result();
      r->set_verified(v.result.verified);
      r->set_inliers(v.result.num_inliers);
      r->set_firm(v.result.firm);
      r->set_overlay(v.overlay);
      for (double m : v.result.db_from_query.m) r->add_db_from_query(m);
      for (float b : v.result.db_region) r->add_db_region(b);
    }
    return grpc::Status::OK;
  }

  grpc::Status RegionFeatures(grpc::ServerContext* context, const RegionFeaturesRequest* request,
                              RegionFeaturesReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    if (request->regions_size() != 4 * request->ids_size()) return Invalid("a region of 4 values per id");
    const std::shared_ptr<Search> search = SearchOf(*context, service);
    const std::lock_guard<std::mutex> in_use(search->mutex);
    index::search::Source* source = search->source.get();
    std::vector<size_t> positions;
    auto refs = Found(*source, request->ids(), &positions);
    if (!refs) return ToGrpc(refs.error());
    std::vector<std::array<float, 4>> regions;
    for (size_t k : positions) {
      const auto at = static_cast<int>(4 * k);
      regions.push_back({request->regions(at), request->regions(at + 1), request->regions(at + 2),
                         request->regions(at + 3)});
    }
    auto features = source->Features(*refs, regions,
                                     {.max_features = request->max_features(),
                                      .signatures = request->signatures(),
                                      .all_words = request->all_words()});
    if (!features) return ToGrpc(features.error());
    std::vector<ImageFeatures*> out(static_cast<size_t>(request->ids_size()));
    for (ImageFeatures*& one : out) one = reply->add_images();
    for (size_t k = 0; k < positions.size(); ++k) {
      const index::search::RegionFeatures& f = (*features)[k];
      ImageFeatures* one = out[positions[k]];
      one->set_found(true);
      PutKeypoints(f.keypoints, one->mutable_keypoints());
      one->mutable_words()->Add(f.words.begin(), f.words.end());
      one->mutable_signatures()->Add(f.signatures.begin(), f.signatures.end());
      one->mutable_all_words()->Add(f.all_words.begin(), f.all_words.end());
    }
    return grpc::Status::OK;
  }

  grpc::Status ScoreAmong(grpc::ServerContext* context, const ScoreAmongRequest* request,
                          ScoreAmongReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    const size_t vocabulary_size = service->index().vocabulary().size();
    std::vector<std::vector<uint32_t>> queries;
    queries.reserve(static_cast<size_t>(request->queries_size()));
    for (const WordList& q : request->queries()) {
      if (!WordsIn(q.words(), vocabulary_size)) return Invalid("a word outside the vocabulary");
      queries.emplace_back(q.words().begin(), q.words().end());
    }
    const std::shared_ptr<Search> search = SearchOf(*context, service);
    const std::lock_guard<std::mutex> in_use(search->mutex);
    index::search::Source* source = search->source.get();
    // The ranking of the search's previous round, when it asked about the same images.
    std::vector<std::string> ids(request->ids().begin(), request->ids().end());
    if (ids != search->ranked_ids || search->ranked_ids.empty()) {
      search->ranked_ids.clear();
      search->ranked_positions.clear();
      auto refs = Found(*source, request->ids(), &search->ranked_positions);
      if (!refs) return ToGrpc(refs.error());
      if (auto s = source->RankAmong(*refs); !s) return ToGrpc(s.error());
      search->ranked_ids = std::move(ids);
    }
    const std::vector<size_t>& positions = search->ranked_positions;
    auto scores = source->ScoreAmong(queries);
    if (!scores) return ToGrpc(scores.error());
    for (const std::vector<float>& found : *scores) {
      std::vector<float> row(static_cast<size_t>(request->ids_size()), 0.0f);
      for (size_t k = 0; k < positions.size(); ++k) row[positions[k]] = found[k];
      reply->add_rows()->mutable_scores()->Add(row.begin(), row.end());
    }
    return grpc::Status::OK;
  }

  grpc::Status RegionTerms(grpc::ServerContext* context, const RegionTermsRequest* request,
                           RegionTermsReply* reply) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    Stamp(context, *service);
    if (request->region_size() != 4) return Invalid("a region of 4 values");
    const std::shared_ptr<Search> search = SearchOf(*context, service);
    const std::lock_guard<std::mutex> in_use(search->mutex);
    index::search::Source* source = search->source.get();
    auto found = source->Find(request->id());
    if (!found) return ToGrpc(found.error());
    const std::optional<index::search::ImageRef>& maybe = *found;
    if (!maybe) return ToGrpc(Error{ErrorCode::kNotFound, "no image with id '" + request->id() + "'"});
    const index::search::ImageRef ref = *maybe;
    const std::array<float, 4> region = Box(request->region());
    auto terms = source->RegionTerms(std::span(&ref, 1), std::span(&region, 1));
    if (!terms) return ToGrpc(terms.error());
    PutTerms(terms->front(), reply->mutable_terms());
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

  grpc::Status EndSearch(grpc::ServerContext* context, const EndSearchRequest* /*request*/,
                         EndSearchReply* /*reply*/) override {
    std::shared_ptr<api::Service> service;
    if (grpc::Status refused = Admit(*context, &service); !refused.ok()) return refused;
    const auto& metadata = context->client_metadata();
    const auto it = metadata.find(kSearchKey);
    if (it == metadata.end()) return grpc::Status::OK;
    const std::string key(it->second.data(), it->second.size());
    std::shared_ptr<Search> ended;  // released after the lock (a call of the search may still hold it)
    {
      const std::lock_guard<std::mutex> lock(searches_mutex_);
      const auto kept = std::find_if(searches_.begin(), searches_.end(), [&](const KeptSearch& k) { return k.key == key; });
      if (kept != searches_.end()) {
        ended = std::move(kept->search);
        searches_.erase(kept);
      }
    }
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
    api::CollectionRef collection;
    if (grpc::Status refused = Admit(*context, &service, &collection); !refused.ok()) return refused;
    // The limits of this shard's part of the collection (its collection.json), as its own HTTP API applies
    // them; the front applies the collection's limits over all partitions first.
    if (auto full = api::Collections::CheckRoom(collection, request->replace() ? 0 : 1)) {
      Stamp(context, *service);
      return ToGrpc({ErrorCode::kResourceExhausted, "partition full: " + *full});
    }
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
    // FOLDER passes the single node's checks (its parent exists; no '..', link or control character; not
    // the served folder) and is new, or holds only the partition folders of this backup: the partitions
    // on this machine make theirs at once, so FOLDER may appear between the check and its creation, and
    // a taken FOLDER is judged by its contents. BackupIndex checks FOLDER/partition-K.
    const std::filesystem::path folder = out.parent_path();
    if (auto ok = index::CheckBackupFolder(service->index().directory(), folder.string());
        !ok && ok.error().code != ErrorCode::kAlreadyExists)
      return ToGrpc(ok.error());
    std::error_code error;
    std::filesystem::create_directory(folder, error);  // false, without an error, when it exists
    if (std::filesystem::is_symlink(folder, error))
      return ToGrpc({ErrorCode::kInvalidArgument, "the backup folder " + folder.string() + " is a symbolic link"});
    if (!std::filesystem::is_directory(folder, error))
      return ToGrpc({ErrorCode::kAlreadyExists, "the backup folder " + folder.string() + " exists and is not a folder"});
    for (const auto& entry : std::filesystem::directory_iterator(folder, error)) {
      if (!entry.path().filename().string().starts_with("partition-"))
        return ToGrpc({ErrorCode::kAlreadyExists, "the backup folder " + folder.string() +
                                                      " exists and holds other files: give a new folder"});
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
  // A search's source, kept between the search's calls to this shard (kSearchKey): each stage reads the
  // features and bags the previous ones read, from one snapshot. The front ends each search (EndSearch),
  // which frees what it kept: while a search is kept, the next one cannot reuse its memory and faults in
  // fresh pages (on the Paris subset that made every stage of a search through a front 2-5x slower
  // than the same stage of the shard's own searches). Searches a front did not end are kept at most
  // kMaxSearches at once, each for kSearchIdle after its last call (a search's calls come within its
  // own latency); a call without the key, or one whose search was dropped, gets a fresh source, with the
  // same answers.
  struct Search {
    std::mutex mutex;  // one call of the search at a time
    std::unique_ptr<index::search::Source> source;
    std::vector<std::string> ranked_ids;   // the images source->RankAmong ranked (ScoreAmong)...
    std::vector<size_t> ranked_positions;  // ... the positions among them of those indexed here
  };
  static constexpr size_t kMaxSearches = 16;
  static constexpr std::chrono::seconds kSearchIdle{10};

  std::shared_ptr<Search> SearchOf(const grpc::ServerContext& context, const std::shared_ptr<api::Service>& service) {
    const auto fresh = [&] {
      auto search = std::make_shared<Search>();
      search->source = service->index().OpenSearch();
      return search;
    };
    const auto& metadata = context.client_metadata();
    const auto it = metadata.find(kSearchKey);
    if (it == metadata.end() || it->second.empty() || it->second.size() > 64) return fresh();
    const std::string key(it->second.data(), it->second.size());
    const auto now = std::chrono::steady_clock::now();
    const std::lock_guard<std::mutex> lock(searches_mutex_);
    std::erase_if(searches_, [&](const KeptSearch& kept) { return now - kept.used > kSearchIdle; });
    for (auto kept = searches_.begin(); kept != searches_.end(); ++kept) {
      if (kept->key != key || kept->service.owner_before(service) || service.owner_before(kept->service)) continue;
      KeptSearch found = std::move(*kept);
      searches_.erase(kept);
      found.used = now;
      searches_.push_front(std::move(found));
      return searches_.front().search;
    }
    searches_.push_front({key, service, now, fresh()});
    if (searches_.size() > kMaxSearches) searches_.pop_back();
    return searches_.front().search;
  }

  // Requests' sizes: a search asks for at most top_k + the re-ranking's and expansion's depths.
  static constexpr uint32_t kMaxResults = 100000;

  static grpc::Status Invalid(const std::string& message) { return {grpc::StatusCode::INVALID_ARGUMENT, message}; }

  static bool WordsIn(const google::protobuf::RepeatedField<uint32_t>& words, size_t vocabulary_size) {
    return std::all_of(words.begin(), words.end(), [&](uint32_t w) { return w < vocabulary_size; });
  }

  // The images of `ids` indexed here, as `source` names them; *positions receives their positions in
  // `ids` (an image not indexed any more is left out: it answers as not found).
  static Result<std::vector<index::search::ImageRef>> Found(index::search::Source& source,
                                                            const google::protobuf::RepeatedPtrField<std::string>& ids,
                                                            std::vector<size_t>* positions) {
    std::vector<index::search::ImageRef> refs;
    for (int k = 0; k < ids.size(); ++k) {
      auto found = source.Find(ids[k]);
      if (!found) return std::unexpected(found.error());
      const std::optional<index::search::ImageRef>& ref = *found;
      if (!ref) continue;
      refs.push_back(*ref);
      positions->push_back(static_cast<size_t>(k));
    }
    return refs;
  }

  // Every call's first step: the cluster key (transport_security.h), then the loaded collections, then the
  // collection the call names (kCollectionKey; "default" without it).
  // `collection` (optional) receives the collection as a request holds it (its limits).
  grpc::Status Admit(const grpc::ServerContext& context, std::shared_ptr<api::Service>* service,
                     api::CollectionRef* collection = nullptr) const {
    if (grpc::Status refused = Authorize(context, key_); !refused.ok()) return refused;
    std::shared_ptr<api::Collections> collections;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      collections = collections_;
    }
    if (!collections) return NotReady();
    std::string name = api::kDefaultCollection;
    const auto& metadata = context.client_metadata();
    if (const auto it = metadata.find(kCollectionKey); it != metadata.end()) name.assign(it->second.data(), it->second.size());
    if (!api::Collections::IsValidName(name))
      return ToGrpc({ErrorCode::kInvalidArgument, "not a collection name (" + std::string(kCollectionKey) + ")"});
    auto found = collections->Find(name);
    if (!found) return ToGrpc({ErrorCode::kNotFound, "this shard holds no collection '" + name + "'"});
    *service = found->service;
    if (collection) *collection = std::move(*found);
    return grpc::Status::OK;
  }
  // Reads stamp the sequence before they read: a value at or above the front's floor then guarantees
  // the answer holds every write the floor counts (front.h).
  static void Stamp(grpc::ServerContext* context, const api::Service& service) {
    context->AddInitialMetadata(kWriteSequenceKey, std::to_string(service.index().write_sequence()));
  }
  static grpc::Status NotReady() { return {grpc::StatusCode::UNAVAILABLE, "the index is still loading"}; }

  const std::string key_;  // the cluster key; "" = none
  mutable std::mutex mutex_;  // guards collections_ (pointer copies only)
  std::shared_ptr<api::Collections> collections_;
  struct KeptSearch {
    std::string key;
    std::weak_ptr<const api::Service> service;  // the index it searches (a reloaded one starts afresh)
    std::chrono::steady_clock::time_point used;
    std::shared_ptr<Search> search;
  };
  std::mutex searches_mutex_;       // guards searches_; never taken while a Search's mutex is held
  std::list<KeptSearch> searches_;  // most recently used first
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
  SetCollections(api::Collections::Single(std::move(service)));
}

void ShardServer::SetCollections(std::shared_ptr<api::Collections> collections) {
  if (!impl_) return;
  impl_->SetCollections(std::move(collections));
  if (server_) server_->GetHealthCheckService()->SetServingStatus(true);
}

void ShardServer::Shutdown() {
  if (!server_) return;
  server_->GetHealthCheckService()->SetServingStatus(false);
  server_->Shutdown();
  server_.reset();
}

}  // namespace oxbow::cluster
