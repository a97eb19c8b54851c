// A cluster served by shards and a front (server/README.md, "Operating a cluster"): the same
// images built as one index and as 3 partitions (`index build --mpi --partitions 3`, an MPI singleton),
// each partition served by `oxbow serve --grpc-port`, the front (cluster::ClusterFront) asking them over
// gRPC. With no write in flight the front's rankings equal the single node's: ids, order, scores,
// verified flags and inliers.
#include <gtest/gtest.h>

#include <signal.h>
#include <sys/wait.h>

#include <atomic>
#include <filesystem>
#include <fstream>
#include <regex>
#include <set>
#include <thread>

#include <nlohmann/json.hpp>

#include "api/partition.h"
#include "index/image_index.h"
#include "index/search/source.h"
#include "server/cluster/front.h"
#include "sift/sift.h"
#include "tests/support/samples.h"
// After the project headers: <httplib.h> (through tests/support/e2e.h) defines a `_res` macro that breaks Eigen.
#include "tests/support/e2e.h"
#include "tests/support/temp_dir.h"

namespace oxbow {
namespace {

namespace fs = std::filesystem;
using testing::RunCommand;

constexpr int kPartitions = 3;

class Cluster : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new oxbow::testing::TempDir("oxbow-cluster");
    const std::string images = dir_->path() + "/images";
    fs::create_directories(images);
    // Twelve pictures: crops of four opencv-doc photos at three offsets each (views of one scene verify
    // against each other), so that re-ranking and query expansion have something to do.
    const char* samples[] = {"graf1.png", "box.png", "baboon.jpg", "building.jpg"};
    for (int i = 0; i < 12; ++i) {
      ASSERT_TRUE(cv::imwrite(images + "/img" + std::to_string(i) + ".png",
                              testing::Texture(320, 240, samples[i % 4], 25 * (i / 4), 20 * (i / 4))));
    }
    auto extractor = sift::SiftExtractor::Create(sift::SiftOptions{});
    ASSERT_TRUE(extractor);
    std::vector<float> sample;
    for (int i = 0; i < 12; ++i) {
      auto features = extractor->ExtractFromFile(images + "/img" + std::to_string(i) + ".png");
      ASSERT_TRUE(features);
      sample.insert(sample.end(), features->descriptors.begin(), features->descriptors.end());
      queries_->push_back(std::move(*features));
    }
    // A vocabulary with Hamming-embedding parameters (learnt from the pictures), so that the defaults
    // search with them.
    const std::string vocab = dir_->path() + "/v.oxvoc";
    auto hamming = testing::RandomVocabulary(sift::SiftOptions{}.Describe(), 512)->WithHamming(sample, 1);
    ASSERT_TRUE(hamming);
    ASSERT_TRUE(hamming->Write(vocab));
    Run(std::string(OXBOW_BINARY) + " -q index build --vocab " + vocab + " --images " + images +
        " --threads 1 --out " + dir_->path() + "/single 2>&1");
    Run(std::string(testing::kMpiChildEnvironment) + OXBOW_BINARY + " -q index build --mpi --vocab " + vocab +
        " --images " + images + " --partitions " + std::to_string(kPartitions) + " --threads 1 --out " +
        dir_->path() + "/cluster 2>&1");
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  static void Run(const std::string& command) {
    int code = -1;
    const std::string out = RunCommand(command, &code);
    ASSERT_EQ(code, 0) << command << "\n" << out;
  }

  // `oxbow serve --grpc-port GRPC_PORT` (0: a free one) on partition p (or the index folder `folder`);
  // its gRPC address ("" when it failed).
  std::string StartShard(int p, const std::string& folder = "", int grpc_port = 0) {
    const std::string n = std::to_string(started_++);  // a fresh log (ServerProcess appends)
    shards_.push_back(std::make_unique<testing::ServerProcess>(
        std::vector<std::string>{"serve", "--index",
                                 folder.empty() ? api::PartitionFolder(dir_->path() + "/cluster", p) : folder, "--port", "0",
                                 "--grpc-port", std::to_string(grpc_port), "--index-threads", "1"},
        dir_->path() + "/shard-" + n + ".log"));
    const testing::ServerProcess& shard = *shards_.back();
    EXPECT_TRUE(shard.port() > 0 && shard.WaitReady()) << shard.Log();
    return shard.GrpcAddress();
  }

  // One shard per partition, in `config`.
  void StartCluster(cluster::ClusterConfig* config) {
    config->vocabulary = dir_->path() + "/v.oxvoc";
    for (int p = 0; p < kPartitions; ++p) {
      const std::string address = StartShard(p);
      ASSERT_FALSE(address.empty()) << shards_.back()->Log();
      config->partitions.push_back({address});
    }
  }

  // cluster.json over `partitions` (per partition its replicas' gRPC addresses) and `serve --cluster`.
  std::unique_ptr<testing::ServerProcess> StartFront(const std::vector<std::vector<std::string>>& partitions,
                                                     const std::vector<std::string>& flags = {}) {
    nlohmann::json list = nlohmann::json::array();
    for (const auto& replicas : partitions) list.push_back({{"replicas", replicas}});
    const std::string config = dir_->path() + "/cluster-" + std::to_string(started_++) + ".json";
    std::ofstream(config) << nlohmann::json{{"vocabulary", "v.oxvoc"}, {"partitions", list}}.dump();
    std::vector<std::string> args = {"serve", "--cluster", config, "--port", "0"};
    args.insert(args.end(), flags.begin(), flags.end());
    auto front = std::make_unique<testing::ServerProcess>(args, config + ".log");
    EXPECT_TRUE(front->port() > 0 && front->WaitReady()) << front->Log();
    return front;
  }

  // `serve --index FOLDER` (a single node).
  std::unique_ptr<testing::ServerProcess> StartSingle(const std::string& folder) {
    auto single = std::make_unique<testing::ServerProcess>(
        std::vector<std::string>{"serve", "--index", folder, "--port", "0"},
        dir_->path() + "/single-" + std::to_string(started_++) + ".log");
    EXPECT_TRUE(single->port() > 0 && single->WaitReady()) << single->Log();
    return single;
  }

  // GET `path` on `server`: {status, body as JSON (null when not JSON)}.
  static std::pair<int, nlohmann::json> GetJson(testing::ServerProcess& server, const std::string& path) {
    auto res = server.Client().Get(path);
    if (!res) return {0, nullptr};
    return {res->status, nlohmann::json::parse(res->body, nullptr, false)};
  }

  // An image record of the front against the single node's: every field but added_unix_ms (each
  // index took its own time).
  static void ExpectSameRecord(nlohmann::json single, nlohmann::json front, const std::string& what) {
    ASSERT_TRUE(single.is_object() && front.is_object()) << what;
    single.erase("added_unix_ms");
    front.erase("added_unix_ms");
    EXPECT_EQ(single, front) << what;
  }

  // Search answers (POST /v1/search, GET similar): the query, the counts and every result's fields.
  static void ExpectSameSearch(const nlohmann::json& single, const nlohmann::json& front, const std::string& what) {
    for (const char* field : {"query", "params", "candidates"}) {
      EXPECT_EQ(single.at(field), front.at(field)) << what << ": " << field;
    }
    const auto& a = single["results"];
    const auto& b = front["results"];
    ASSERT_EQ(a.size(), b.size()) << what << "\n" << front.dump();
    for (size_t i = 0; i < a.size(); ++i) {
      for (const char* field :
           {"rank", "id", "score", "verified", "inliers", "via", "transform", "region", "width", "height", "metadata"})
        EXPECT_EQ(a[i][field], b[i][field]) << what << ": " << field << " of rank " << i;
    }
  }

  // The first id stem0, stem1, ... that belongs to `partition`.
  static std::string IdIn(uint32_t partition, const std::string& stem) {
    for (int k = 0;; ++k) {
      std::string id = stem + std::to_string(k);
      if (api::PartitionOf(id, kPartitions) == partition) return id;
    }
  }

  static void ExpectSameRanking(const index::QueryResponse& single, const index::QueryResponse& front,
                                const std::string& what) {
    ASSERT_EQ(single.results.size(), front.results.size()) << what;
    for (size_t i = 0; i < single.results.size(); ++i) {
      const index::QueryResult& a = single.results[i];
      const index::QueryResult& b = front.results[i];
      EXPECT_EQ(a.id, b.id) << what << " rank " << i;
      EXPECT_EQ(a.score, b.score) << what << " rank " << i;
      EXPECT_EQ(a.verified, b.verified) << what << " rank " << i;
      EXPECT_EQ(a.inliers, b.inliers) << what << " rank " << i;
      EXPECT_EQ(a.via, b.via) << what << " rank " << i;
      EXPECT_EQ(a.db_region, b.db_region) << what << " rank " << i;
      EXPECT_EQ(a.record.id, b.record.id) << what << " rank " << i;
      EXPECT_EQ(a.record.num_features, b.record.num_features) << what << " rank " << i;
      EXPECT_EQ(a.record.width, b.record.width) << what << " rank " << i;
    }
    EXPECT_EQ(single.candidates, front.candidates) << what;
  }

