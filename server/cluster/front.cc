// The cluster front (front.h): a query's stages over the shards' gRPC API (shard.proto).
#include "server/cluster/front.h"

#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdlib>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <mutex>
#include <numeric>
#include <random>
#include <optional>
#include <set>
#include <shared_mutex>
#include <thread>

#include <nlohmann/json.hpp>

#include "api/partition.h"
#include "index/search/pipeline.h"
#include "index/search/source.h"
#include "sift/base/log.h"
#include "server/cluster/call_threads.h"
#include "server/cluster/proto_convert.h"
#include "server/cluster/shard.grpc.pb.h"
#include "vocab/vocabulary.h"

namespace oxbow::cluster {
namespace {

using Clock = std::chrono::steady_clock;

// Ids travel in protobuf string fields, which hold UTF-8 only. Adds refuse an id that is not, so no
// partition holds it: it is not found, as on a single node, and no shard is asked.
Status CheckStorableId(const std::string& id) {
  if (log::IsWellFormedUtf8(id)) return Ok();
  return Fail(ErrorCode::kNotFound, "no image with id '" + id + "'");
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

// A shard's own refusal (shard.proto: the ErrorCode's name in the details), or nullopt for a failure
// of the call itself (unreachable, deadline, still loading).
std::optional<Error> ShardRefusal(const grpc::Status& status) {
  for (int c = 0; c <= static_cast<int>(ErrorCode::kInternal); ++c) {
    const auto code = static_cast<ErrorCode>(c);
    if (status.error_details() == ErrorCodeName(code)) return Error{code, status.error_message()};
  }
  return std::nullopt;
}

// The options of a search through a front: those a single node takes, with a filter that can be sent to
// the partitions (api::ParseFilter's always can).
Status CheckServed(const index::QueryOptions& options) {
  if (auto e = options.Check()) return Fail(ErrorCode::kInvalidArgument, "query options: " + *e);
  if (options.filter && options.filter->Text().empty())
    return Fail(ErrorCode::kInvalidArgument, "this filter cannot be sent to a cluster's partitions");
  return Ok();
}

// Writes of one id through a front run one at a time: lock stripes by the id's hash.
constexpr uint32_t kWriteStripes = 64;
// How long reads ask a replica that failed after its partition's others (Impl::Replica::failing_until),
// unless the background check (every replica_check_ms) hears from it sooner.
constexpr std::chrono::seconds kFailingFor{5};

}  // namespace

Result<ClusterConfig> ClusterConfig::Read(const std::string& path) {
  std::ifstream in(path);
  if (!in) return Fail(ErrorCode::kNotFound, "cannot read the cluster file " + path);
  const nlohmann::json json = nlohmann::json::parse(in, nullptr, /*allow_exceptions=*/false);
  const auto invalid = [&](const std::string& why) { return Fail(ErrorCode::kInvalidArgument, path + ": " + why); };
  const bool has_default = json.is_object() && json.contains("vocabulary");
  const bool has_collections = json.is_object() && json.contains("collections");
  if (!json.is_object() || (!has_default && !has_collections) || (has_default && !json["vocabulary"].is_string()))
    return invalid("expected {\"vocabulary\": PATH, \"partitions\": [{\"replicas\": [HOST:PORT, ...]}, ...]} "
                   "(or \"collections\": {NAME: {\"vocabulary\": PATH}, ...} in place of or beside \"vocabulary\")");
  const auto relative = [&](const std::string& file) {
    return std::filesystem::path(file).is_relative() ? (std::filesystem::path(path).parent_path() / file).string() : file;
  };
  ClusterConfig config;
  if (has_default) {
    config.vocabulary = relative(json["vocabulary"].get<std::string>());
    config.collections.push_back({api::kDefaultCollection, config.vocabulary, {}});
  }
  if (has_collections) {
    if (!json["collections"].is_object() || json["collections"].empty())
      return invalid("\"collections\" is an object: {NAME: {\"vocabulary\": PATH, \"public\": BOOL, "
                     "\"max_images\": N, \"max_bytes\": N}, ...}");
    for (const auto& [name, entry] : json["collections"].items()) {
      const std::string where = "collection \"" + name + "\": ";
      if (!api::Collections::IsValidName(name)) return invalid(where + "not a collection name ([a-z0-9][a-z0-9_-]{0,63})");
      if (name == api::kDefaultCollection && has_default)
        return invalid(where + "named twice (the top-level \"vocabulary\" is the collection \"default\")");
      if (!entry.is_object() || !entry.contains("vocabulary") || !entry["vocabulary"].is_string() ||
          entry["vocabulary"].get<std::string>().empty())
        return invalid(where + "needs \"vocabulary\": PATH");
      ClusterCollection collection{name, relative(entry["vocabulary"].get<std::string>()), {}};
      for (const auto& [field, value] : entry.items()) {
        if (field == "vocabulary") continue;
        if (field == "public") {
          if (!value.is_boolean()) return invalid(where + "\"public\" is true or false");
          collection.settings.is_public = value.get<bool>();
        } else if (field == "max_images" || field == "max_bytes") {
          if (!value.is_number_unsigned() || value.get<uint64_t>() == 0)
            return invalid(std::string(where).append("\"").append(field).append("\" is a positive integer"));
          (field == "max_images" ? collection.settings.max_images : collection.settings.max_bytes) = value.get<uint64_t>();
        } else {
          return invalid(std::string(where).append("unknown field \"").append(field).append(
              "\" (vocabulary, public, max_images, max_bytes)"));
        }
      }
      if (name == api::kDefaultCollection) config.vocabulary = collection.vocabulary;
      config.collections.push_back(std::move(collection));
    }
  }
  if (json.contains("collection_keys")) {
    if (!json["collection_keys"].is_string() || json["collection_keys"].get<std::string>().empty())
      return invalid("\"collection_keys\" is the path of the collections' key file");
    config.collection_keys = relative(json["collection_keys"].get<std::string>());
  }
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
  if (json.contains("key_file")) {
    if (!json["key_file"].is_string() || json["key_file"].get<std::string>().empty())
      return invalid("\"key_file\" is the path of a file holding the cluster key");
    auto key = ReadSmallFile(relative(json["key_file"].get<std::string>()), "the cluster key file");
    if (!key) return std::unexpected(key.error());
    if (key->ends_with('\n')) key->pop_back();
    if (key->ends_with('\r')) key->pop_back();
    if (key->empty()) return invalid("the cluster key file is empty");
    config.security.key = std::move(*key);
  }
  if (json.contains("tls")) {
    const nlohmann::json& tls = json["tls"];
    if (!tls.is_object()) return invalid("\"tls\" is an object: {\"ca\", \"cert\", \"key\", \"server_name\"}");
    config.security.tls = true;
    for (const auto& [name, value] : tls.items()) {
      if (!value.is_string() || value.get<std::string>().empty())
        return invalid("\"tls\".\"" + name + "\" must be a non-empty string");
      const std::string text = value.get<std::string>();
      if (name == "ca") {
        config.security.tls_ca_file = relative(text);
      } else if (name == "cert") {
        config.security.tls_cert_file = relative(text);
      } else if (name == "key") {
        config.security.tls_key_file = relative(text);
      } else if (name == "server_name") {
        config.security.tls_server_name = text;
      } else {
        return invalid("unknown \"tls\" field \"" + name + "\" (ca, cert, key, server_name)");
      }
    }
    if (config.security.tls_cert_file.empty() != config.security.tls_key_file.empty())
      return invalid("\"tls\" needs \"cert\" and \"key\" together");
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
    std::atomic<int64_t> sequence{-1};  // the write sequence of its last answer; -1: none yet
    std::atomic<bool> reported_behind{false};
    // After a call that failed without an answer (unreachable, past its deadline, still loading), reads
    // start with the partition's other replicas until then (Clock ticks); the background check keeps
    // asking it, and its first answer clears this.
    std::atomic<Clock::rep> failing_until{0};
  };

  // Refreshes hold writes back: a write holds it shared, a refresh exclusively (front.h).
  mutable std::shared_mutex refresh_mutex;
  mutable std::atomic<uint64_t> writes_since_refresh{0};
  mutable std::atomic<uint64_t> images_at_refresh{0};  // 0: not known yet

  // Per partition: the floor of its replicas' write sequences and this front's writes (front.h).
  struct PartitionState {
    std::atomic<uint64_t> floor{0};
    std::atomic<uint64_t> writes_started{0};
    std::atomic<int> writes_in_flight{0};
  };

  template <typename Reply>
  using ShardCall = std::function<grpc::Status(Shard::Stub&, grpc::ClientContext&, Reply*)>;

  Impl(vocab::Vocabulary v, const FrontOptions& o, const std::string& key, std::string name)
      : vocabulary(std::move(v)),
        settings(o),
        bearer(key.empty() ? "" : std::string(kBearerPrefix) + key),
        collection(std::move(name)) {}
  ~Impl() {
    {
      std::unique_lock<std::mutex> lock(ends_mutex);
      ends_done.wait(lock, [&] { return ends_in_flight == 0; });
    }
    {
      const std::lock_guard<std::mutex> lock(checker_mutex);
      stopping = true;
    }
    checker_wake.notify_all();
    if (checker.joinable()) checker.join();
  }
  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;

  // One call to one replica within `deadline_ms`, counted in its metrics (unless `counted` is false: the
  // background check). The write sequence the replica stamped on its answer (-1 when none) goes to
  // `sequence` and to the replica. `stale` (optional) says whether the answer shows the replica behind:
  // stamped below the partition's floor as it was when the call started. A floor raised during the call
  // (a write of this front committed meanwhile) does not make the answer stale: the shard stamped it
  // before that write committed there, and the read began before the write was acknowledged.
  template <typename Reply>
  grpc::Status Invoke(Replica& replica, int deadline_ms, const ShardCall<Reply>& call, Reply* reply,
                      int64_t* sequence = nullptr, bool counted = true, bool* stale = nullptr,
                      bool wait_for_ready = false) const {
    const uint64_t floor_at_start = states[replica.partition]->floor.load();
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::milliseconds(deadline_ms));
    context.set_wait_for_ready(wait_for_ready);
    if (!bearer.empty()) context.AddMetadata(std::string(kAuthorizationKey), bearer);
    context.AddMetadata(kCollectionKey, collection);
    const auto t0 = Clock::now();
    grpc::Status status = call(*replica.stub, context, reply);
    if (counted) {
      replica.calls.fetch_add(1);
      replica.total_us.fetch_add(
          static_cast<uint64_t>(std::chrono::duration_cast<std::chrono::microseconds>(Clock::now() - t0).count()));
      if (!status.ok() && !ShardRefusal(status)) replica.errors.fetch_add(1);  // a refusal is the request's
    }
    NoteOutcome(replica, status);
    int64_t stamped = -1;
    if (status.ok() || ShardRefusal(status)) {
      const auto& metadata = context.GetServerInitialMetadata();
      if (const auto it = metadata.find(kWriteSequenceKey); it != metadata.end()) {
        const std::string value(it->second.data(), it->second.size());
        char* end = nullptr;
        const unsigned long long parsed = std::strtoull(value.c_str(), &end, 10);
        if (!value.empty() && end != nullptr && *end == '\0') stamped = static_cast<int64_t>(parsed);
      }
      if (stamped >= 0) {
        if (static_cast<uint64_t>(stamped) < floor_at_start) {
          replica.sequence.store(stamped);  // behind (restored from an old copy, or it missed writes)
        } else {
          // Answers of calls that overlapped a write arrive in any order: the replica is at least at the
          // highest it reported since it was last seen behind.
          int64_t current = replica.sequence.load();
          while (current < stamped && !replica.sequence.compare_exchange_weak(current, stamped)) {
          }
        }
        Reassess(replica);
      }
    }
    if (sequence) *sequence = stamped;
    if (stale) *stale = stamped >= 0 && static_cast<uint64_t>(stamped) < floor_at_start;
    return status;
  }

