// The front of a cluster (server/README.md, "Operating a cluster"): it holds the vocabulary, prepares a
// query once (region, max_query_features, quantisation, multiple assignment, Hamming-embedding
// signatures: index::search::PrepareQuery) and runs the one search pipeline (index/search/pipeline.h)
// over a Source whose images are the partitions' (index/search/source.h): every stage is one call per
// partition holding images it concerns, all at once (shard.proto), each shard answering with its own
// index (index::ImageIndex::OpenSearch) and the cluster's statistics (pinned, api::PinClusterStatistics):
//   1. Score: every partition scores the query with the filter, if any (each shard applies it while
//      scoring), and returns its best; the front merges them into the global ranking (ties: smaller
//      id first, where a single node takes the smaller image number). Hamming: the owners re-score
//      the shortlist with the query's signatures.
//   2. VerifyBatch: each of the top rerank_depth candidates is verified by the shard that holds it
//      (the geometry stays there).
//   3. Query expansion: the owners give the matched regions' features with their signatures
//      (RegionFeatures; without Hamming embedding their tf-idf vectors, RegionTerms).
//   4. Transitive verification, in rounds: the owners give the anchors' regions (RegionFeatures), the
//      partitions score them against the ranking so far (ScoreAmong), and the candidates' owners
//      verify them against the anchors, attempt after attempt (VerifyBatch).
// Every option of a single node's search is served, with the same defaults; with no write in flight
// the answer (ids, order, scores, verified, inliers, regions, transforms) is the single node's over the
// same images (ties in tf-idf score are broken by id instead of image number).
// QuerySimilar runs the same stages with an indexed image's stored features, which its owner gives
// (the image itself is among the results, as on a single node).
//
// Reads and writes of one image go to its owner, partition api::PartitionOf(id, P) (the function
// `index build --partitions` places images with). Get asks one replica (failover as
// above); List and Stats ask every partition and need them all (kResourceExhausted otherwise: a sum or
// a page without a partition would look complete). Add and Delete are applied on EVERY replica of the
// owner: first every replica must answer Ping within the shard deadline (a replica not seen failing is
// waited for: a failed connection attempt is retried; else kResourceExhausted, nothing written); then the
// first replica applies the write (its refusal, e.g. id taken or undecodable image, is every replica's:
// returned as is, nothing written), then the others at once. A replica that fails after the first
// applied the write leaves the replicas different: kResourceExhausted naming the replicas that applied
// it and those that did not (server/README.md). Writes of one id through this front run one
// at a time (replicas apply them in the same order); two fronts writing one id do not coordinate.
//
// Replicas that missed writes. Every shard answer carries the shard's write sequence (images inserted
// + removed over its index's life, index::ImageIndex::write_sequence; equal on replicas that applied
// the same writes). Per partition the front keeps a floor: a sequence every up-to-date replica has
// reached. It rises after a write that every replica applied (to the smallest sequence they reported),
// and to the highest sequence seen when every replica is asked while no write of this front is in flight
// (at Open, every FrontOptions::replica_check_ms in the background, and before each write). A replica
// below the floor is behind: it missed writes (it was down, restored from an old backup, written to
// directly, or a write failed half-way). It is kept out of reads (an answer that shows it behind is
// dropped and the next replica asked), writes to its partition are refused (kResourceExhausted, nothing
// written), a warning is logged; once it reports the floor again (it was caught up from an up-to-date
// replica, server/README.md) it is used again. Limits: the front compares counts, so replicas
// that applied different writes of the same number look equal; a front that has seen no up-to-date
// replica of a partition since it started cannot know that the ones it sees are behind.
//
// The cluster's statistics (the N and document frequencies every partition scores with, pinned from
// global-frequencies.oxdf) are those of the build until a refresh: RefreshStatistics sums every
// partition's live counts (shard Counts) and has every replica store and pin the sums (PinStatistics;
// the file first, so a restarted shard scores the same). It needs every replica up and none behind, and
// holds this front's writes back while it runs; afterwards, with no write in flight, rankings equal a
// single node's over the same live images again. It runs on demand (POST /v1/admin/refresh-statistics)
// and by itself in the background once the writes through this front since the last refresh reach
// FrontOptions::refresh_fraction of the cluster's images then (the single node's
// statistics_refresh_fraction rule). Between a refresh's first and last pin, partitions score with
// different statistics.
//
// Each partition is asked through one of its replicas, in turn; a replica that fails (unreachable,
// past the deadline) is skipped for the next one of the same partition. A partition none of whose
// replicas answers fails the query with kResourceExhausted (503), or, when partial answers are allowed,
// is left out of it: its images are missing from the ranking and Coverage names it (a query that no
// partition answers fails all the same).
//
// Thread safety: every member may be called from any number of threads at once.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "api/collections.h"
#include "api/service.h"
#include "index/image_index.h"
#include "server/cluster/transport_security.h"
#include "sift/base/error.h"
#include "sift/types.h"