  static inline oxbow::testing::TempDir* dir_ = nullptr;
  static inline std::vector<sift::FeatureSet>* queries_ = new std::vector<sift::FeatureSet>;
  static inline int started_ = 0;
  std::vector<std::unique_ptr<testing::ServerProcess>> shards_;
};

// The best 100 tf-idf scores of a bag (distinct words with their counts) on one index, no posting budget.
std::vector<index::search::ScoredRef> TfIdfScores(const index::ImageIndex& idx, std::span<const uint32_t> words,
                                                  std::span<const float> tf) {
  index::QueryOptions options;
  options.max_scored_postings = 0;
  auto scored = idx.OpenSearch()->Score({.words = words, .tf = tf}, 100, options);
  EXPECT_TRUE(scored) << scored.error().ToString();
  return scored ? scored->best : std::vector<index::search::ScoredRef>{};
}

// The hook under the front: a partition that pins the cluster's statistics scores each of its images
// exactly as the single node does; with its own statistics it does not.
TEST_F(Cluster, PartitionsScoreWithTheClusterStatistics) {
  const auto single = index::ImageIndex::Open(dir_->path() + "/single").value();
  for (int p = 0; p < kPartitions; ++p) {
    const std::string folder = api::PartitionFolder(dir_->path() + "/cluster", p);
    const auto partition = index::ImageIndex::Open(folder).value();
    const sift::FeatureSet& query = (*queries_)[static_cast<size_t>(p)];
    std::vector<uint32_t> words(query.size());
    single->vocabulary().Quantize(query.descriptors, words, {});
    const index::BagOfWords bag = index::BagOfWords::FromWords(words);
    const std::vector<float> tf(bag.counts.begin(), bag.counts.end());
    const auto scores_of = [&](const index::ImageIndex& idx) {
      std::map<std::string, float> out;
      for (const auto& s : TfIdfScores(idx, bag.words, tf)) out[s.id] = s.score;
      return out;
    };
    const std::map<std::string, float> everything = scores_of(*single);
    const std::map<std::string, float> own = scores_of(*partition);
    ASSERT_TRUE(api::PinClusterStatistics(folder, *partition));
    const std::map<std::string, float> pinned = scores_of(*partition);
    ASSERT_FALSE(pinned.empty());
    bool differs = false;
    for (const auto& [id, score] : pinned) {
      EXPECT_EQ(score, everything.at(id)) << "partition " << p << " image " << id;
      differs = differs || own.at(id) != score;
    }
    EXPECT_TRUE(differs) << "partition " << p << " scores with its own statistics as with the cluster's";
  }
}

// Pinned statistics stay after a write (the cluster's frequencies describe the cluster as built; a
// partition's own add does not replace them), and the added image is scored with them.
TEST_F(Cluster, PinnedStatisticsStayAfterAWrite) {
  const std::string folder = dir_->path() + "/written-partition";
  fs::copy(api::PartitionFolder(dir_->path() + "/cluster", 1), folder, fs::copy_options::recursive);
  const auto partition = index::ImageIndex::Open(folder).value();
  ASSERT_TRUE(api::PinClusterStatistics(folder, *partition));
  const sift::FeatureSet& query = (*queries_)[1];
  std::vector<uint32_t> words(query.size());
  partition->vocabulary().Quantize(query.descriptors, words, {});
  const index::BagOfWords bag = index::BagOfWords::FromWords(words);
  const std::vector<float> tf(bag.counts.begin(), bag.counts.end());
  const auto scores = [&] {
    std::map<std::string, float> out;
    for (const auto& s : TfIdfScores(*partition, bag.words, tf)) out[s.id] = s.score;
    return out;
  };
  const std::map<std::string, float> before = scores();
  index::ImageInfo info;
  info.extractor_settings = partition->extractor_settings();
  ASSERT_TRUE(partition->Add("added", query, info));
  std::map<std::string, float> after = scores();
  ASSERT_TRUE(after.contains("added"));
  EXPECT_GT(after["added"], 0.99f);  // the query itself, scored with the cluster's statistics
  after.erase("added");
  EXPECT_EQ(before, after) << "a write replaced the cluster's statistics";
}

TEST_F(Cluster, FrontRankingsEqualTheSingleNode) {
  cluster::ClusterConfig config;
  ASSERT_NO_FATAL_FAILURE(StartCluster(&config));
  const auto front = cluster::ClusterFront::Open(config).value();
  const auto single = index::ImageIndex::Open(dir_->path() + "/single").value();

  index::QueryOptions options;  // the defaults: re-ranking, query expansion, transitive verification
  options.top_k = 12;
  index::QueryOptions plain = options;
  plain.query_expansion = false;
  plain.transitive_depth = 0;
  index::QueryOptions region = options;
  region.region = std::array<float, 4>{40, 30, 260, 200};
  // Only the best candidate re-ranked: the other views of its scene can only verify transitively,
  // against it (and against each other in later rounds).
  index::QueryOptions transitive = options;
  transitive.rerank_depth = 1;
  transitive.query_expansion = false;
  index::QueryOptions transitive_qe = transitive;
  transitive_qe.query_expansion = true;
  // A posting budget small enough to drop words of these queries: every partition must drop the words
  // the single node drops (both passes, the first and query expansion's).
  index::QueryOptions budget = options;
  budget.max_scored_postings = 40;
  index::QueryOptions soft = options;
  soft.query_assignments = 2;
  index::QueryOptions asmk = options;  // the aggregated score in the first re-scoring too
  asmk.asmk_weight = 5;
  index::QueryOptions symmetric = options;  // the Hamming score's normalisation, not the default (0.9)
  symmetric.hamming_norm_exponent = 0.5;
  index::QueryOptions tf_idf = options;  // without Hamming embedding: tf-idf query expansion
  tf_idf.hamming = false;
  index::QueryOptions tf_idf_transitive = transitive_qe;
  tf_idf_transitive.hamming = false;
  ASSERT_TRUE(front->vocabulary().has_hamming());
  size_t verified = 0;
  size_t verified_transitively = 0;
  size_t budget_binds = 0;
  for (size_t q = 0; q < queries_->size(); ++q) {
    for (const auto& [name, o] : {std::pair{"default", options}, std::pair{"plain", plain}, std::pair{"region", region},
                                  std::pair{"transitive", transitive}, std::pair{"transitive+qe", transitive_qe},
                                  std::pair{"budget", budget}, std::pair{"query_assignments=2", soft},
                                  std::pair{"asmk_weight=5", asmk},
                                  std::pair{"hamming_norm_exponent=0.5", symmetric},
                                  std::pair{"hamming=false", tf_idf},
                                  std::pair{"hamming=false transitive+qe", tf_idf_transitive}}) {
      const auto expected = single->Query((*queries_)[q], o);
      const auto got = front->Query((*queries_)[q], o);
      ASSERT_TRUE(expected && got) << (got ? "" : got.error().ToString());
      ExpectSameRanking(*expected, *got, std::string(name) + " query " + std::to_string(q));
      if (o.max_scored_postings == budget.max_scored_postings) {
        const auto unlimited = single->Query((*queries_)[q], options);
        ASSERT_TRUE(unlimited);
        budget_binds += got->candidates < unlimited->candidates ? 1 : 0;
      }
      for (size_t i = 0; i < got->results.size(); ++i) {
        const index::QueryResult& r = got->results[i];
        verified += r.verified ? 1 : 0;
        if (o.rerank_depth == 1 && i > 0 && r.verified) {
          ++verified_transitively;
          for (size_t k = 0; k < r.db_from_query.m.size(); ++k)
            EXPECT_NEAR(r.db_from_query.m[k], expected->results[i].db_from_query.m[k], 1e-9) << name << " query " << q;
        }
      }
    }
  }
  // Every image as a query by its stored features (/similar), with the defaults and a region.
  for (int i = 0; i < 12; ++i) {
    const std::string id = "img" + std::to_string(i);
    for (const auto& [name, o] : {std::pair{"similar", options}, std::pair{"similar region", region},
                                  std::pair{"similar transitive", transitive}}) {
      const auto expected = single->QuerySimilar(id, o);
      const auto got = front->QuerySimilar(id, o);
      ASSERT_TRUE(expected && got) << (got ? "" : got.error().ToString());
      ExpectSameRanking(*expected, got->index, std::string(name) + " " + id);
      ASSERT_FALSE(got->index.results.empty());
      EXPECT_EQ(got->index.results[0].id, id);
    }
  }
  const auto unknown = front->QuerySimilar("no-such-image", options);
  ASSERT_FALSE(unknown);
  EXPECT_EQ(unknown.error().code, ErrorCode::kNotFound);
  EXPECT_GT(verified, queries_->size()) << "nothing but the queries themselves verified: the test proves little";
  EXPECT_GE(verified_transitively, queries_->size()) << "transitive verification found little: the test proves little";
  EXPECT_GT(budget_binds, 0u) << "the posting budget dropped no word: the budget case proves little";
  for (const cluster::ReplicaMetrics& m : front->Metrics()) {
    EXPECT_GT(m.calls, 0u) << m.address;
    EXPECT_EQ(m.errors, 0u) << m.address;
  }
}

// A filter the front cannot send to its partitions (one not made by api::ParseFilter, which has no
// text) is refused, never dropped: an unfiltered answer to a filtered search would look valid.
TEST_F(Cluster, FrontRefusesAFilterItCannotSend) {
  cluster::ClusterConfig config;
  ASSERT_NO_FATAL_FAILURE(StartCluster(&config));
  const auto front = cluster::ClusterFront::Open(config).value();
  struct AnyImage : index::ImageFilter {
    bool Matches(const index::ImageRecord&) const override { return true; }
  };
  index::QueryOptions filtered;
  filtered.filter = std::make_shared<AnyImage>();
  const auto got = front->Query((*queries_)[0], filtered);
  ASSERT_FALSE(got);
  EXPECT_EQ(got.error().code, ErrorCode::kInvalidArgument);
  EXPECT_NE(got.error().message.find("filter"), std::string::npos) << got.error().message;
}

// A second shard on the gRPC port of a running one is refused (no SO_REUSEPORT): the kernel would
// otherwise split the front's connections between the two.
TEST_F(Cluster, ASecondShardOnTheSameGrpcPortIsRefused) {
  const std::string first = StartShard(0);
  ASSERT_FALSE(first.empty()) << shards_.back()->Log();
  const testing::ServerProcess& running = *shards_.back();
  const std::string port = first.substr(first.rfind(':') + 1);
  testing::ServerProcess second({"serve", "--index", api::PartitionFolder(dir_->path() + "/cluster", 1), "--port", "0",
                                 "--grpc-port", port, "--index-threads", "1"},
                                dir_->path() + "/shard-" + std::to_string(started_++) + ".log");
  EXPECT_EQ(second.port(), 0) << "a second shard started on gRPC port " << port;
  EXPECT_EQ(second.Wait(), 7) << second.Log();
  EXPECT_NE(second.Log().find("cannot listen for gRPC on 127.0.0.1:" + port), std::string::npos) << second.Log();
  EXPECT_TRUE(running.WaitReady()) << "the first shard stopped serving";
}

TEST_F(Cluster, AReplicaDownChangesNothingAPartitionDownIsPartialOrRefused) {
  cluster::ClusterConfig config;
  ASSERT_NO_FATAL_FAILURE(StartCluster(&config));
  // Partition 0 gets a second replica (a copy of its folder); the first is killed.
  const std::string copy = dir_->path() + "/replica-" + std::to_string(started_);
  fs::copy(api::PartitionFolder(dir_->path() + "/cluster", 0), copy, fs::copy_options::recursive);
  const std::string second = StartShard(0, copy);
  ASSERT_FALSE(second.empty());
  config.partitions[0].push_back(second);
  cluster::FrontOptions front_options;
  front_options.shard_deadline_ms = 2000;
  const auto front = cluster::ClusterFront::Open(config, front_options).value();
  index::QueryOptions options;
  options.transitive_depth = 0;
  const auto before = front->Query((*queries_)[0], options);
  ASSERT_TRUE(before) << before.error().ToString();
  kill(shards_[0]->pid(), SIGKILL);
  for (int repeat = 0; repeat < 3; ++repeat) {  // round-robin reaches the dead replica
    const auto after = front->Query((*queries_)[0], options);
    ASSERT_TRUE(after) << after.error().ToString();
    ExpectSameRanking(*before, *after, "with a replica down");
  }
  // The dead replica failed one call; after that its partition's other replica was asked first.
  for (const cluster::ReplicaMetrics& m : front->Metrics()) {
    if (m.address == config.partitions[0][0]) {
      EXPECT_EQ(m.errors, 1u) << m.address << " of " << m.calls << " calls";
    }
  }
  // Partition 0 entirely down: 503 (kResourceExhausted), or a partial answer without its images.
  kill(shards_[3]->pid(), SIGKILL);
  const auto down = front->Query((*queries_)[0], options);
  ASSERT_FALSE(down);
  EXPECT_EQ(down.error().code, ErrorCode::kResourceExhausted) << down.error().ToString();
  cluster::ClusterFront::Coverage coverage;
  const auto partial = front->Query((*queries_)[0], options, /*allow_partial=*/true, &coverage);
  ASSERT_TRUE(partial) << partial.error().ToString();
  EXPECT_EQ(coverage.total, 3u);
  EXPECT_EQ(coverage.ok, 2u);
  EXPECT_EQ(coverage.failed, std::vector<uint32_t>{0});
  ASSERT_FALSE(partial->results.empty());
  for (const auto& r : partial->results) EXPECT_NE(api::PartitionOf(r.id, kPartitions), 0u) << r.id;
  // /similar of an image of the partition that is down has no query: 503 even when a partial answer is
  // allowed; of an image of another partition, a partial answer.
  std::string on_down, on_up;
  for (int i = 0; i < 12; ++i) {
    const std::string id = "img" + std::to_string(i);
    (api::PartitionOf(id, kPartitions) == 0 ? on_down : on_up) = id;
  }
  ASSERT_FALSE(on_down.empty() || on_up.empty());
  const auto no_query = front->QuerySimilar(on_down, options, /*allow_partial=*/true, &coverage);
  ASSERT_FALSE(no_query);
  EXPECT_EQ(no_query.error().code, ErrorCode::kResourceExhausted) << no_query.error().ToString();
  const auto similar = front->QuerySimilar(on_up, options, /*allow_partial=*/true, &coverage);
  ASSERT_TRUE(similar) << similar.error().ToString();
  EXPECT_EQ(coverage.failed, std::vector<uint32_t>{0});
  ASSERT_FALSE(similar->index.results.empty());
  EXPECT_EQ(similar->index.results[0].id, on_up);
  for (const auto& r : similar->index.results) EXPECT_NE(api::PartitionOf(r.id, kPartitions), 0u) << r.id;

  // A shard that hangs (SIGSTOP) is given up at the deadline, not waited for.
  kill(shards_[1]->pid(), SIGSTOP);
  const auto hung = front->Query((*queries_)[0], options, /*allow_partial=*/true, &coverage);
  kill(shards_[1]->pid(), SIGCONT);
  ASSERT_TRUE(hung) << hung.error().ToString();
  EXPECT_EQ(coverage.failed, (std::vector<uint32_t>{0, 1}));
  for (const auto& r : hung->results) EXPECT_EQ(api::PartitionOf(r.id, kPartitions), 2u) << r.id;
}

// `serve --cluster`: the front's HTTP search answers as a single node's `serve` does; its metrics count
// the shard calls; routes it does not serve yet say so.
TEST_F(Cluster, HttpFrontAnswersAsASingleNodeServer) {
  cluster::ClusterConfig config;
  ASSERT_NO_FATAL_FAILURE(StartCluster(&config));
  const auto front_process = StartFront(config.partitions);
  const auto single_process = StartSingle(dir_->path() + "/single");
  testing::ServerProcess& front = *front_process;
  testing::ServerProcess& single = *single_process;

  const std::string image = testing::FileBytes(dir_->path() + "/images/img5.png");
  const std::string path = "/v1/search?top_k=8";  // the defaults, transitive verification included
  auto expected = single.Client().Post(path, image, "image/png");
  auto got = front.Client().Post(path, image, "image/png");
  ASSERT_TRUE(expected && got);
  ASSERT_EQ(expected->status, 200) << expected->body;
  ASSERT_EQ(got->status, 200) << got->body;
  const auto a = nlohmann::json::parse(expected->body)["results"];
  const auto b = nlohmann::json::parse(got->body)["results"];
  ASSERT_EQ(a.size(), b.size()) << got->body;
  ASSERT_GE(a.size(), 3u);
  for (size_t i = 0; i < a.size(); ++i) {
    for (const char* field : {"id", "score", "verified", "inliers", "via", "region", "width", "height"})
      EXPECT_EQ(a[i][field], b[i][field]) << field << " of rank " << i;
  }
  EXPECT_EQ(nlohmann::json::parse(expected->body)["candidates"], nlohmann::json::parse(got->body)["candidates"]);
  // The image as `curl --data-binary @photo.png` sends it (labelled a form): the same answer.
  auto as_form = front.Client().Post(path, image, "application/x-www-form-urlencoded");
  ASSERT_TRUE(as_form);
  ASSERT_EQ(as_form->status, 200) << as_form->body;
  EXPECT_EQ(nlohmann::json::parse(as_form->body)["results"], b);

  EXPECT_EQ(nlohmann::json::parse(got->body)["partial"], false);
  EXPECT_EQ(nlohmann::json::parse(got->body)["shards"], (nlohmann::json{{"total", 3}, {"ok", 3}, {"failed", nlohmann::json::array()}}));

  // Partition 2 down: a partial answer by default, 503 with allow_partial=false.
  kill(shards_[2]->pid(), SIGKILL);
  auto partial = front.Client().Post(path, image, "image/png");
  ASSERT_TRUE(partial);
  ASSERT_EQ(partial->status, 200) << partial->body;
  const auto body = nlohmann::json::parse(partial->body);
  EXPECT_EQ(body["partial"], true);
  EXPECT_EQ(body["shards"], (nlohmann::json{{"total", 3}, {"ok", 2}, {"failed", {2}}}));
  auto refused = front.Client().Post(path + "&allow_partial=false", image, "image/png");
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->status, 503) << refused->body;