  // Replica::failing_until after a call: set when it failed without an answer, cleared when it answered;
  // each change logged.
  static void NoteOutcome(Replica& replica, const grpc::Status& status) {
    const bool answered = status.ok() || ShardRefusal(status);
    const Clock::rep until = answered ? 0 : (Clock::now() + kFailingFor).time_since_epoch().count();
    const Clock::rep before = replica.failing_until.exchange(until);
    if ((before == 0) == (until == 0)) return;
    if (answered) {
      OXBOW_LOG(kInfo) << "replica " << replica.address << " of partition " << replica.partition << " answers again";
      return;
    }
    OXBOW_LOG(kWarning) << "replica " << replica.address << " of partition " << replica.partition << " failed ("
                        << status.error_message()
                        << "): its partition's other replicas are asked first until it answers the background check";
  }

  // Whether `replica` is below its partition's floor (front.h).
  bool Behind(const Replica& replica) const {
    const int64_t sequence = replica.sequence.load();
    return sequence >= 0 && static_cast<uint64_t>(sequence) < states[replica.partition]->floor.load();
  }
  // Logs a replica falling behind or catching up, once per change.
  void Reassess(Replica& replica) const {
    const bool behind = Behind(replica);
    if (behind == replica.reported_behind.load() || replica.reported_behind.exchange(behind) == behind) return;
    if (behind) {
      OXBOW_LOG(kWarning) << "replica " << replica.address << " of partition " << replica.partition
                          << " is behind: write sequence " << replica.sequence.load() << ", the partition's is "
                          << states[replica.partition]->floor.load()
                          << "; it missed writes and is kept out of reads, and writes to the partition are refused, "
                             "until it catches up from an up-to-date replica (server/README.md)";
    } else {
      OXBOW_LOG(kInfo) << "replica " << replica.address << " of partition " << replica.partition
                       << " has caught up (write sequence " << replica.sequence.load() << "): used again";
    }
  }
  // Raises partition p's floor to `sequence` (never lowers it).
  void RaiseFloor(uint32_t p, uint64_t sequence) const {
    std::atomic<uint64_t>& floor = states[p]->floor;
    uint64_t current = floor.load();
    while (current < sequence && !floor.compare_exchange_weak(current, sequence)) {
    }
    for (const auto& replica : partitions[p]) Reassess(*replica);
  }
  // "behind (write sequence s < floor)" for a replica below its partition's floor.
  std::string BehindText(const Replica& replica) const {
    return replica.address + " (behind: write sequence " + std::to_string(replica.sequence.load()) + ", the partition's is " +
           std::to_string(states[replica.partition]->floor.load()) + ")";
  }

  // Asks every replica of partition p for its write sequence (uncounted); returns them (-1: no answer).
  std::vector<int64_t> PingAll(uint32_t p, std::vector<std::string>* why = nullptr) const {
    const std::vector<std::unique_ptr<Replica>>& replicas = partitions[p];
    std::vector<int64_t> sequences(replicas.size(), -1);
    const Clock::rep now = Clock::now().time_since_epoch().count();
    ForEach(replicas.size(), [&](uint32_t r) -> Status {
      PingReply pong;
      // Before a write, a replica not seen failing waits for its connection within the deadline: one
      // failed connection attempt (a fresh channel, a reconnect after an idle spell) is retried by gRPC
      // instead of refusing the write. A replica seen failing is not waited for.
      const bool wait = why != nullptr && replicas[r]->failing_until.load() <= now;
      const grpc::Status status = Invoke<PingReply>(
          *replicas[r], settings.shard_deadline_ms,
          [](Shard::Stub& stub, grpc::ClientContext& context, PingReply* out) { return stub.Ping(&context, {}, out); },
          &pong, &sequences[r], /*counted=*/why != nullptr, /*stale=*/nullptr, wait);
      if (!status.ok() && why) (*why)[r] = replicas[r]->address + " (" + status.error_message() + ")";
      if (status.ok() && sequences[r] < 0 && why)
        (*why)[r] = replicas[r]->address + " (it reports no write sequence: an older oxbow?)";
      return Ok();
    });
    return sequences;
  }