namespace oxbow::cluster {

// cluster.json: {"vocabulary": "V.oxvoc", "partitions": [{"replicas": ["host:port", ...]}, ...]}, and
// optionally:
//   "collections": {"NAME": {"vocabulary": PATH, "public": bool, "max_images": n, "max_bytes": n}, ...}:
//     the collections the front serves (api/collections.h; each shard is then `serve --data DIR` with
//     DIR/NAME/ its partition of NAME). "vocabulary" at the top is the collection "default" (optional
//     when "collections" is given). "public" (default true): reads need no key; the limits (default none)
//     count the images and index bytes of every partition together.
//   "collection_keys": a key file (api/access_keys.h) of the collections' read and write keys, which the
//     front checks and makes (POST /v1/collections/NAME/keys); created when missing.
//   "key_file": a file holding the cluster key the shards require (its whole text, one trailing newline
//     dropped);
//   "tls": {"ca": PEM, "cert": PEM, "key": PEM, "server_name": NAME} to reach the shards over TLS ("ca":
//     the roots to trust, else the system's; "cert" and "key": the front's own certificate, for shards
//     that require one; "server_name": the name the shards' certificates carry, when not the replicas'
//     host; each part optional, `"tls": {}` = TLS with the system's roots).
// Paths are relative to the file's folder unless absolute. Partition k is the k-th entry of "partitions"
// (of every collection).
struct ClusterCollection {
  std::string name;
  std::string vocabulary;
  api::CollectionSettings settings;
};

struct ClusterConfig {
  std::string vocabulary;  // the collection "default"'s; "" when the file names only "collections"
  std::vector<ClusterCollection> collections;  // every collection, "default" (from "vocabulary") included
  std::vector<std::vector<std::string>> partitions;  // per partition, its replicas' gRPC addresses
  std::string collection_keys;  // "collection_keys"; "" = none (only the admin key and public reads)
  FrontSecurity security;  // key (from "key_file") and TLS

  // kNotFound, kInvalidArgument (not JSON, missing fields, a partition without replicas, a collection
  // name that is not valid).
  [[nodiscard]] static Result<ClusterConfig> Read(const std::string& path);
};

struct FrontOptions {
  // Deadline of one call to one shard, milliseconds. [1, 600000].
  int shard_deadline_ms = 5000;
  // Threads that quantise a query's descriptors; 0 = all cores.
  int num_threads = 0;
  // Deadline of one write (Add, Delete) on one replica, milliseconds: an add decodes and extracts on the
  // shard (up to its --processing-timeout-s after waiting for an extraction slot). A write past it may
  // still be applied there. [1, 600000].
  int write_deadline_ms = 60000;
  // How often every replica is asked for its write sequence in the background (see the file comment),
  // milliseconds. [10, 3600000].
  int replica_check_ms = 1000;
  // Refresh the cluster's statistics by itself (see the file comment) once the writes through this front
  // since the last refresh reach this fraction of the cluster's images then; 0: only on demand. [0, 1].
  // The single node's default (index::TfIdfOptions::statistics_refresh_fraction).
  double refresh_fraction = index::TfIdfOptions{}.statistics_refresh_fraction;
};

// What a refresh of the cluster's statistics did.
struct StatisticsRefresh {
  uint64_t images = 0;    // N: live images over the partitions
  uint32_t partitions = 0;
  uint32_t replicas = 0;  // replicas that pinned the new statistics (all of them)
  double ms = 0;
};

// Per replica: calls made, calls failed, and their total latency.
struct ReplicaMetrics {
  uint32_t partition = 0;
  std::string address;
  uint64_t calls = 0;
  uint64_t errors = 0;  // calls that failed (not the shard's refusals of a request, e.g. an unknown id)
  double total_ms = 0;
  int64_t write_sequence = -1;  // the last one it reported; -1 before its first answer
  bool behind = false;          // below its partition's floor (see the file comment)
};

class ClusterFront {
 public:
  // Reads the vocabulary of `collection` (config.collections; for "default", config.vocabulary when
  // the list does not name it) and connects (lazily: a shard down now is tried at the first query).
  // Every call to a shard names the collection (kCollectionKey, proto_convert.h). kNotFound for a
  // collection the config does not name.
  [[nodiscard]] static Result<std::unique_ptr<ClusterFront>> Open(const ClusterConfig& config,
                                                                  const FrontOptions& options = {},
                                                                  const std::string& collection = api::kDefaultCollection);
  ~ClusterFront();
  ClusterFront(const ClusterFront&) = delete;
  ClusterFront& operator=(const ClusterFront&) = delete;