  auto metrics = front.Client().Get("/metrics");
  ASSERT_TRUE(metrics);
  EXPECT_NE(metrics->body.find("oxbow_shard_calls_total{partition=\"2\""), std::string::npos) << metrics->body;
  EXPECT_TRUE(std::regex_search(metrics->body, std::regex(R"(oxbow_shard_errors_total\{partition="2",replica="[^"]+",collection="default"\} [1-9])")))
      << metrics->body;
}

// GET /v1/images/{id}, /v1/images (pages), /v1/stats and /v1/images/{id}/similar through the front
// answer as the single node over the same images; an unknown id is 404 on every route.
TEST_F(Cluster, HttpFrontReadsAnswerAsASingleNodeServer) {
  cluster::ClusterConfig config;
  ASSERT_NO_FATAL_FAILURE(StartCluster(&config));
  const auto front = StartFront(config.partitions);
  const auto single = StartSingle(dir_->path() + "/single");

  const auto [status, all] = GetJson(*single, "/v1/images");
  ASSERT_EQ(status, 200);
  ASSERT_EQ(all["images"].size(), 12u) << all.dump();
  for (const auto& page : {"/v1/images", "/v1/images?limit=5", "/v1/images?offset=3&limit=4", "/v1/images?offset=10",
                           "/v1/images?offset=20"}) {
    const auto [a_status, a] = GetJson(*single, page);
    const auto [b_status, b] = GetJson(*front, page);
    ASSERT_EQ(a_status, 200) << page;
    ASSERT_EQ(b_status, 200) << page << " " << b.dump();
    for (const char* field : {"offset", "limit", "total"}) EXPECT_EQ(a[field], b[field]) << page << ": " << field;
    ASSERT_EQ(a["images"].size(), b["images"].size()) << page;
    for (size_t i = 0; i < a["images"].size(); ++i) ExpectSameRecord(a["images"][i], b["images"][i], page);
  }
  size_t verified_others = 0;
  for (const auto& image : all["images"]) {
    const std::string id = image["id"];
    const auto [a_status, a] = GetJson(*single, "/v1/images/" + id);
    const auto [b_status, b] = GetJson(*front, "/v1/images/" + id);
    ASSERT_EQ(b_status, 200) << b.dump();
    ExpectSameRecord(a, b, id);
    for (const char* params : {"?top_k=12", "?top_k=5&qe=false&transitive_depth=0",
                               "?bbox=40,30,260,200&transitive_depth=0"}) {
      std::string target = "/v1/images/" + id;
      target += "/similar";
      target += params;
      const auto [sa_status, sa] = GetJson(*single, target);
      const auto [sb_status, sb] = GetJson(*front, target);
      ASSERT_EQ(sa_status, 200) << sa.dump();
      ASSERT_EQ(sb_status, 200) << sb.dump();
      ExpectSameSearch(sa, sb, "similar " + target);
      EXPECT_EQ(sb["partial"], false);
      for (const auto& r : sb["results"]) verified_others += r["verified"] == true && r["id"] != id ? 1 : 0;
    }
  }
  EXPECT_GT(verified_others, 0u) << "no image verified another one: the similar comparison proves little";

  const auto [sa_status, sa] = GetJson(*single, "/v1/stats");
  const auto [sb_status, sb] = GetJson(*front, "/v1/stats");
  ASSERT_EQ(sb_status, 200) << sb.dump();
  for (const char* field : {"images", "features", "words", "vocabulary_fingerprint"}) EXPECT_EQ(sa[field], sb[field]) << field;
  for (const auto& [field, value] : sa.items()) EXPECT_TRUE(sb.contains(field)) << field;
  for (const auto& [field, value] : sb.items()) EXPECT_TRUE(sa.contains(field)) << field;

  for (const std::string path : {"/v1/images/no-such-image", "/v1/images/no-such-image/similar"}) {
    const auto [a_status, a] = GetJson(*single, path);
    const auto [b_status, b] = GetJson(*front, path);
    EXPECT_EQ(a_status, 404) << path;
    EXPECT_EQ(b_status, 404) << path << " " << b.dump();
    EXPECT_EQ(b["error"]["code"], "not_found") << b.dump();
  }
  auto deleted = front->Client().Delete("/v1/images/no-such-image");
  ASSERT_TRUE(deleted);
  EXPECT_EQ(deleted->status, 404) << deleted->body;
  // An id that is not UTF-8 (no add takes one, and a shard call could not carry it) is not found, as on
  // a single node, and no replica is counted as failed for it.
  const auto errors_counted = [&] {
    const std::string body = front->Client().Get("/metrics")->body;
    const std::regex line(R"(oxbow_shard_errors_total\{[^}]*\} ([0-9]+))");
    long total = 0;
    for (auto it = std::sregex_iterator(body.begin(), body.end(), line); it != std::sregex_iterator(); ++it)
      total += std::stol((*it)[1].str());
    return total;
  };
  const long errors_before = errors_counted();
  for (const std::string path : {"/v1/images/%FF", "/v1/images/%C3%28/similar", "/v1/images/%FF/thumbnail"}) {
    const auto [a_status, a] = GetJson(*single, path);
    const auto [b_status, b] = GetJson(*front, path);
    EXPECT_EQ(a_status, 404) << path << " " << a.dump();
    EXPECT_EQ(b_status, 404) << path << " " << b.dump();
  }
  EXPECT_EQ(front->Client().Delete("/v1/images/%FF")->status, 404);
  EXPECT_EQ(errors_counted(), errors_before);

  // Thumbnails come from the owner: the single node's bytes.
  for (const auto& image : all["images"]) {
    const std::string target = "/v1/images/" + image["id"].get<std::string>() + "/thumbnail?size=64";
    auto a = single->Client().Get(target);
    auto b = front->Client().Get(target);
    ASSERT_TRUE(a && b);
    ASSERT_EQ(a->status, 200) << a->body;
    ASSERT_EQ(b->status, 200) << target << " " << b->body;
    EXPECT_EQ(b->get_header_value("Content-Type"), "image/jpeg");
    EXPECT_EQ(a->body, b->body) << target;
  }
  EXPECT_EQ(GetJson(*front, "/v1/images/no-such-image/thumbnail").first, 404);
  EXPECT_EQ(GetJson(*front, "/v1/images/img1/thumbnail?size=1").first, 400);

  // POST /v1/match runs at the front (no index needed): the single node's answer.
  const std::string bytes_a = testing::FileBytes(dir_->path() + "/images/img0.png");
  const std::string bytes_b = testing::FileBytes(dir_->path() + "/images/img4.png");
  const httplib::MultipartFormDataItems pair = {{"a", bytes_a, "a.png", "image/png"}, {"b", bytes_b, "b.png", "image/png"}};
  auto ma = single->Client().Post("/v1/match", pair);
  auto mb = front->Client().Post("/v1/match", pair);
  ASSERT_TRUE(ma && mb);
  ASSERT_EQ(ma->status, 200) << ma->body;
  ASSERT_EQ(mb->status, 200) << mb->body;
  nlohmann::json match_a = nlohmann::json::parse(ma->body), match_b = nlohmann::json::parse(mb->body);
  match_a.erase("timings_ms");
  match_b.erase("timings_ms");
  EXPECT_EQ(match_a, match_b);
  EXPECT_GT(match_b["inliers"].get<int>(), 10) << mb->body;

  // The single node's HTTP guards and error bodies: too many headers (431, before httplib reads them),
  // an unknown route (404) and a known route's wrong method (405), each a JSON error.
  httplib::Headers many;
  for (int k = 0; k < 150; ++k) many.emplace("X-Filler-" + std::to_string(k), "1");
  auto crowded = front->Client().Get("/v1/stats", many);
  ASSERT_TRUE(crowded);
  EXPECT_EQ(crowded->status, 431) << crowded->body;
  EXPECT_EQ(nlohmann::json::parse(crowded->body)["error"]["code"], "headers_too_large") << crowded->body;
  auto unknown = front->Client().Get("/v1/nothing-here");
  ASSERT_TRUE(unknown);
  EXPECT_EQ(unknown->status, 404) << unknown->body;
  auto wrong_method = front->Client().Delete("/v1/search");
  ASSERT_TRUE(wrong_method);
  EXPECT_EQ(wrong_method->status, 405) << wrong_method->body;
  EXPECT_EQ(wrong_method->get_header_value("Allow"), "POST");
  // Request ids as a single node (openapi.json: the header on every answer, the same in error bodies).
  auto named = front->Client().Get("/v1/images/no-such-image", {{"X-Request-Id", "front-test-1"}});
  ASSERT_TRUE(named);
  EXPECT_EQ(named->get_header_value("X-Request-Id"), "front-test-1");
  EXPECT_EQ(nlohmann::json::parse(named->body)["error"]["request_id"], "front-test-1");
  EXPECT_FALSE(front->Client().Get("/v1/stats")->get_header_value("X-Request-Id").empty());
}

// POST /v1/images and DELETE /v1/images/{id} through the front land on every replica of the owner
// partition (each shard asked directly) and nowhere else; with a replica of the owner down they answer
// 503 and nothing is written anywhere; a replica that refuses after another applied the write is named.
TEST_F(Cluster, HttpFrontWritesOnEveryReplicaOfTheOwnerPartition) {
  // Writes change the folders: a copy of the cluster (and of the single node), with partition 0 served
  // by two replicas (two copies of its folder).
  const std::string copy = dir_->path() + "/written-" + std::to_string(started_++);
  fs::create_directories(copy);
  fs::copy(dir_->path() + "/cluster", copy + "/cluster", fs::copy_options::recursive);
  fs::copy(dir_->path() + "/single", copy + "/single", fs::copy_options::recursive);
  fs::copy(api::PartitionFolder(copy + "/cluster", 0), copy + "/replica", fs::copy_options::recursive);
  std::vector<std::vector<std::string>> partitions;
  std::vector<std::vector<size_t>> shard_of(kPartitions);  // per partition: its shards_ positions
  for (int p = 0; p < kPartitions; ++p) {
    shard_of[p].push_back(shards_.size());
    partitions.push_back({StartShard(p, api::PartitionFolder(copy + "/cluster", p))});
  }
  shard_of[0].push_back(shards_.size());
  partitions[0].push_back(StartShard(0, copy + "/replica"));
  for (const auto& replicas : partitions)
    for (const std::string& address : replicas) ASSERT_FALSE(address.empty());
  const auto front = StartFront(partitions);
  const auto single = StartSingle(copy + "/single");

  // The image to add (another crop: its own features).
  std::vector<uchar> png;
  ASSERT_TRUE(cv::imencode(".png", testing::Texture(300, 220, "box.png", 60, 40), png));
  const std::string image(png.begin(), png.end());
  const auto add = [&](testing::ServerProcess& server, const std::string& id) {
    httplib::MultipartFormDataItems items = {{"file", image, "new.png", "image/png"},
                                             {"id", id, "", ""},
                                             {"metadata", R"({"kind": "added"})", "", ""}};
    auto res = server.Client().Post("/v1/images", items);
    return res ? std::pair{res->status, nlohmann::json::parse(res->body, nullptr, false)} : std::pair{0, nlohmann::json()};
  };
  // Which shards hold `id` (asked directly, on their own HTTP API).
  const auto holders = [&](const std::string& id) {
    std::vector<size_t> out;
    for (size_t i = 0; i < shards_.size(); ++i) {
      if (kill(shards_[i]->pid(), 0) != 0) continue;
      auto res = shards_[i]->Client().Get("/v1/images/" + id);
      if (res && res->status == 200) out.push_back(i);
    }
    return out;
  };

  // An add lands on both replicas of partition 0 and nowhere else; the answer is the single node's.
  const std::string added = IdIn(0, "added-");
  const auto [a_status, a] = add(*single, added);
  const auto [b_status, b] = add(*front, added);
  ASSERT_EQ(a_status, 201) << a.dump();
  ASSERT_EQ(b_status, 201) << b.dump();
  for (const char* field : {"id", "width", "height", "features", "source", "metadata", "replaced"})
    EXPECT_EQ(a[field], b[field]) << field;
  EXPECT_EQ(holders(added), shard_of[0]);
  ExpectSameRecord(GetJson(*single, "/v1/images/" + added).second, GetJson(*front, "/v1/images/" + added).second, added);
  EXPECT_EQ(GetJson(*front, "/v1/images").second["total"], 13);
  const std::string other = IdIn(2, "added-");
  ASSERT_EQ(add(*front, other).first, 201);
  EXPECT_EQ(holders(other), shard_of[2]);
  EXPECT_EQ(add(*front, other).first, 409);  // taken: refused by the owner, as a single node
  // A file name that is not UTF-8 (a Latin-1 "café.png") is stored as a single node shows it.
  const auto add_named = [&](testing::ServerProcess& server, const std::string& id) {
    httplib::MultipartFormDataItems items = {{"file", image, "caf\xE9.png", "image/png"}, {"id", id, "", ""}};
    auto res = server.Client().Post("/v1/images", items);
    return res ? std::pair{res->status, nlohmann::json::parse(res->body, nullptr, false)} : std::pair{0, nlohmann::json()};
  };
  const std::string latin1 = IdIn(1, "latin1-");
  const auto [la_status, la] = add_named(*single, latin1);
  const auto [lb_status, lb] = add_named(*front, latin1);
  ASSERT_EQ(la_status, 201) << la.dump();
  ASSERT_EQ(lb_status, 201) << lb.dump();
  EXPECT_EQ(la["source"], lb["source"]);
  EXPECT_EQ(holders(latin1), shard_of[1]);
  // The raw image as `curl --data-binary @photo.png` sends it (labelled a form), as a single node takes it.
  auto raw = front->Client().Post("/v1/images?id=" + IdIn(1, "raw-"), image, "application/x-www-form-urlencoded");
  ASSERT_TRUE(raw);
  EXPECT_EQ(raw->status, 201) << raw->body;
  // Location names an id with '?', '#' and a space in a form that reaches it, as on a single node.
  const std::string odd = IdIn(2, "odd?v=2#a b-");
  const std::string odd_encoded = "odd%3Fv%3D2%23a%20b-" + odd.substr(std::string("odd?v=2#a b-").size());
  const std::string location = testing::RawResponseHeader(
      front->port(),
      "POST /v1/images?id=" + odd_encoded + " HTTP/1.1\r\nHost: localhost\r\nContent-Type: image/png\r\n"
      "Content-Length: " + std::to_string(image.size()) + "\r\nConnection: close\r\n\r\n" + image,
      "Location");
  EXPECT_EQ(location, "/v1/images/" + odd_encoded);
  const auto [odd_status, odd_record] = GetJson(*front, location);
  EXPECT_EQ(odd_status, 200) << odd_record.dump();
  EXPECT_EQ(odd_record["id"], odd) << odd_record.dump();

  // A front with an API key asks for it on writes, as a single node: 401 without, 403 with another.
  const auto keyed = StartFront(partitions, {"--api-key", "cluster-key"});
  const std::string key_id = IdIn(2, "keyed-");
  EXPECT_EQ(add(*keyed, key_id).first, 401);
  EXPECT_EQ(keyed->Client().Delete("/v1/images/" + other, {{"X-API-Key", "wrong"}})->status, 403);
  EXPECT_TRUE(holders(key_id).empty());
  EXPECT_EQ(holders(other), shard_of[2]);
  EXPECT_EQ(GetJson(*keyed, "/v1/images/" + other).first, 200);  // reads stay open
  auto with_key = keyed->Client().Delete("/v1/images/" + other, {{"Authorization", "Bearer cluster-key"}});
  ASSERT_TRUE(with_key);
  EXPECT_EQ(with_key->status, 200) << with_key->body;
  EXPECT_TRUE(holders(other).empty());

  // A batch: each image lands on its owner's replicas; per-image results as on a single node (the id
  // taken: 409, the others added).
  const std::vector<std::string> batch_ids = {IdIn(0, "batch-"), IdIn(1, "batch-"), IdIn(2, "batch-"), added};
  httplib::MultipartFormDataItems batch;
  for (const std::string& id : batch_ids) {
    batch.push_back({"image", image, id + ".png", "image/png"});
    batch.push_back({"id", id, "", ""});
  }
  auto batched = front->Client().Post("/v1/images/batch", batch);
  ASSERT_TRUE(batched);
  ASSERT_EQ(batched->status, 200) << batched->body;
  const auto batch_answer = nlohmann::json::parse(batched->body);
  EXPECT_EQ(batch_answer["added"], 3) << batched->body;
  EXPECT_EQ(batch_answer["failed"], 1) << batched->body;
  for (size_t k = 0; k < 3; ++k) {
    EXPECT_EQ(batch_answer["results"][k]["status"], 201) << batched->body;
    EXPECT_EQ(batch_answer["results"][k]["image"]["id"], batch_ids[k]);
    EXPECT_EQ(holders(batch_ids[k]), shard_of[k]) << batch_ids[k];
  }
  EXPECT_EQ(batch_answer["results"][3]["status"], 409) << batched->body;
  EXPECT_EQ(keyed->Client().Post("/v1/images/batch", batch)->status, 401);

  // A backup: every partition into out/partition-k, made by one of its replicas; an admin route (the
  // API key, and refused on a front without one).
  const std::string backup = copy + "/backup";
  const std::string backup_body = R"({"out": ")" + backup + R"("})";
  EXPECT_EQ(front->Client().Post("/v1/admin/backup", backup_body, "application/json")->status, 403);
  auto backed = keyed->Client().Post("/v1/admin/backup", {{"X-API-Key", "cluster-key"}}, backup_body, "application/json");
  ASSERT_TRUE(backed);
  ASSERT_EQ(backed->status, 200) << backed->body;
  const auto backup_answer = nlohmann::json::parse(backed->body);
  ASSERT_EQ(backup_answer["partitions"].size(), 3u) << backed->body;
  int64_t backed_up = 0;
  for (int p = 0; p < kPartitions; ++p) {
    const auto& part = backup_answer["partitions"][p];
    EXPECT_EQ(part["partition"], p);
    EXPECT_EQ(part["out"], api::PartitionFolder(backup, p)) << backed->body;
    EXPECT_TRUE(index::ImageIndex::Exists(api::PartitionFolder(backup, p)));
    // With the cluster's statistics the partition scores with (a restored partition scores as before).
    const auto statistics = api::ReadGlobalFrequencies(
        (fs::path(api::PartitionFolder(backup, p)) / api::kGlobalFrequenciesFile).string());
    ASSERT_TRUE(statistics) << statistics.error().ToString();
    EXPECT_EQ(statistics->partition, static_cast<uint32_t>(p));
    EXPECT_EQ(statistics->num_partitions, static_cast<uint32_t>(kPartitions));
    EXPECT_EQ(part["images"], GetJson(*shards_[shard_of[p][0]], "/v1/stats").second["images"]) << p;
    backed_up += part["images"].get<int64_t>();
  }
  EXPECT_EQ(backed_up, GetJson(*front, "/v1/images").second["total"].get<int64_t>());

  // A delete leaves no replica with the image.
  auto removed = front->Client().Delete("/v1/images/" + added);
  ASSERT_TRUE(removed);
  ASSERT_EQ(removed->status, 200) << removed->body;
  EXPECT_EQ(nlohmann::json::parse(removed->body), (nlohmann::json{{"id", added}, {"deleted", true}}));
  EXPECT_TRUE(holders(added).empty());
  EXPECT_EQ(GetJson(*front, "/v1/images/" + added).first, 404);

  // A replica that already holds the id (it diverged) refuses after the other applied the add: 503
  // naming both. (Each replica took one add directly, so that their write sequences stay equal: with one
  // add the other would be behind, and the front would refuse before writing; see the next test.)
  const std::string diverged = IdIn(0, "diverged-");
  ASSERT_EQ(add(*shards_[shard_of[0][1]], diverged).first, 201);
  ASSERT_EQ(add(*shards_[shard_of[0][0]], IdIn(0, "direct-")).first, 201);
  const auto [d_status, d] = add(*front, diverged);
  EXPECT_EQ(d_status, 503) << d.dump();
  const std::string message = d["error"]["message"];
  EXPECT_NE(message.find("applied on " + partitions[0][0]), std::string::npos) << message;
  EXPECT_NE(message.find("not on " + partitions[0][1]), std::string::npos) << message;
  EXPECT_EQ(holders(diverged), shard_of[0]);

  // A replica of partition 0 down: its writes are refused with 503 and nothing is written anywhere;
  // other partitions still take writes.
  kill(shards_[shard_of[0][1]]->pid(), SIGKILL);
  waitpid(shards_[shard_of[0][1]]->pid(), nullptr, 0);
  const std::string refused = IdIn(0, "refused-");
  const auto [r_status, r] = add(*front, refused);
  EXPECT_EQ(r_status, 503) << r.dump();
  EXPECT_TRUE(holders(refused).empty());
  std::string kept;  // an image of partition 0
  const nlohmann::json listed = GetJson(*front, "/v1/images").second;
  for (const auto& record : listed["images"])
    if (api::PartitionOf(record["id"].get<std::string>(), kPartitions) == 0) kept = record["id"];
  ASSERT_FALSE(kept.empty());
  auto not_removed = front->Client().Delete("/v1/images/" + kept);
  ASSERT_TRUE(not_removed);
  EXPECT_EQ(not_removed->status, 503) << not_removed->body;
  EXPECT_EQ(holders(kept), std::vector<size_t>{shard_of[0][0]});
  EXPECT_EQ(add(*front, IdIn(1, "still-")).first, 201);
}

// After writes the partitions score with the build's statistics, so rankings drift from a single node
// that took the same writes; a refresh (POST /v1/admin/refresh-statistics) makes them equal again, and
// a shard restarted afterwards scores with the refreshed statistics (stored beside its index).
TEST_F(Cluster, RankingsEqualTheSingleNodeAfterWritesAndARefresh) {
  const std::string copy = dir_->path() + "/refresh-" + std::to_string(started_++);
  fs::create_directories(copy);
  fs::copy(dir_->path() + "/cluster", copy + "/cluster", fs::copy_options::recursive);
  fs::copy(dir_->path() + "/single", copy + "/single", fs::copy_options::recursive);
  std::vector<std::vector<std::string>> partitions;
  partitions.reserve(kPartitions);
  const size_t first = shards_.size();
  for (int p = 0; p < kPartitions; ++p) {
    partitions.push_back({StartShard(p, api::PartitionFolder(copy + "/cluster", p))});
    ASSERT_FALSE(partitions.back()[0].empty());
  }
  const auto front = StartFront(partitions, {"--refresh-fraction", "0"});
  const auto single = StartSingle(copy + "/single");
  const auto search = [](testing::ServerProcess& server, const std::string& image) {
    auto res = server.Client().Post("/v1/search?top_k=20&transitive_depth=0", image, "image/png");
    return res && res->status == 200 ? nlohmann::json::parse(res->body) : nlohmann::json();
  };
  std::vector<std::string> queries;
  queries.reserve(3);
  for (int i : {0, 5, 10}) queries.push_back(testing::FileBytes(dir_->path() + "/images/img" + std::to_string(i) + ".png"));
  // The same writes on both: two adds (another crop each) and a delete.
  for (const auto& [id, sample] : {std::pair{"new-a", "box.png"}, std::pair{"new-b", "graf1.png"}}) {
    std::vector<uchar> png;
    ASSERT_TRUE(cv::imencode(".png", testing::Texture(300, 220, sample, 70, 30), png));
    const std::string image(png.begin(), png.end());
    for (testing::ServerProcess* server : {single.get(), front.get()}) {
      auto res = server->Client().Post(std::string("/v1/images?id=") + id + "&metadata=%7B%22kind%22%3A%22new%22%7D",
                                       image, "image/png");
      ASSERT_TRUE(res);
      ASSERT_EQ(res->status, 201) << res->body;
    }
  }
  for (testing::ServerProcess* server : {single.get(), front.get()}) ASSERT_EQ(server->Client().Delete("/v1/images/img3")->status, 200);

  // Before the refresh the scores differ (N and the frequencies are the build's on the partitions).
  bool differs = false;
  for (const std::string& image : queries) {
    const nlohmann::json a = search(*single, image);
    const nlohmann::json b = search(*front, image);
    ASSERT_FALSE(a.is_null() || b.is_null());
    for (size_t i = 0; i < std::min(a["results"].size(), b["results"].size()); ++i)
      differs = differs || a["results"][i]["score"] != b["results"][i]["score"];
  }
  EXPECT_TRUE(differs);

  auto refreshed = front->Client().Post("/v1/admin/refresh-statistics", "", "application/json");
  ASSERT_TRUE(refreshed);
  ASSERT_EQ(refreshed->status, 200) << refreshed->body;
  const nlohmann::json summary = nlohmann::json::parse(refreshed->body);
  EXPECT_EQ(summary["images"], 13);
  EXPECT_EQ(summary["partitions"], kPartitions);
  EXPECT_EQ(summary["replicas"], kPartitions);
  // The front's own admin route is labelled as such in its log line and metrics.
  EXPECT_TRUE(front->WaitForLog("POST /v1/admin/refresh-statistics route=/v1/admin/refresh-statistics status=200"))
      << front->Log();
  const auto metrics = front->Client().Get("/metrics");
  ASSERT_TRUE(metrics);
  EXPECT_NE(metrics->body.find(R"(oxbow_http_requests_total{route="/v1/admin/refresh-statistics",method="POST")"),
            std::string::npos) << metrics->body;
  for (size_t q = 0; q < queries.size(); ++q)
    ExpectSameSearch(search(*single, queries[q]), search(*front, queries[q]), "after the refresh, query " + std::to_string(q));
  // A filtered search (the defaults otherwise): the single node's answer, and only the images it allows.
  const auto filtered = [](testing::ServerProcess& server, const std::string& image) {
    auto res = server.Client().Post("/v1/search?top_k=20&filter=%7B%22kind%22%3A%22new%22%7D", image, "image/png");
    EXPECT_TRUE(res && res->status == 200) << (res ? res->body : "no answer");
    return res && res->status == 200 ? nlohmann::json::parse(res->body) : nlohmann::json();
  };
  size_t allowed = 0;
  for (size_t q = 0; q < queries.size(); ++q) {
    const nlohmann::json a = filtered(*single, queries[q]);
    const nlohmann::json b = filtered(*front, queries[q]);
    ASSERT_FALSE(a.is_null() || b.is_null());
    ExpectSameSearch(a, b, "filtered, query " + std::to_string(q));
    for (const auto& r : b["results"]) {
      EXPECT_EQ(r["metadata"], (nlohmann::json{{"kind", "new"}})) << r.dump();
      ++allowed;
    }
  }
  EXPECT_GT(allowed, 0u) << "the filter allowed nothing: the filtered case proves little";

  // A shard restarted on its folder scores with the refreshed statistics.
  const std::string restarted = partitions[1][0];
  kill(shards_[first + 1]->pid(), SIGKILL);
  waitpid(shards_[first + 1]->pid(), nullptr, 0);
  ASSERT_EQ(StartShard(1, api::PartitionFolder(copy + "/cluster", 1), std::stoi(restarted.substr(restarted.rfind(':') + 1))),
            restarted);
  nlohmann::json again;
  for (int wait = 0; wait < 200; ++wait) {  // until the front has reconnected to it
    again = search(*front, queries[0]);
    if (!again.is_null() && again["partial"] == false) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  ExpectSameSearch(search(*single, queries[0]), again, "after a shard restart");
}

// The value of a front metric for one replica (-1 when absent).
double ReplicaMetric(const std::string& metrics, const std::string& name, int partition, const std::string& address) {
  const std::string key =
      name + "{partition=\"" + std::to_string(partition) + "\",replica=\"" + address + "\",collection=\"default\"} ";
  const size_t at = metrics.find(key);
  return at == std::string::npos ? -1 : std::stod(metrics.substr(at + key.size()));
}

// A replica that missed writes (here: it came back from a copy taken before two adds) is detected by its
// write sequence: reads never use it, writes to its partition are refused with 503 and nothing written;
// once caught up from an up-to-date replica (`oxbow index backup` of it, served on the same address) it
// is used again (server/README.md, "Operating a cluster").
TEST_F(Cluster, AReplicaThatMissedWritesIsKeptOutOfReadsUntilItCatchesUp) {
  const std::string copy = dir_->path() + "/stale-" + std::to_string(started_++);
  fs::create_directories(copy);
  fs::copy(dir_->path() + "/cluster", copy + "/cluster", fs::copy_options::recursive);
  fs::copy(api::PartitionFolder(copy + "/cluster", 0), copy + "/replica", fs::copy_options::recursive);
  std::vector<std::vector<std::string>> partitions;
  partitions.reserve(kPartitions);
  const size_t first = shards_.size();  // partition 0's first replica
  for (int p = 0; p < kPartitions; ++p) partitions.push_back({StartShard(p, api::PartitionFolder(copy + "/cluster", p))});
  size_t second = shards_.size();
  partitions[0].push_back(StartShard(0, copy + "/replica"));
  for (const auto& replicas : partitions)
    for (const std::string& address : replicas) ASSERT_FALSE(address.empty());
  const std::string stale = partitions[0][1];
  const int stale_port = std::stoi(stale.substr(stale.rfind(':') + 1));
  // No background check (the reads below must find the replica behind by themselves) and no background
  // refresh of the statistics (its calls would blur the count of reads below).
  const auto front = StartFront(partitions, {"--replica-check-ms", "600000", "--refresh-fraction", "0"});
  // The second replica as it is now, copied while it serves.
  Run(std::string(OXBOW_BINARY) + " -q index backup --index " + copy + "/replica --out " + copy + "/old 2>&1");

  std::vector<uchar> png;
  ASSERT_TRUE(cv::imencode(".png", testing::Texture(300, 220, "baboon.jpg", 60, 40), png));
  const std::string image(png.begin(), png.end());
  const auto add = [&](testing::ServerProcess& server, const std::string& id) {
    auto res = server.Client().Post("/v1/images?id=" + id, image, "image/png");
    return res ? std::pair{res->status, res->body} : std::pair{0, std::string()};
  };
  const auto metrics = [&] {
    auto res = front->Client().Get("/metrics");
    return res ? res->body : std::string();
  };
  const std::string added = IdIn(0, "late-");
  const std::string also = IdIn(0, "later-");
  ASSERT_EQ(add(*front, added).first, 201);
  ASSERT_EQ(add(*front, also).first, 201);

  // The second replica comes back from the old copy, on its address: it missed both adds.
  kill(shards_[second]->pid(), SIGKILL);
  waitpid(shards_[second]->pid(), nullptr, 0);
  second = shards_.size();
  ASSERT_EQ(StartShard(0, copy + "/old", stale_port), stale);
  EXPECT_EQ(shards_[second]->Client().Get("/v1/images/" + added)->status, 404);  // it really lacks them
  // From its first answer on (once the front has reconnected to it), reads see it behind: even its
  // refusals (it lacks the image: 404) are dropped and the other replica answers.
  std::string seen;
  for (int wait = 0; wait < 200 && ReplicaMetric(seen, "oxbow_shard_behind", 0, stale) != 1; ++wait) {
    EXPECT_EQ(GetJson(*front, "/v1/images/" + added).first, 200) << "read " << wait;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    seen = metrics();
  }
  ASSERT_EQ(ReplicaMetric(seen, "oxbow_shard_behind", 0, stale), 1) << seen;
  EXPECT_EQ(ReplicaMetric(seen, "oxbow_shard_behind", 0, partitions[0][0]), 0) << seen;
  EXPECT_LT(ReplicaMetric(seen, "oxbow_shard_write_sequence", 0, stale),
            ReplicaMetric(seen, "oxbow_shard_write_sequence", 0, partitions[0][0]));
  EXPECT_NE(front->Log().find("replica " + stale + " of partition 0 is behind"), std::string::npos) << front->Log();

  // Reads never ask it: every get and search finds the adds (round-robin would ask it every other time).
  const double calls_before = ReplicaMetric(seen, "oxbow_shard_calls_total", 0, stale);
  for (int k = 0; k < 4; ++k) {
    for (const std::string& id : {added, also}) EXPECT_EQ(GetJson(*front, "/v1/images/" + id).first, 200) << id;
    auto found = front->Client().Post("/v1/search?top_k=20&transitive_depth=0", image, "image/png");
    ASSERT_TRUE(found);
    ASSERT_EQ(found->status, 200) << found->body;
    const nlohmann::json answer = nlohmann::json::parse(found->body);
    std::set<std::string> ids;
    for (const auto& r : answer["results"]) ids.insert(r["id"].get<std::string>());
    EXPECT_TRUE(ids.contains(added) && ids.contains(also)) << found->body;
  }
  EXPECT_EQ(GetJson(*front, "/v1/images").second["total"], 14);
  EXPECT_EQ(ReplicaMetric(metrics(), "oxbow_shard_calls_total", 0, stale), calls_before);

  // Writes to partition 0 are refused, naming it, and nothing is written; other partitions take writes.
  const std::string refused = IdIn(0, "refused-");
  const auto [r_status, r_body] = add(*front, refused);
  EXPECT_EQ(r_status, 503) << r_body;
  EXPECT_NE(r_body.find(stale), std::string::npos) << r_body;
  EXPECT_NE(r_body.find("missed writes"), std::string::npos) << r_body;
  EXPECT_EQ(shards_[first]->Client().Get("/v1/images/" + refused)->status, 404);
  EXPECT_EQ(shards_[second]->Client().Get("/v1/images/" + refused)->status, 404);
  EXPECT_EQ(add(*front, IdIn(1, "elsewhere-")).first, 201);

  // Caught up: a copy of the up-to-date replica, served on its address. It is used again.
  kill(shards_[second]->pid(), SIGKILL);
  waitpid(shards_[second]->pid(), nullptr, 0);
  Run(std::string(OXBOW_BINARY) + " -q index backup --index " + api::PartitionFolder(copy + "/cluster", 0) + " --out " +
      copy + "/caught-up 2>&1");
  second = shards_.size();
  ASSERT_EQ(StartShard(0, copy + "/caught-up", stale_port), stale);
  const std::string after = IdIn(0, "after-");
  std::pair<int, std::string> written;
  for (int wait = 0; wait < 200; ++wait) {  // 503 (nothing written) until the front reconnects to it
    written = add(*front, after);
    if (written.first != 503) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  EXPECT_EQ(written.first, 201) << written.second;
  EXPECT_EQ(shards_[second]->Client().Get("/v1/images/" + after)->status, 200);
  EXPECT_EQ(shards_[second]->Client().Get("/v1/images/" + added)->status, 200);
  seen = metrics();
  EXPECT_EQ(ReplicaMetric(seen, "oxbow_shard_behind", 0, stale), 0) << seen;
  const double calls_caught_up = ReplicaMetric(seen, "oxbow_shard_calls_total", 0, stale);
  for (int k = 0; k < 4; ++k) EXPECT_EQ(GetJson(*front, "/v1/images/" + added).first, 200);
  EXPECT_GT(ReplicaMetric(metrics(), "oxbow_shard_calls_total", 0, stale), calls_caught_up);
  EXPECT_NE(front->Log().find("replica " + stale + " of partition 0 has caught up"), std::string::npos) << front->Log();
}

// Reads that overlap a write on a partition with one replica are answered, never refused as "behind":
// a replica is behind only when it answers below the floor its partition had when the read started.
TEST_F(Cluster, ReadsDuringWritesAreAnsweredWithoutAFault) {
  const std::string copy = dir_->path() + "/overlap-" + std::to_string(started_++);
  fs::create_directories(copy);
  fs::copy(dir_->path() + "/cluster", copy + "/cluster", fs::copy_options::recursive);
  std::vector<std::vector<std::string>> partitions;
  partitions.reserve(kPartitions);
  for (int p = 0; p < kPartitions; ++p) partitions.push_back({StartShard(p, api::PartitionFolder(copy + "/cluster", p))});
  for (const auto& replicas : partitions) ASSERT_FALSE(replicas[0].empty());
  const auto front = StartFront(partitions, {"--refresh-fraction", "0"});
  std::string stable;  // an image of partition 0 that no write touches
  for (int i = 0; i < 12 && stable.empty(); ++i)
    if (api::PartitionOf("img" + std::to_string(i), kPartitions) == 0) stable = "img" + std::to_string(i);
  ASSERT_FALSE(stable.empty());
  std::vector<uchar> png;
  ASSERT_TRUE(cv::imencode(".png", testing::Texture(300, 220, "box.png", 30, 20), png));
  const std::string image(png.begin(), png.end());
  const std::string churned = IdIn(0, "churn-");

  std::atomic<bool> done{false};
  std::atomic<int> writes{0};
  std::thread writer([&] {
    auto client = front->Client();
    for (int k = 0; k < 400 && !done; ++k) {
      auto res = (k % 3 == 2) ? client.Delete("/v1/images/" + churned)
                              : client.Post("/v1/images?replace=true&id=" + churned, image, "image/png");
      if (res && (res->status == 200 || res->status == 201)) ++writes;
    }
  });
  int reads = 0;
  std::vector<std::string> faults;
  auto client = front->Client();
  const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(4);
  while (std::chrono::steady_clock::now() < end && faults.size() < 5) {
    auto got = client.Get("/v1/images/" + stable);
    if (!got || got->status != 200) faults.push_back(got ? got->body : "no answer");
    auto similar = client.Get("/v1/images/" + stable + "/similar?rerank=0");
    if (!similar || similar->status != 200) {
      faults.push_back(similar ? similar->body : "no answer");
    } else if (nlohmann::json::parse(similar->body).value("partial", false)) {
      faults.push_back("partial: " + similar->body.substr(0, 200));
    }
    reads += 2;
  }
  done = true;
  writer.join();
  EXPECT_GT(writes.load(), 0);
  EXPECT_GT(reads, 0);
  EXPECT_TRUE(faults.empty()) << faults.size() << " of " << reads << " reads failed during " << writes.load()
                              << " writes; first: " << (faults.empty() ? "" : faults[0]);
}

// Collections over a cluster: every shard serves --data DIR with its partition of each collection
// (DIR/photos/ = partition k of the cluster built above; DIR/other/ an empty one with another
// vocabulary); the front serves the collections cluster.json names, each searched with its own
// vocabulary and partitions, with per-collection keys, public and private reads and limits.
TEST_F(Cluster, HttpFrontServesCollectionsWithTheirKeysAndLimits) {
  const std::string other_vocab = dir_->path() + "/v-other.oxvoc";
  ASSERT_TRUE(testing::RandomVocabulary(sift::SiftOptions{}.Describe(), 256)->Write(other_vocab));
  nlohmann::json partitions = nlohmann::json::array();
  for (int p = 0; p < kPartitions; ++p) {
    const std::string data = dir_->path() + "/data-" + std::to_string(p);
    fs::create_directories(data);
    fs::copy(api::PartitionFolder(dir_->path() + "/cluster", p), data + "/photos", fs::copy_options::recursive);
    const std::string n = std::to_string(started_++);
    shards_.push_back(std::make_unique<testing::ServerProcess>(
        std::vector<std::string>{"serve", "--data", data, "--port", "0", "--grpc-port", "0", "--index-threads", "1",
                                 "--api-key", "admin"},
        dir_->path() + "/shard-" + n + ".log"));
    testing::ServerProcess& shard = *shards_.back();
    ASSERT_TRUE(shard.port() > 0 && shard.WaitReady()) << shard.Log();
    httplib::Headers admin = {{"X-API-Key", "admin"}};
    auto created = shard.Client().Post("/v1/collections", admin,
                                       nlohmann::json{{"name", "other"}, {"vocabulary", other_vocab}}.dump(),
                                       "application/json");
    ASSERT_TRUE(created);
    ASSERT_EQ(created->status, 201) << created->body;
    const std::string address = shard.GrpcAddress();
    ASSERT_FALSE(address.empty()) << shard.Log();
    partitions.push_back({{"replicas", {address}}});
  }
  const std::string config = dir_->path() + "/collections-cluster.json";
  std::ofstream(config) << nlohmann::json{
      {"partitions", partitions},
      {"collections",
       {{"photos", {{"vocabulary", "v.oxvoc"}}},
        {"other", {{"vocabulary", "v-other.oxvoc"}, {"public", false}, {"max_images", 2}}}}},
      {"collection_keys", "front-keys.json"}}.dump();
  testing::ServerProcess front({"serve", "--cluster", config, "--port", "0", "--api-key", "admin"}, config + ".log");
  ASSERT_TRUE(front.port() > 0 && front.WaitReady()) << front.Log();
  const auto single_process = StartSingle(dir_->path() + "/single");
  const httplib::Headers admin = {{"X-API-Key", "admin"}};

  // The list: the public collection to anyone, both to the admin key.
  auto listed = front.Client().Get("/v1/collections");
  ASSERT_TRUE(listed);
  ASSERT_EQ(listed->status, 200) << listed->body;
  auto names = [](const std::string& body) {
    std::set<std::string> out;
    const nlohmann::json parsed = nlohmann::json::parse(body);
    for (const auto& c : parsed["collections"]) out.insert(c["name"].get<std::string>());
    return out;
  };
  EXPECT_EQ(names(listed->body), (std::set<std::string>{"photos"})) << listed->body;
  listed = front.Client().Get("/v1/collections", admin);
  ASSERT_TRUE(listed && listed->status == 200);
  EXPECT_EQ(names(listed->body), (std::set<std::string>{"other", "photos"}));
  auto described = front.Client().Get("/v1/collections/photos");
  ASSERT_TRUE(described);
  ASSERT_EQ(described->status, 200) << described->body;
  EXPECT_EQ(nlohmann::json::parse(described->body)["images"], 12);
  EXPECT_EQ(nlohmann::json::parse(described->body)["partitions"], kPartitions);

  // A search of the partitioned collection answers as the single node over the same images.
  const std::string image = testing::FileBytes(dir_->path() + "/images/img5.png");
  auto expected = single_process->Client().Post("/v1/search?top_k=8", image, "image/png");
  auto got = front.Client().Post("/v1/collections/photos/search?top_k=8", image, "image/png");
  ASSERT_TRUE(expected && got);
  ASSERT_EQ(got->status, 200) << got->body;
  ASSERT_GE(nlohmann::json::parse(got->body)["results"].size(), 3u) << got->body;
  ExpectSameSearch(nlohmann::json::parse(expected->body), nlohmann::json::parse(got->body), "collection photos");
  // No collection "default" in this cluster: 404 to the admin key, 401 without a key (as a private one).
  auto no_default = front.Client().Post("/v1/search", admin, image, "image/png");
  ASSERT_TRUE(no_default);
  EXPECT_EQ(no_default->status, 404) << no_default->body;
  no_default = front.Client().Post("/v1/search", image, "image/png");
  ASSERT_TRUE(no_default);
  EXPECT_EQ(no_default->status, 401) << no_default->body;

  // Keys of the private collection: made by the admin on the front; a write key writes and reads it, a
  // read key of another collection gets 403 with the answer an unknown collection gets.
  const auto make_key = [&](const std::string& collection, const std::string& access) {
    auto made = front.Client().Post("/v1/collections/" + collection + "/keys", admin,
                                    nlohmann::json{{"access", access}}.dump(), "application/json");
    EXPECT_TRUE(made && made->status == 201) << (made ? made->body : "no answer");
    return made ? nlohmann::json::parse(made->body).value("key", "") : "";
  };
  const std::string writer = make_key("other", "write");
  const std::string photos_reader = make_key("photos", "read");
  ASSERT_FALSE(writer.empty());
  ASSERT_FALSE(photos_reader.empty());
  EXPECT_NE(fs::file_size(dir_->path() + "/front-keys.json"), 0u);
  const std::string image0 = testing::FileBytes(dir_->path() + "/images/img0.png");
  const auto add = [&](const std::string& id, const std::string& key, const std::string& bytes) {
    httplib::Headers headers;
    if (!key.empty()) headers.insert({"X-API-Key", key});
    auto res = front.Client().Post("/v1/collections/other/images?id=" + id, headers, bytes, "image/png");
    return res ? res->status : 0;
  };
  EXPECT_EQ(add("a", "", image), 401);
  EXPECT_EQ(add("a", photos_reader, image), 403);
  EXPECT_EQ(add("a", writer, image), 201);
  EXPECT_EQ(add("b", writer, image0), 201);
  EXPECT_EQ(add("c", writer, image0), 507);  // max_images 2 over the partitions
  const auto images_of = [&](const std::string& collection, const std::string& key) {
    httplib::Headers headers;
    if (!key.empty()) headers.insert({"X-API-Key", key});
    return front.Client().Get("/v1/collections/" + collection + "/images", headers);
  };
  auto other_images = images_of("other", writer);
  ASSERT_TRUE(other_images);
  ASSERT_EQ(other_images->status, 200) << other_images->body;
  EXPECT_EQ(nlohmann::json::parse(other_images->body)["total"], 2);
  auto refused = images_of("other", photos_reader);
  auto unknown = images_of("nope", photos_reader);
  ASSERT_TRUE(refused && unknown);
  EXPECT_EQ(refused->status, 403);
  EXPECT_EQ(unknown->status, 403);
  // The same answer apart from the name, whether or not the collection exists.
  EXPECT_EQ(nlohmann::json::parse(refused->body)["error"]["code"], nlohmann::json::parse(unknown->body)["error"]["code"]);
  EXPECT_EQ(front.Client().Get("/v1/collections/nope", admin)->status, 404);
  // The photos collection did not get other's images, and reads of it need no key.
  auto photos_images = images_of("photos", "");
  ASSERT_TRUE(photos_images && photos_images->status == 200);
  EXPECT_EQ(nlohmann::json::parse(photos_images->body)["total"], 12);
  // The other collection searched with its own vocabulary (after a refresh of its statistics: each
  // partition holds at most one of its images) finds its image first.
  auto refreshed = front.Client().Post("/v1/collections/other/admin/refresh-statistics", {{"X-API-Key", writer}}, "",
                                       "application/json");
  ASSERT_TRUE(refreshed);
  ASSERT_EQ(refreshed->status, 200) << refreshed->body;
  EXPECT_EQ(nlohmann::json::parse(refreshed->body)["images"], 2);
  auto other_search = front.Client().Post("/v1/collections/other/search?top_k=2", {{"X-API-Key", writer}}, image, "image/png");
  ASSERT_TRUE(other_search);
  ASSERT_EQ(other_search->status, 200) << other_search->body;
  const auto other_results = nlohmann::json::parse(other_search->body)["results"];
  ASSERT_FALSE(other_results.empty()) << other_search->body;
  EXPECT_EQ(other_results[0]["id"], "a");
  auto other_stats = front.Client().Get("/v1/collections/other/stats", {{"X-API-Key", writer}});
  ASSERT_TRUE(other_stats && other_stats->status == 200);
  EXPECT_EQ(nlohmann::json::parse(other_stats->body)["words"], 256);

  // A cluster's collections are those of cluster.json: create and delete are refused (409), and only
  // the admin key learns that.
  auto create = front.Client().Post("/v1/collections", admin, R"({"name": "new"})", "application/json");
  ASSERT_TRUE(create);
  EXPECT_EQ(create->status, 409) << create->body;
  auto remove = front.Client().Delete("/v1/collections/photos", {{"X-API-Key", writer}});
  ASSERT_TRUE(remove);
  EXPECT_EQ(remove->status, 403) << remove->body;

  auto metrics = front.Client().Get("/metrics");
  ASSERT_TRUE(metrics);
  EXPECT_TRUE(std::regex_search(metrics->body,
                                std::regex(R"(oxbow_shard_calls_total\{partition="0",replica="[^"]+",collection="other"\} [1-9])")))
      << metrics->body;

  // The front's key file is re-read on SIGHUP: keys removed by hand stop working.
  std::ofstream(dir_->path() + "/front-keys.json", std::ios::trunc) << R"({"keys": []})";
  front.Signal(SIGHUP);
  EXPECT_TRUE(front.WaitForLog("re-read the collections' key file")) << front.Log();
  EXPECT_EQ(add("d", writer, image0), 403);
  auto revoked = images_of("other", writer);
  ASSERT_TRUE(revoked);
  EXPECT_EQ(revoked->status, 403) << revoked->body;
}

TEST(ClusterConfigFile, ReadsReplicasAndResolvesTheVocabularyBesideIt) {
  oxbow::testing::TempDir dir("oxbow-cluster-config");
  const std::string path = dir.path() + "/cluster.json";
  std::ofstream(path) << R"({"vocabulary": "v.oxvoc", "partitions": [{"replicas": ["a:1", "b:2"]}, {"replicas": ["c:3"]}]})";
  const auto config = cluster::ClusterConfig::Read(path);
  ASSERT_TRUE(config) << config.error().ToString();
  EXPECT_EQ(config->vocabulary, dir.path() + "/v.oxvoc");
  ASSERT_EQ(config->partitions.size(), 2u);
  EXPECT_EQ(config->partitions[0], (std::vector<std::string>{"a:1", "b:2"}));
  std::ofstream(path) << R"({"vocabulary": "v.oxvoc", "partitions": [{"replicas": []}]})";
  EXPECT_EQ(cluster::ClusterConfig::Read(path).error().code, ErrorCode::kInvalidArgument);
  // Collections: each with its vocabulary and settings; "default" from the top-level vocabulary.
  std::ofstream(path) << R"({"vocabulary": "v.oxvoc", "partitions": [{"replicas": ["a:1"]}],
      "collections": {"photos": {"vocabulary": "/abs/p.oxvoc", "public": false, "max_images": 10}},
      "collection_keys": "keys.json"})";
  const auto with_collections = cluster::ClusterConfig::Read(path);
  ASSERT_TRUE(with_collections) << with_collections.error().ToString();
  ASSERT_EQ(with_collections->collections.size(), 2u);
  EXPECT_EQ(with_collections->collections[0].name, "default");
  EXPECT_EQ(with_collections->collections[1].name, "photos");
  EXPECT_EQ(with_collections->collections[1].vocabulary, "/abs/p.oxvoc");
  EXPECT_FALSE(with_collections->collections[1].settings.is_public);
  EXPECT_EQ(with_collections->collections[1].settings.max_images, 10u);
  EXPECT_EQ(with_collections->collection_keys, dir.path() + "/keys.json");
  for (const char* bad : {R"({"partitions": [{"replicas": ["a:1"]}], "collections": {"Bad Name": {"vocabulary": "v"}}})",
                          R"({"partitions": [{"replicas": ["a:1"]}], "collections": {"p": {}}})",
                          R"({"partitions": [{"replicas": ["a:1"]}], "collections": {"p": {"vocabulary": "v", "max_images": -1}}})",
                          R"({"partitions": [{"replicas": ["a:1"]}], "collections": {"p": {"vocabulary": "v", "colour": 1}}})",
                          R"({"vocabulary": "v", "partitions": [{"replicas": ["a:1"]}], "collections": {"default": {"vocabulary": "v"}}})",
                          R"({"partitions": [{"replicas": ["a:1"]}]})"}) {
    std::ofstream(path) << bad;
    EXPECT_EQ(cluster::ClusterConfig::Read(path).error().code, ErrorCode::kInvalidArgument) << bad;
  }
}

}  // namespace
}  // namespace oxbow