  // The background check (front.h): every replica's sequence; a partition with no write of this front
  // in flight during the round raises its floor to the highest.
  void CheckReplicas() const {
    ForEach(partitions.size(), [&](uint32_t p) -> Status {
      PartitionState& state = *states[p];
      const uint64_t started = state.writes_started.load();
      if (state.writes_in_flight.load() != 0) return Ok();
      const std::vector<int64_t> sequences = PingAll(p);
      if (state.writes_in_flight.load() != 0 || state.writes_started.load() != started) return Ok();
      const int64_t highest = *std::max_element(sequences.begin(), sequences.end());
      if (highest >= 0) RaiseFloor(p, static_cast<uint64_t>(highest));
      return Ok();
    });
  }
  Result<StatisticsRefresh> Refresh() const;
  // The background refresh rule (front.h).
  bool RefreshDue() const {
    const uint64_t writes = writes_since_refresh.load();
    return settings.refresh_fraction > 0 && writes > 0 &&
           static_cast<double>(writes) >= settings.refresh_fraction * static_cast<double>(images_at_refresh.load());
  }
  void CheckerLoop() {
    std::unique_lock<std::mutex> lock(checker_mutex);
    while (!checker_wake.wait_for(lock, std::chrono::milliseconds(settings.replica_check_ms), [&] { return stopping; })) {
      lock.unlock();
      CheckReplicas();
      if (RefreshDue()) {
        const uint64_t writes = writes_since_refresh.load();
        if (auto refreshed = Refresh()) {
          OXBOW_LOG(kInfo) << "refreshed the cluster's statistics after " << writes << " writes: " << refreshed->images
                           << " images, " << refreshed->replicas << " replicas, " << refreshed->ms << " ms";
          last_refresh_error.clear();
        } else if (refreshed.error().message != last_refresh_error) {  // once per distinct failure
          last_refresh_error = refreshed.error().message;
          OXBOW_LOG(kWarning) << "the cluster's statistics are due for a refresh (" << writes
                              << " writes since the last) but it failed; retried every check: "
                              << refreshed.error().ToString();
        }
      }
      lock.lock();
    }
  }

  // Calls `call` on the partition's replicas in turn (starting with the next one round-robin) until one
  // answers; the last failure otherwise. `deadline_ms`: per replica, 0 for settings.shard_deadline_ms. A shard's own refusal (unknown id, invalid request) is what
  // every replica would answer: returned at once.
  template <typename Reply>
  Result<Reply> Call(uint32_t partition, const ShardCall<Reply>& call, int deadline_ms = 0) const {
    const std::vector<std::unique_ptr<Replica>>& replicas = partitions[partition];
    const size_t start = AnsweringFrom(partition, next[partition]->fetch_add(1) % replicas.size());
    std::string failures;
    for (size_t k = 0; k < replicas.size(); ++k) {
      Replica& replica = *replicas[(start + k) % replicas.size()];
      if (Behind(replica)) {
        failures += (failures.empty() ? "" : "; ") + BehindText(replica);
        continue;
      }
      Reply reply;
      bool stale = false;
      const grpc::Status status = Invoke(replica, deadline_ms > 0 ? deadline_ms : settings.shard_deadline_ms, call, &reply,
                                         /*sequence=*/nullptr, /*counted=*/true, &stale);
      // An answer (or refusal: an image it lacks) from a replica that shows itself behind is not used.
      if ((status.ok() || ShardRefusal(status)) && stale) {
        failures += (failures.empty() ? "" : "; ") + BehindText(replica);
        continue;
      }
      if (status.ok()) return reply;
      if (auto refusal = ShardRefusal(status)) return std::unexpected(*refusal);
      failures += (failures.empty() ? "" : "; ") + replica.address + ": " + status.error_message();
    }
    return Fail(ErrorCode::kResourceExhausted,
                "partition " + std::to_string(partition) + " did not answer (" + failures + ")");
  }

  // The first replica of partition p from `start` on (round-robin order) that has not failed recently
  // (Replica::failing_until), else `start`: a dead or hung replica would otherwise cost a failed
  // connection or its deadline on every call that starts with it.
  size_t AnsweringFrom(uint32_t p, size_t start) const {
    const std::vector<std::unique_ptr<Replica>>& replicas = partitions[p];
    const Clock::rep now = Clock::now().time_since_epoch().count();
    for (size_t k = 0; k < replicas.size(); ++k) {
      const size_t r = (start + k) % replicas.size();
      if (replicas[r]->failing_until.load() <= now) return r;
    }
    return start;
  }

  // A write on every replica of `partition` (front.h): Ping all, then the first replica, then the others.
  template <typename Reply>
  Result<Reply> WriteAll(uint32_t partition, const ShardCall<Reply>& call) const {
    const std::vector<std::unique_ptr<Replica>>& replicas = partitions[partition];
    const std::string where = "partition " + std::to_string(partition) + ": ";
    PartitionState& state = *states[partition];
    const std::shared_lock<std::shared_mutex> no_refresh(refresh_mutex);
    const uint64_t started = state.writes_started.fetch_add(1) + 1;
    state.writes_in_flight.fetch_add(1);
    struct Done {
      std::atomic<int>& in_flight;
      ~Done() { in_flight.fetch_sub(1); }
    } done{state.writes_in_flight};
    std::vector<std::string> why(replicas.size());  // per replica: its failure, "" when it answered
    const std::vector<int64_t> before = PingAll(partition, &why);
    const std::string down = Join(why);
    if (!down.empty())
      return Fail(ErrorCode::kResourceExhausted, where + "replica " + down + " did not answer; nothing was written");
    // No other write of this front in flight: the replicas should agree; the highest is the floor.
    if (state.writes_in_flight.load() == 1 && state.writes_started.load() == started)
      RaiseFloor(partition, static_cast<uint64_t>(*std::max_element(before.begin(), before.end())));
    for (size_t r = 0; r < replicas.size(); ++r)
      if (Behind(*replicas[r])) why[r] = BehindText(*replicas[r]);
    if (const std::string behind = Join(why); !behind.empty())
      return Fail(ErrorCode::kResourceExhausted,
                  where + "replica " + behind +
                      " missed writes; nothing was written: writes to this partition are refused until it catches up "
                      "from an up-to-date replica (server/README.md)");

    std::vector<int64_t> after(replicas.size(), -1);
    Reply first;
    const grpc::Status status = Invoke(*replicas[0], settings.write_deadline_ms, call, &first, &after[0]);
    if (!status.ok()) {
      if (auto refusal = ShardRefusal(status)) return std::unexpected(*refusal);
      return Fail(ErrorCode::kResourceExhausted, where + "replica " + replicas[0]->address + " failed during the write (" +
                                                     status.error_message() +
                                                     "): it may have applied it; the other replicas did not");
    }
    std::vector<std::string> applied(replicas.size());
    applied[0] = replicas[0]->address;
    ForEach(replicas.size() - 1, [&](uint32_t k) -> Status {
      const uint32_t r = k + 1;
      Reply reply;
      const grpc::Status s = Invoke(*replicas[r], settings.write_deadline_ms, call, &reply, &after[r]);
      if (s.ok()) {
        applied[r] = replicas[r]->address;
      } else {
        why[r] = replicas[r]->address + " (" + s.error_message() + ")";
      }
      return Ok();
    });
    if (const std::string failed = Join(why); !failed.empty())
      return Fail(ErrorCode::kResourceExhausted, where + "the write was applied on " + Join(applied) +
                                                     " but not on " + failed +
                                                     ": the replicas differ until it is repeated there");
    writes_since_refresh.fetch_add(1);
    // Every replica applied it: each one is now at least at the smallest sequence they reported.
    if (const int64_t lowest = *std::min_element(after.begin(), after.end()); lowest >= 0)
      RaiseFloor(partition, static_cast<uint64_t>(lowest));
    return first;
  }

  // Tells every replica of each partition in `asked` that search `key` is over (ShardServer drops what
  // it kept for it), without waiting: the answers matter to nobody, and ~Impl waits for them.
  void EndSearch(const std::string& key, const std::vector<uint8_t>& asked) const {
    for (uint32_t p = 0; p < asked.size(); ++p) {
      if (!asked[p]) continue;
      for (const std::unique_ptr<Replica>& replica : partitions[p]) {
        {
          const std::lock_guard<std::mutex> lock(ends_mutex);
          ++ends_in_flight;
        }
        PostOnCallThread([this, stub = replica->stub.get(), key] {
          grpc::ClientContext context;
          // Short: a shard that does not answer drops the search after its idle limit anyway, and a front
          // that closes waits for these calls.
          context.set_deadline(std::chrono::system_clock::now() +
                               std::chrono::milliseconds(std::min(settings.shard_deadline_ms, 1000)));
          if (!bearer.empty()) context.AddMetadata(std::string(kAuthorizationKey), bearer);
          context.AddMetadata(kCollectionKey, collection);
          context.AddMetadata(kSearchKey, key);
          EndSearchReply reply;
          (void)stub->EndSearch(&context, EndSearchRequest(), &reply);
          const std::lock_guard<std::mutex> lock(ends_mutex);
          if (--ends_in_flight == 0) ends_done.notify_all();
        });
      }
    }
  }