  // Which partitions answered a query.
  struct Coverage {
    uint32_t total = 0;            // partitions in the cluster
    uint32_t ok = 0;               // those that answered every call
    std::vector<uint32_t> failed;  // the others, ascending
  };
  // index::ImageIndex::Query over the cluster (see the file comment). `coverage` (optional) receives
  // which partitions answered.
  [[nodiscard]] Result<index::QueryResponse> Query(const sift::FeatureSet& query, const index::QueryOptions& options,
                                                   bool allow_partial = false, Coverage* coverage = nullptr) const;

  // index::ImageIndex::QuerySimilar over the cluster: the owner gives the image's stored features, then
  // the stages of Query. As api::Service::SearchSimilar (query_id, size, features).
  [[nodiscard]] Result<api::SearchResponse> QuerySimilar(const std::string& id, const index::QueryOptions& options,
                                                         bool allow_partial = false, Coverage* coverage = nullptr) const;

  // api::Service's reads and writes over the cluster (see the file comment). kNotFound for an unknown
  // id, as a single node.
  [[nodiscard]] Result<index::ImageRecord> Get(const std::string& id) const;
  // Live images of every partition ordered by id, [offset, offset + limit); total over the cluster.
  [[nodiscard]] Result<api::ListResponse> List(uint64_t offset, uint64_t limit) const;
  // Sums over the partitions (one replica each): images, features, index bytes, segments, shard memory,
  // extractions in flight and slots; the vocabulary's words and fingerprint; the front's uptime.
  [[nodiscard]] Result<api::ServiceStats> Stats() const;
  // `request.client_gone` is not used: a write once started goes to every replica.
  [[nodiscard]] Result<api::AddImageResponse> Add(const api::AddImageRequest& request) const;
  [[nodiscard]] Status Delete(const std::string& id) const;
  // POST /v1/images/batch over the cluster: the images go to their owners' replicas as Add does, one
  // at a time per partition and the partitions in parallel (one commit per image, not one per batch as
  // on a single node). Per-image results as api::Service::AddImages (an image whose partition cannot be
  // written gets 503); the call itself does not fail.
  [[nodiscard]] Result<api::AddBatchResponse> AddBatch(const api::AddBatchRequest& request) const;
  // api::Service::GetThumbnail, asked of the owner partition (one replica, with failover).
  [[nodiscard]] Result<std::string> Thumbnail(const std::string& id, int max_side_px) const;
  // A backup of every partition (api::Service::Backup) into `out`/partition-k on the machine of the
  // replica that makes it (one per partition, the partitions in parallel); each partition's copy is
  // consistent, but writes between two partitions' snapshots may be in one and not the other. Fails
  // (naming the partitions) when one could not be backed up; the others' copies stay.
  struct PartitionBackup {
    uint32_t partition = 0;
    std::string out;  // its folder
    index::BackupResult result;
  };
  [[nodiscard]] Result<std::vector<PartitionBackup>> Backup(const std::string& out) const;

  // Refreshes the cluster's statistics (see the file comment). kResourceExhausted when a replica does not
  // answer or is behind (nothing changed), or when some replicas pinned and others failed (named; repeat
  // it); kIncompatible when a shard counts another vocabulary's words.
  [[nodiscard]] Result<StatisticsRefresh> RefreshStatistics() const;

  std::vector<ReplicaMetrics> Metrics() const;
  const vocab::Vocabulary& vocabulary() const;
  size_t num_partitions() const;
  const std::string& collection() const;

  class Impl;

 private:
  explicit ClusterFront(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace oxbow::cluster