  // The non-empty strings, comma-separated.
  static std::string Join(const std::vector<std::string>& parts) {
    std::string out;
    for (const std::string& p : parts)
      if (!p.empty()) out += (out.empty() ? "" : ", ") + p;
    return out;
  }

  uint32_t OwnerOf(const std::string& id) const {
    return api::PartitionOf(id, static_cast<uint32_t>(partitions.size()));
  }
  std::mutex& WriteLockOf(const std::string& id) const { return write_locks[api::PartitionOf(id, kWriteStripes)]; }

  // fn(i) for i in [0, n), all at once; every call's status.
  static std::vector<Status> ForEach(size_t n, const std::function<Status(uint32_t)>& fn) {
    std::vector<Status> statuses(n, Ok());
    RunOnCallThreads(n, [&](size_t i) { statuses[i] = fn(static_cast<uint32_t>(i)); });
    return statuses;
  }

  vocab::Vocabulary vocabulary;
  FrontOptions settings;
  const std::string bearer;  // "Bearer KEY" of the cluster key, sent on every call; "" = none
  const std::string collection;  // named on every call (kCollectionKey)
  std::vector<std::vector<std::unique_ptr<Replica>>> partitions;
  std::vector<std::unique_ptr<std::atomic<uint64_t>>> next;  // per partition: round-robin position
  std::vector<std::unique_ptr<PartitionState>> states;        // per partition
  mutable std::array<std::mutex, kWriteStripes> write_locks;
  Clock::time_point opened = Clock::now();
  std::mutex checker_mutex;  // guards stopping
  std::condition_variable checker_wake;
  bool stopping = false;
  std::thread checker;  // runs CheckerLoop
  std::string last_refresh_error;  // CheckerLoop's own
  mutable std::mutex ends_mutex;  // guards ends_in_flight; taken alone
  mutable std::condition_variable ends_done;
  mutable size_t ends_in_flight = 0;  // EndSearch calls posted and not yet answered
};

Result<std::unique_ptr<ClusterFront>> ClusterFront::Open(const ClusterConfig& config, const FrontOptions& options,
                                                         const std::string& collection) {
  if (options.shard_deadline_ms < 1 || options.shard_deadline_ms > 600000)
    return Fail(ErrorCode::kInvalidArgument, "the shard deadline must be in [1, 600000] ms");
  if (options.write_deadline_ms < 1 || options.write_deadline_ms > 600000)
    return Fail(ErrorCode::kInvalidArgument, "the write deadline must be in [1, 600000] ms");
  if (!(options.refresh_fraction >= 0 && options.refresh_fraction <= 1))
    return Fail(ErrorCode::kInvalidArgument, "the refresh fraction must be in [0, 1]");
  if (options.replica_check_ms < 10 || options.replica_check_ms > 3600000)
    return Fail(ErrorCode::kInvalidArgument, "the replica check interval must be in [10, 3600000] ms");
  // A list of deep pages and an image's stored features can pass gRPC's default 4 MiB per message.
  grpc::ChannelArguments channel;
  channel.SetMaxReceiveMessageSize(-1);
  // A replica back after a restart is used again within about a second (gRPC's default reconnect
  // backoff grows to 2 minutes). Not GRPC_ARG_MIN_RECONNECT_BACKOFF_MS: gRPC core takes it as the
  // minimum connect timeout (default 20 s), and a short one fails connections on a loaded machine.
  channel.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, 200);
  channel.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, 1000);
  if (!config.security.tls_server_name.empty()) channel.SetSslTargetNameOverride(config.security.tls_server_name);
  auto credentials = MakeChannelCredentials(config.security);
  if (!credentials) return std::unexpected(credentials.error());
  std::string vocabulary_path;
  for (const ClusterCollection& c : config.collections)
    if (c.name == collection) vocabulary_path = c.vocabulary;
  if (vocabulary_path.empty() && collection == api::kDefaultCollection) vocabulary_path = config.vocabulary;
  if (vocabulary_path.empty()) return Fail(ErrorCode::kNotFound, "the cluster has no collection '" + collection + "'");
  auto vocabulary = vocab::Vocabulary::Read(vocabulary_path);
  if (!vocabulary) return std::unexpected(vocabulary.error());
  auto impl = std::make_unique<Impl>(std::move(*vocabulary), options, config.security.key, collection);
  for (uint32_t p = 0; p < config.partitions.size(); ++p) {
    std::vector<std::unique_ptr<Impl::Replica>> replicas;
    for (const std::string& address : config.partitions[p]) {
      auto replica = std::make_unique<Impl::Replica>();
      replica->partition = p;
      replica->address = address;
      replica->stub = Shard::NewStub(grpc::CreateCustomChannel(address, *credentials, channel));
      replicas.push_back(std::move(replica));
    }
    impl->partitions.push_back(std::move(replicas));
    impl->next.push_back(std::make_unique<std::atomic<uint64_t>>(0));
    impl->states.push_back(std::make_unique<Impl::PartitionState>());
  }
  // The partitions' floors before the first query, then in the background.
  impl->CheckReplicas();
  impl->checker = std::thread([raw = impl.get()] { raw->CheckerLoop(); });
  auto front = std::unique_ptr<ClusterFront>(new ClusterFront(std::move(impl)));
  // The cluster's images, for the background refresh rule (best effort: unknown, the first write is due).
  if (auto stats = front->Stats()) front->impl_->images_at_refresh = stats->index.num_images;
  return front;
}

ClusterFront::ClusterFront(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
ClusterFront::~ClusterFront() = default;

size_t ClusterFront::num_partitions() const { return impl_->partitions.size(); }
const vocab::Vocabulary& ClusterFront::vocabulary() const { return impl_->vocabulary; }
const std::string& ClusterFront::collection() const { return impl_->collection; }

std::vector<ReplicaMetrics> ClusterFront::Metrics() const {
  std::vector<ReplicaMetrics> out;
  for (const auto& replicas : impl_->partitions)
    for (const auto& r : replicas)
      out.push_back({r->partition, r->address, r->calls.load(), r->errors.load(),
                     static_cast<double>(r->total_us.load()) / 1000, r->sequence.load(), impl_->Behind(*r)});
  return out;
}

Result<index::ImageRecord> ClusterFront::Get(const std::string& id) const {
  if (auto s = CheckStorableId(id); !s) return std::unexpected(s.error());
  ImageRequest request;
  request.set_id(id);
  auto record = impl_->Call<Record>(impl_->OwnerOf(id), [&](Shard::Stub& stub, grpc::ClientContext& context, Record* out) {
    return stub.Get(&context, request, out);
  });
  if (!record) return std::unexpected(record.error());
  return FromProto(*record);
}

Result<api::ListResponse> ClusterFront::List(uint64_t offset, uint64_t limit) const {
  // Each partition's first offset + limit by id hold the cluster's page: deep pages cost O(offset).
  ListRequest request;
  request.set_offset(0);
  request.set_limit(offset + limit);
  std::vector<ListReply> replies(impl_->partitions.size());
  const std::vector<Status> statuses = Impl::ForEach(replies.size(), [&](uint32_t p) -> Status {
    auto reply = impl_->Call<ListReply>(p, [&](Shard::Stub& stub, grpc::ClientContext& context, ListReply* out) {
      return stub.List(&context, request, out);
    });
    if (!reply) return std::unexpected(reply.error());
    replies[p] = std::move(*reply);
    return Ok();
  });
  for (const Status& status : statuses)
    if (!status) return std::unexpected(status.error());
  api::ListResponse response;
  response.offset = offset;
  response.limit = limit;
  std::vector<index::ImageRecord> all;
  for (const ListReply& reply : replies) {
    response.total += reply.total();
    for (const Record& r : reply.images()) all.push_back(FromProto(r));
  }
  std::sort(all.begin(), all.end(), [](const index::ImageRecord& a, const index::ImageRecord& b) { return a.id < b.id; });
  for (uint64_t i = offset; i < all.size() && response.images.size() < limit; ++i) response.images.push_back(std::move(all[i]));
  return response;
}

Result<api::ServiceStats> ClusterFront::Stats() const {
  std::vector<StatsReply> replies(impl_->partitions.size());
  const std::vector<Status> statuses = Impl::ForEach(replies.size(), [&](uint32_t p) -> Status {
    auto reply = impl_->Call<StatsReply>(p, [&](Shard::Stub& stub, grpc::ClientContext& context, StatsReply* out) {
      return stub.Stats(&context, {}, out);
    });
    if (!reply) return std::unexpected(reply.error());
    replies[p] = *reply;
    return Ok();
  });
  for (const Status& status : statuses)
    if (!status) return std::unexpected(status.error());
  api::ServiceStats stats;
  index::IndexStats& s = stats.index;
  for (const StatsReply& r : replies) {
    s.num_images += r.images();
    s.num_features += r.features();
    s.postings_bytes += r.postings_bytes();
    s.geometry_bytes += r.geometry_bytes();
    s.other_bytes += r.other_bytes();
    s.num_segments += r.segments();
    stats.rss_bytes += r.rss_bytes();
    stats.extractions_in_flight += r.extractions_in_flight();
    stats.max_concurrent_extractions += r.max_concurrent_extractions();
  }
  // As ImageIndex::Stats, over the sums.
  if (s.num_features > 0)
    s.bytes_per_feature = static_cast<double>(s.postings_bytes + s.geometry_bytes + s.other_bytes) / static_cast<double>(s.num_features);
  s.vocabulary_size = impl_->vocabulary.size();
  s.vocabulary_fingerprint = impl_->vocabulary.fingerprint();
  stats.uptime_s = std::chrono::duration<double>(Clock::now() - impl_->opened).count();
  return stats;
}

Result<StatisticsRefresh> ClusterFront::RefreshStatistics() const { return impl_->Refresh(); }

Result<StatisticsRefresh> ClusterFront::Impl::Refresh() const {
  const auto t0 = Clock::now();
  const std::unique_lock<std::shared_mutex> no_writes(refresh_mutex);
  const uint32_t num_partitions = static_cast<uint32_t>(partitions.size());
  // Every replica up, and none behind (no write of this front in flight: the highest is the floor).
  std::vector<std::string> problems;
  for (uint32_t p = 0; p < num_partitions; ++p) {
    std::vector<std::string> why(partitions[p].size());
    const std::vector<int64_t> sequences = PingAll(p, &why);
    const int64_t highest = *std::max_element(sequences.begin(), sequences.end());
    if (highest >= 0) RaiseFloor(p, static_cast<uint64_t>(highest));
    for (size_t r = 0; r < why.size(); ++r) {
      if (!why[r].empty()) problems.push_back(why[r] + " did not answer");
      else if (Behind(*partitions[p][r])) problems.push_back(BehindText(*partitions[p][r]));
    }
  }
  if (!problems.empty())
    return Fail(ErrorCode::kResourceExhausted, "a refresh of the cluster's statistics needs every replica: " +
                                                   Join(problems) + "; nothing changed");
  // The sums of the partitions' live counts, one replica each.
  std::vector<CountsReply> counts(num_partitions);
  const std::vector<Status> statuses = ForEach(num_partitions, [&](uint32_t p) -> Status {
    auto reply = Call<CountsReply>(p, [](Shard::Stub& stub, grpc::ClientContext& context, CountsReply* out) {
      return stub.Counts(&context, {}, out);
    });
    if (!reply) return std::unexpected(reply.error());
    counts[p] = std::move(*reply);
    return Ok();
  });
  for (const Status& status : statuses)
    if (!status) return std::unexpected(status.error());
  PinRequest pin;
  pin.set_vocabulary_fingerprint(vocabulary.fingerprint());
  pin.set_num_partitions(num_partitions);
  std::vector<uint64_t> sums(vocabulary.size(), 0);
  uint64_t images = 0;
  for (uint32_t p = 0; p < num_partitions; ++p) {
    if (counts[p].vocabulary_fingerprint() != vocabulary.fingerprint() ||
        static_cast<size_t>(counts[p].document_frequency_size()) != sums.size())
      return Fail(ErrorCode::kIncompatible, "partition " + std::to_string(p) + " counts another vocabulary's words");
    images += counts[p].images();
    for (size_t w = 0; w < sums.size(); ++w) sums[w] += counts[p].document_frequency(static_cast<int>(w));
  }
  pin.set_images(images);
  for (const uint64_t df : sums) pin.add_document_frequency(static_cast<uint32_t>(std::min<uint64_t>(df, UINT32_MAX)));
  // Every replica stores and pins them.
  std::vector<Replica*> all;
  for (const auto& replicas : partitions)
    for (const auto& replica : replicas) all.push_back(replica.get());
  std::vector<std::string> pinned(all.size());
  std::vector<std::string> failed(all.size());
  ForEach(all.size(), [&](uint32_t k) -> Status {
    PinRequest request = pin;
    request.set_partition(all[k]->partition);
    PinReply reply;
    const grpc::Status status = Invoke<PinReply>(
        *all[k], settings.write_deadline_ms,
        [&](Shard::Stub& stub, grpc::ClientContext& context, PinReply* out) {
          return stub.PinStatistics(&context, request, out);
        },
        &reply);
    if (status.ok()) {
      pinned[k] = all[k]->address;
    } else {
      failed[k] = all[k]->address + " (" + status.error_message() + ")";
    }
    return Ok();
  });
  if (const std::string not_pinned = Join(failed); !not_pinned.empty())
    return Fail(ErrorCode::kResourceExhausted, "the cluster's statistics were refreshed on " + Join(pinned) +
                                                   " but not on " + not_pinned +
                                                   ": partitions score with different statistics until it is repeated");
  writes_since_refresh = 0;
  images_at_refresh = images;
  StatisticsRefresh refresh;
  refresh.images = images;
  refresh.partitions = num_partitions;
  refresh.replicas = static_cast<uint32_t>(all.size());
  refresh.ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
  return refresh;
}

Result<api::AddImageResponse> ClusterFront::Add(const api::AddImageRequest& request) const {
  AddRequest add;
  add.set_id(request.id);
  add.set_image(request.image.data(), request.image.size());
  add.set_metadata_json(request.metadata_json);
  add.set_source_name(log::ToWellFormedUtf8(request.source_name));  // a client's file name, any bytes
  add.set_replace(request.replace);
  const std::lock_guard<std::mutex> lock(impl_->WriteLockOf(request.id));
  auto reply = impl_->WriteAll<AddReply>(impl_->OwnerOf(request.id),
                                         [&](Shard::Stub& stub, grpc::ClientContext& context, AddReply* out) {
                                           return stub.Add(&context, add, out);
                                         });
  if (!reply) return std::unexpected(reply.error());
  api::AddImageResponse response;
  response.record = FromProto(reply->record());
  response.replaced = reply->replaced();
  response.decode_extract_ms = reply->decode_extract_ms();
  response.add_ms = reply->add_ms();
  return response;
}

Status ClusterFront::Delete(const std::string& id) const {
  if (auto s = CheckStorableId(id); !s) return std::unexpected(s.error());
  ImageRequest request;
  request.set_id(id);
  const std::lock_guard<std::mutex> lock(impl_->WriteLockOf(id));
  auto reply = impl_->WriteAll<DeleteReply>(impl_->OwnerOf(id),
                                            [&](Shard::Stub& stub, grpc::ClientContext& context, DeleteReply* out) {
                                              return stub.Delete(&context, request, out);
                                            });
  if (!reply) return std::unexpected(reply.error());
  return Ok();
}

Result<api::AddBatchResponse> ClusterFront::AddBatch(const api::AddBatchRequest& request) const {
  const auto start = std::chrono::steady_clock::now();
  std::vector<std::vector<size_t>> by_partition(impl_->partitions.size());
  for (size_t i = 0; i < request.images.size(); ++i) by_partition[impl_->OwnerOf(request.images[i].id)].push_back(i);
  api::AddBatchResponse response;
  response.results.assign(request.images.size(), Fail(ErrorCode::kInternal, "not processed"));
  std::vector<double> extract_ms(request.images.size(), 0);
  Impl::ForEach(by_partition.size(), [&](uint32_t p) -> Status {
    for (const size_t i : by_partition[p]) {
      const api::AddBatchItem& item = request.images[i];
      api::AddImageRequest add;
      add.id = item.id;
      add.image = item.image;
      add.metadata_json = item.metadata_json;
      add.source_name = item.source_name;
      auto added = Add(add);
      if (added) {
        extract_ms[i] = added->decode_extract_ms;
        response.results[i] = std::move(added->record);
      } else {
        response.results[i] = std::unexpected(added.error());
      }
    }
    return Ok();
  });
  response.decode_extract_ms = std::accumulate(extract_ms.begin(), extract_ms.end(), 0.0);
  response.add_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  return response;
}

Result<std::string> ClusterFront::Thumbnail(const std::string& id, int max_side_px) const {
  if (auto s = CheckStorableId(id); !s) return std::unexpected(s.error());
  ThumbnailRequest request;
  request.set_id(id);
  request.set_max_side_px(max_side_px);
  auto reply = impl_->Call<ThumbnailReply>(
      impl_->OwnerOf(id), [&](Shard::Stub& stub, grpc::ClientContext& context, ThumbnailReply* out) {
        return stub.Thumbnail(&context, request, out);
      });
  if (!reply) return std::unexpected(reply.error());
  return std::move(*reply->mutable_jpeg());
}

Result<std::vector<ClusterFront::PartitionBackup>> ClusterFront::Backup(const std::string& out) const {
  if (!log::IsWellFormedUtf8(out)) {
    return Fail(ErrorCode::kInvalidArgument, "a cluster's backup folder must be a UTF-8 path: the shards are "
                                             "sent it as text");
  }
  std::vector<PartitionBackup> done(impl_->partitions.size());
  const std::vector<Status> statuses = Impl::ForEach(done.size(), [&](uint32_t p) -> Status {
    BackupRequest request;
    request.set_out(out + "/partition-" + std::to_string(p));
    // A backup copies the whole partition: the write deadline, not a search's.
    auto reply = impl_->Call<BackupReply>(
        p, [&](Shard::Stub& stub, grpc::ClientContext& context, BackupReply* answer) {
          return stub.Backup(&context, request, answer);
        }, impl_->settings.write_deadline_ms);
    if (!reply) return std::unexpected(reply.error());
    done[p] = {p, request.out(), {reply->images(), reply->generation(), reply->bytes(), reply->attempts()}};
    return Ok();
  });
  std::string failed;
  // The client's own error (a bad or taken folder, a missing parent), which every partition refuses
  // alike, keeps its code (400, 409, 404); an unreachable partition or a failed copy is kResourceExhausted.
  std::optional<ErrorCode> refused;
  for (uint32_t p = 0; p < statuses.size(); ++p) {
    if (statuses[p]) continue;
    failed += (failed.empty() ? "" : "; ") + std::string("partition ") + std::to_string(p) + ": " +
              statuses[p].error().message;
    const ErrorCode code = statuses[p].error().code;
    const bool clients =
        code == ErrorCode::kInvalidArgument || code == ErrorCode::kAlreadyExists || code == ErrorCode::kNotFound;
    if (!refused) {
      refused = clients ? code : ErrorCode::kResourceExhausted;
    } else if (*refused != code) {
      refused = ErrorCode::kResourceExhausted;
    }
  }
  if (!failed.empty())
    return Fail(refused.value_or(ErrorCode::kResourceExhausted), "the backup is incomplete (" + failed + ")");
  return done;
}

namespace {

using index::search::ImageRef;

// One search over the partitions (index/search/source.h): a ref is (partition, an entry of the
// search's own id table). One call per partition per stage, all partitions at once. A partition that
// fails joins the search's failures: with allow_partial its images answer as removed ones and leave
// the answer (Answered), else the search fails, as it does when every partition failed.
class PartitionsSource final : public index::search::Source {
 public:
  PartitionsSource(const ClusterFront::Impl& front, bool allow_partial)
      : front_(front),
        allow_partial_(allow_partial),
        num_partitions_(front.partitions.size()),
        key_(NewKey()),
        asked_(num_partitions_, 0) {}
  ~PartitionsSource() override {
    for (uint32_t p = 0; p < num_partitions_; ++p) {
      if (failed_.Contains(p)) asked_[p] = 0;  // it may be down: nothing to end there
    }
    front_.EndSearch(key_, asked_);
  }
  PartitionsSource(const PartitionsSource&) = delete;
  PartitionsSource& operator=(const PartitionsSource&) = delete;

  Result<std::optional<ImageRef>> Find(const std::string& id) override {
    return std::optional<ImageRef>(Intern(front_.OwnerOf(id), id));
  }

  Result<index::search::ScoreOutput> Score(const index::search::ScoreInput& input, size_t max_results,
                                           const index::QueryOptions& options) override {
    ScoreRequest request;
    request.mutable_words()->Add(input.words.begin(), input.words.end());
    request.mutable_tf()->Add(input.tf.begin(), input.tf.end());
    if (input.words.empty()) PutTerms({input.terms.begin(), input.terms.end()}, request.mutable_terms());
    request.set_max_results(static_cast<uint32_t>(max_results));
    request.set_max_postings(static_cast<uint64_t>(options.max_scored_postings));
    if (options.filter) request.set_filter(options.filter->Text());
    std::vector<ScoreReply> replies(num_partitions_);
    Scatter([&](uint32_t p) -> Status {
      auto reply = Ask<ScoreReply>(p, [&](Shard::Stub& stub, grpc::ClientContext& context, ScoreReply* out) {
        return stub.Score(&context, request, out);
      });
      if (!reply) return std::unexpected(reply.error());
      replies[p] = std::move(*reply);
      return Ok();
    });
    if (auto s = Check(); !s) return std::unexpected(s.error());
    index::search::ScoreOutput out;
    for (uint32_t p = 0; p < num_partitions_; ++p) {
      if (failed_.Contains(p)) continue;
      out.candidates += replies[p].candidates();
      for (const Scored& s : replies[p].images()) {
        const ImageRef ref = Intern(p, s.id());
        records_[ref] = RecordOf(s);
        out.best.push_back({.ref = ref, .id = s.id(), .score = s.score()});
      }
      // Every partition made the same vector from the cluster's statistics; one that holds no image
      // makes none, so take the longest.
      if (static_cast<size_t>(replies[p].terms_size()) > out.terms.size()) out.terms = TermsFrom(replies[p].terms());
    }
    std::sort(out.best.begin(), out.best.end(), [](const index::search::ScoredRef& a, const index::search::ScoredRef& b) {
      return a.score != b.score ? a.score > b.score : a.id < b.id;
    });
    if (out.best.size() > max_results) out.best.resize(max_results);
    return out;
  }

  void Prefetch(std::span<const index::search::ScoredRef> /*refs*/) override {}  // each shard reads its own

  Result<std::vector<double>> HammingScores(std::span<const uint32_t> words, std::span<const uint64_t> signatures,
                                            std::span<const ImageRef> refs,
                                            const index::QueryOptions& options) override {
    HammingRequest head;
    head.mutable_words()->Add(words.begin(), words.end());
    head.mutable_signatures()->Add(signatures.begin(), signatures.end());
    head.set_threshold(options.hamming_threshold);
    head.set_sigma(options.hamming_sigma);
    head.set_asmk_weight(options.asmk_weight);
    head.set_norm_exponent(options.hamming_norm_exponent);
    std::vector<double> out(refs.size(), std::nan(""));
    const std::vector<std::vector<size_t>> held = ByPartition(refs);
    Scatter([&](uint32_t p) -> Status {
      if (held[p].empty()) return Ok();
      HammingRequest request = head;
      for (size_t k : held[p]) request.add_ids(ids_[refs[k].number]);
      auto reply = Ask<HammingReply>(p, [&](Shard::Stub& stub, grpc::ClientContext& context, HammingReply* r) {
        return stub.Hamming(&context, request, r);
      });
      if (!reply) return std::unexpected(reply.error());
      if (static_cast<size_t>(reply->scores_size()) != held[p].size())
        return Fail(ErrorCode::kInternal, "a shard scored another number of images than asked");
      for (size_t i = 0; i < held[p].size(); ++i) out[held[p][i]] = reply->scores(static_cast<int>(i));
      return Ok();
    });
    if (auto s = Check(); !s) return std::unexpected(s.error());
    return out;
  }

  Result<std::vector<index::search::Verified>> Verify(std::span<const index::search::GeometryQuery> geometries,
                                                      std::span<const index::search::VerifyTask> tasks,
                                                      const index::QueryOptions& options) override {
    std::vector<index::search::Verified> out(tasks.size());
    std::vector<std::vector<size_t>> held(num_partitions_);  // per partition: its tasks
    for (size_t k = 0; k < tasks.size(); ++k) held[tasks[k].ref.part].push_back(k);
    Scatter([&](uint32_t p) -> Status {
      if (held[p].empty()) return Ok();
      // The geometries this partition's tasks use, each sent once, renumbered in the order first used.
      VerifyBatchRequest batch;
      batch.set_max_pairs_per_word(options.max_pairs_per_word);
      batch.set_min_inliers(options.verify.min_inliers);
      batch.set_hamming_threshold(options.hamming_threshold);
      batch.set_max_tentative_matches(options.max_tentative_matches);
      std::map<uint32_t, uint32_t> sent;    // batch index of each geometry sent
      std::vector<uint32_t> original;       // and back
      for (size_t k : held[p]) {
        VerifyTask* task = batch.add_tasks();
        task->set_id(ids_[tasks[k].ref.number]);
        for (const uint32_t g : tasks[k].geometries) {
          if (g >= geometries.size()) return Fail(ErrorCode::kInternal, "a verification of no geometry");
          const auto [it, added] = sent.try_emplace(g, static_cast<uint32_t>(original.size()));
          if (added) {
            original.push_back(g);
            PutGeometry(geometries[g], batch.add_geometries());
          }
          task->add_geometries(it->second);
        }
      }
      auto reply = Ask<VerifyBatchReply>(
          p, [&](Shard::Stub& stub, grpc::ClientContext& context, VerifyBatchReply* r) {
            return stub.VerifyBatch(&context, batch, r);
          });
      if (!reply) return std::unexpected(reply.error());
      if (static_cast<size_t>(reply->outcomes_size()) != held[p].size())
        return Fail(ErrorCode::kInternal, "a shard verified another number of images than asked");
      for (size_t i = 0; i < held[p].size(); ++i) {
        const VerifyOutcome& outcome = reply->outcomes(static_cast<int>(i));
        if (!outcome.found()) continue;
        if (outcome.geometry() >= original.size())
          return Fail(ErrorCode::kInternal, "a shard verified against a geometry it was not sent");
        index::search::Verified& v = out[held[p][i]];
        v.geometry = original[outcome.geometry()];
        const Verification& result = outcome.result();
        v.result.num_inliers = result.inliers();
        v.overlay = result.overlay();
        if (result.verified() && result.db_from_query_size() == 6 && result.db_region_size() == 4) {
          v.result.verified = true;
          v.result.firm = result.firm();
          std::copy(result.db_from_query().begin(), result.db_from_query().end(), v.result.db_from_query.m.begin());
          std::copy(result.db_region().begin(), result.db_region().end(), v.result.db_region.begin());
        }
      }
      return Ok();
    });
    if (auto s = Check(); !s) return std::unexpected(s.error());
    return out;
  }

  Result<std::vector<index::search::RegionFeatures>> Features(std::span<const ImageRef> refs,
                                                              std::span<const std::array<float, 4>> regions,
                                                              const index::search::FeaturesRequest& request) override {
    std::vector<index::search::RegionFeatures> out(refs.size());
    const std::vector<std::vector<size_t>> held = ByPartition(refs);
    Scatter([&](uint32_t p) -> Status {
      if (held[p].empty()) return Ok();
      RegionFeaturesRequest call;
      call.set_max_features(static_cast<uint32_t>(request.max_features));
      call.set_signatures(request.signatures);
      call.set_all_words(request.all_words);
      for (size_t k : held[p]) {
        call.add_ids(ids_[refs[k].number]);
        for (float v : regions[k]) call.add_regions(v);
      }
      auto reply = Ask<RegionFeaturesReply>(
          p, [&](Shard::Stub& stub, grpc::ClientContext& context, RegionFeaturesReply* r) {
            return stub.RegionFeatures(&context, call, r);
          });
      if (!reply) return std::unexpected(reply.error());
      if (static_cast<size_t>(reply->images_size()) != held[p].size())
        return Fail(ErrorCode::kInternal, "a shard gave the features of another number of images than asked");
      for (size_t i = 0; i < held[p].size(); ++i) {
        const ImageFeatures& f = reply->images(static_cast<int>(i));
        if (f.keypoints_size() != f.words_size() * kKeypointValues ||
            (f.signatures_size() != 0 && f.signatures_size() != f.words_size()))
          return Fail(ErrorCode::kInternal, "a shard gave another number of words or signatures than keypoints");
        index::search::RegionFeatures& one = out[held[p][i]];
        one.keypoints = KeypointsFrom(f.keypoints());
        one.words.assign(f.words().begin(), f.words().end());
        one.signatures.assign(f.signatures().begin(), f.signatures().end());
        one.all_words.assign(f.all_words().begin(), f.all_words().end());
      }
      return Ok();
    });
    if (auto s = Check(); !s) return std::unexpected(s.error());
    return out;
  }

  Result<std::vector<std::vector<index::QueryTerm>>> RegionTerms(std::span<const ImageRef> refs,
                                                                 std::span<const std::array<float, 4>> regions) override {
    std::vector<std::vector<index::QueryTerm>> out(refs.size());
    const std::vector<Status> statuses = ClusterFront::Impl::ForEach(refs.size(), [&](uint32_t k) -> Status {
      if (failed_.Contains(refs[k].part)) return Ok();
      RegionTermsRequest request;
      request.set_id(ids_[refs[k].number]);
      for (float v : regions[k]) request.add_region(v);
      auto reply = Ask<RegionTermsReply>(
          refs[k].part, [&](Shard::Stub& stub, grpc::ClientContext& context, RegionTermsReply* r) {
            return stub.RegionTerms(&context, request, r);
          });
      if (!reply) return std::unexpected(reply.error());
      out[k] = TermsFrom(reply->terms());
      return Ok();
    });
    for (size_t k = 0; k < refs.size(); ++k) failed_.Record(refs[k].part, statuses[k]);
    if (auto s = Check(); !s) return std::unexpected(s.error());
    return out;
  }

  Status RankAmong(std::span<const ImageRef> refs) override {
    ranked_.assign(refs.begin(), refs.end());
    return Ok();
  }

  Result<std::vector<std::vector<float>>> ScoreAmong(std::span<const std::vector<uint32_t>> queries) override {
    std::vector<std::vector<float>> out(queries.size(), std::vector<float>(ranked_.size(), 0.0f));
    const std::vector<std::vector<size_t>> held = ByPartition(ranked_);
    ScoreAmongRequest head;
    for (const std::vector<uint32_t>& q : queries) head.add_queries()->mutable_words()->Add(q.begin(), q.end());
    Scatter([&](uint32_t p) -> Status {
      if (held[p].empty()) return Ok();
      ScoreAmongRequest request = head;
      for (size_t k : held[p]) request.add_ids(ids_[ranked_[k].number]);
      auto reply = Ask<ScoreAmongReply>(
          p, [&](Shard::Stub& stub, grpc::ClientContext& context, ScoreAmongReply* r) {
            return stub.ScoreAmong(&context, request, r);
          });
      if (!reply) return std::unexpected(reply.error());
      if (static_cast<size_t>(reply->rows_size()) != queries.size())
        return Fail(ErrorCode::kInternal, "a shard scored another number of queries than asked");
      for (size_t a = 0; a < queries.size(); ++a) {
        const ScoreRow& row = reply->rows(static_cast<int>(a));
        if (static_cast<size_t>(row.scores_size()) != held[p].size())
          return Fail(ErrorCode::kInternal, "a shard scored another number of images than asked");
        for (size_t i = 0; i < held[p].size(); ++i) out[a][held[p][i]] = row.scores(static_cast<int>(i));
      }
      return Ok();
    });
    if (auto s = Check(); !s) return std::unexpected(s.error());
    return out;
  }

  Result<std::vector<index::ImageRecord>> Records(std::span<const ImageRef> refs) override {
    std::vector<index::ImageRecord> out(refs.size());
    for (size_t k = 0; k < refs.size(); ++k) {
      if (const auto it = records_.find(refs[k]); it != records_.end()) {
        out[k] = it->second;
        continue;
      }
      if (failed_.Contains(refs[k].part)) continue;
      ImageRequest request;
      request.set_id(ids_[refs[k].number]);
      auto record = Ask<Record>(refs[k].part, [&](Shard::Stub& stub, grpc::ClientContext& context, Record* r) {
        return stub.Get(&context, request, r);
      });
      if (!record) return std::unexpected(record.error());
      out[k] = FromProto(*record);
      records_[refs[k]] = out[k];
    }
    return out;
  }

  bool Answered(const ImageRef& ref) const override { return !failed_.Contains(ref.part); }

  // Ok unless the partition of image `id` failed during the search (its error then).
  Status Holds(const std::string& id) const {
    if (!failed_.Contains(front_.OwnerOf(id))) return Ok();
    return std::unexpected(FirstError());
  }

  // Which partitions answered every call.
  void Cover(ClusterFront::Coverage* coverage) const {
    if (!coverage) return;
    coverage->total = static_cast<uint32_t>(num_partitions_);
    coverage->failed.assign(failed_.partitions().begin(), failed_.partitions().end());
    coverage->ok = coverage->total - static_cast<uint32_t>(coverage->failed.size());
  }

 private:
  // A call of this search to partition p: it names the search (kSearchKey), so that the shard keeps
  // what the search's earlier calls read.
  template <typename Reply>
  Result<Reply> Ask(uint32_t p, const ClusterFront::Impl::ShardCall<Reply>& call) const {
    asked_[p] = 1;  // each partition's calls come from one thread at a time
    return front_.Call<Reply>(p, [&](Shard::Stub& stub, grpc::ClientContext& context, Reply* out) {
      context.AddMetadata(kSearchKey, key_);
      return call(stub, context, out);
    });
  }

  // 128 random bits in hex: a search's key.
  static std::string NewKey() {
    thread_local std::mt19937_64 random(std::random_device{}());
    char text[33];
    std::snprintf(text, sizeof text, "%016llx%016llx", static_cast<unsigned long long>(random()),
                  static_cast<unsigned long long>(random()));
    return text;
  }

  ImageRef Intern(uint32_t partition, const std::string& id) {
    const auto [it, added] = numbers_.try_emplace(id, static_cast<uint32_t>(ids_.size()));
    if (added) ids_.push_back(id);
    return {.part = partition, .number = it->second};
  }

  // Per partition: the positions of its refs.
  std::vector<std::vector<size_t>> ByPartition(std::span<const ImageRef> refs) const {
    std::vector<std::vector<size_t>> held(num_partitions_);
    for (size_t k = 0; k < refs.size(); ++k) held[refs[k].part].push_back(k);
    return held;
  }

  // fn(p) on every partition that has not failed, all at once; failures recorded.
  void Scatter(const std::function<Status(uint32_t)>& fn) {
    const std::vector<Status> statuses = ClusterFront::Impl::ForEach(num_partitions_, [&](uint32_t p) -> Status {
      if (failed_.Contains(p)) return Ok();
      return fn(p);
    });
    for (uint32_t p = 0; p < statuses.size(); ++p) failed_.Record(p, statuses[p]);
  }

  // After each stage: with failures, the answer is partial (allowed) or none.
  Status Check() const {
    if (failed_.partitions().empty()) return Ok();
    if (!allow_partial_ || failed_.partitions().size() == num_partitions_) return std::unexpected(FirstError());
    return Ok();
  }

  Error FirstError() const {
    return failed_.error().value_or(Error{ErrorCode::kResourceExhausted, "a partition did not answer"});
  }

  static void PutGeometry(const index::search::GeometryQuery& g, Geometry* out) {
    PutKeypoints(g.keypoints, out->mutable_keypoints());
    out->mutable_words()->Add(g.words.begin(), g.words.end());
    out->mutable_signatures()->Add(g.signatures.begin(), g.signatures.end());
    for (float v : g.region) out->add_region(v);
  }

  static index::ImageRecord RecordOf(const Scored& s) {
    index::ImageRecord record;
    record.id = s.id();
    record.width = s.width();
    record.height = s.height();
    record.num_features = s.num_features();
    record.metadata_json = s.metadata_json();
    record.source_path = s.source_path();
    record.added_unix_ms = s.added_unix_ms();
    return record;
  }

  const ClusterFront::Impl& front_;
  const bool allow_partial_;
  const size_t num_partitions_;
  const std::string key_;  // the search's (kSearchKey)
  Failures failed_;
  std::vector<std::string> ids_;                  // by ref number
  std::map<std::string, uint32_t> numbers_;       // ids_ inverted
  std::map<ImageRef, index::ImageRecord> records_;  // those the partitions sent with their scores
  std::vector<ImageRef> ranked_;                  // RankAmong's
  mutable std::vector<uint8_t> asked_;            // per partition: called (EndSearch at the end)
};

}  // namespace

Result<index::QueryResponse> ClusterFront::Query(const sift::FeatureSet& query, const index::QueryOptions& options,
                                                 bool allow_partial, Coverage* coverage) const {
  const auto t0 = Clock::now();
  if (auto s = CheckServed(options); !s) return std::unexpected(s.error());
  if (query.kind != impl_->vocabulary.descriptor_kind())
    return Fail(ErrorCode::kIncompatible, "the query's descriptors are not of the vocabulary's kind");
  if (query.descriptors.size() != query.keypoints.size() * sift::kDescriptorDim || query.image_width <= 0 ||
      query.image_height <= 0)
    return Fail(ErrorCode::kInvalidArgument, "the query: 128 descriptor values per keypoint and a positive size");
  // Quantised once, as index::ImageIndex::Query does.
  vocab::QuantizerOptions quantizer = index::IndexOptions{}.quantizer;
  quantizer.num_threads = impl_->settings.num_threads;
  const index::search::QueryFeatures q = index::search::PrepareQuery(query, impl_->vocabulary, options, quantizer);
  index::QueryTimings timings;
  timings.quantize_ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
  PartitionsSource source(*impl_, allow_partial);
  auto response = index::search::Run(source, q, options, timings);
  source.Cover(coverage);
  if (!response) return response;
  response->timings.total_ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
  return response;
}

Result<api::SearchResponse> ClusterFront::QuerySimilar(const std::string& id, const index::QueryOptions& options,
                                                       bool allow_partial, Coverage* coverage) const {
  const auto t0 = Clock::now();
  if (auto s = CheckServed(options); !s) return std::unexpected(s.error());
  if (auto s = CheckStorableId(id); !s) return std::unexpected(s.error());
  PartitionsSource source(*impl_, allow_partial);
  index::ImageRecord record;
  auto q = index::search::StoredQuery(source, id, options, &record);
  if (q) {
    // The query image's own partition must answer, even when a partial answer is allowed: without it
    // there is no query.
    if (auto s = source.Holds(id); !s) q = std::unexpected(s.error());
  }
  if (!q) {
    source.Cover(coverage);
    return std::unexpected(q.error());
  }
  api::SearchResponse response;
  response.options = options;
  response.query_id = id;
  response.query_width = record.width;
  response.query_height = record.height;
  response.extracted_features = record.num_features;
  auto found = index::search::Run(source, *q, options, index::QueryTimings{});
  source.Cover(coverage);
  if (!found) return std::unexpected(found.error());
  response.index = std::move(*found);
  response.index.timings.total_ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
  response.total_ms = response.index.timings.total_ms;
  return response;
}

}  // namespace oxbow::cluster
