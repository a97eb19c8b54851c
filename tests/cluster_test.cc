// A cluster served by shards and a front (issue 15 items 3 and 4, README "Serving a cluster"): the same
// images built as one index and as 3 partitions (`index build --mpi --partitions 3`, an MPI singleton),
// each partition served by `oxbow serve --grpc-port`, the front (cluster::ClusterFront) asking them over
// gRPC. With no write in flight the front's rankings equal the single node's: ids, order, scores,
// verified flags and inliers.
#include <gtest/gtest.h>

#include <signal.h>

#include <filesystem>
#include <fstream>
#include <regex>

#include <nlohmann/json.hpp>

#include "api/partition.h"
#include "api/testing.h"
#include "index/image_index.h"
#include "server/cluster/front.h"
#include "sift/sift.h"
// After the project headers: <httplib.h> (through e2e_testing.h) defines a `_res` macro that breaks Eigen.
#include "e2e_testing.h"

namespace oxbow {
namespace {

namespace fs = std::filesystem;
using testing::RunCommand;

constexpr int kPartitions = 3;

class Cluster : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new api::testing::TempDir("oxbow-cluster");
    const std::string images = dir_->path() + "/images";
    fs::create_directories(images);
    // Twelve pictures: crops of four opencv-doc photos at three offsets each (views of one scene verify
    // against each other), so that re-ranking and query expansion have something to do.
    const char* samples[] = {"graf1.png", "box.png", "baboon.jpg", "building.jpg"};
    for (int i = 0; i < 12; ++i) {
      ASSERT_TRUE(cv::imwrite(images + "/img" + std::to_string(i) + ".png",
                              testing::Texture(320, 240, samples[i % 4], 25 * (i / 4), 20 * (i / 4))));
    }
    const std::string vocab = dir_->path() + "/v.oxvoc";
    ASSERT_TRUE(testing::RandomVocabulary(sift::SiftOptions{}.Describe(), 512)->Write(vocab));
    Run(std::string(OXBOW_BINARY) + " -q index build --vocab " + vocab + " --images " + images +
        " --threads 1 --out " + dir_->path() + "/single 2>&1");
    Run(std::string(testing::kMpiChildEnvironment) + OXBOW_BINARY + " -q index build --mpi --vocab " + vocab +
        " --images " + images + " --partitions " + std::to_string(kPartitions) + " --threads 1 --out " +
        dir_->path() + "/cluster 2>&1");
    auto extractor = sift::SiftExtractor::Create(sift::SiftOptions{});
    ASSERT_TRUE(extractor);
    for (int i = 0; i < 12; ++i) {
      auto features = extractor->ExtractFromFile(images + "/img" + std::to_string(i) + ".png");
      ASSERT_TRUE(features);
      queries_->push_back(std::move(*features));
    }
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

  // `oxbow serve --grpc-port 0` on partition p (or the index folder `folder`); its gRPC address ("" when
  // it failed).
  std::string StartShard(int p, const std::string& folder = "") {
    const std::string n = std::to_string(started_++);  // a fresh log (ServerProcess appends)
    shards_.push_back(std::make_unique<testing::ServerProcess>(
        std::vector<std::string>{"serve", "--index",
                                 folder.empty() ? api::PartitionFolder(dir_->path() + "/cluster", p) : folder, "--port", "0",
                                 "--grpc-port", "0", "--index-threads", "1"},
        dir_->path() + "/shard-" + n + ".log"));
    const testing::ServerProcess& shard = *shards_.back();
    EXPECT_TRUE(shard.port() > 0 && shard.WaitReady()) << shard.Log();
    std::smatch m;
    const std::string log = shard.Log();
    if (!std::regex_search(log, m, std::regex(R"(gRPC\) on (127\.0\.0\.1:\d+))"))) return "";
    return m[1];
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
      EXPECT_EQ(a.db_region, b.db_region) << what << " rank " << i;
      EXPECT_EQ(a.record.id, b.record.id) << what << " rank " << i;
      EXPECT_EQ(a.record.num_features, b.record.num_features) << what << " rank " << i;
      EXPECT_EQ(a.record.width, b.record.width) << what << " rank " << i;
    }
    EXPECT_EQ(single.candidates, front.candidates) << what;
  }

  static inline api::testing::TempDir* dir_ = nullptr;
  static inline std::vector<sift::FeatureSet>* queries_ = new std::vector<sift::FeatureSet>;
  static inline int started_ = 0;
  std::vector<std::unique_ptr<testing::ServerProcess>> shards_;
};

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
      for (const auto& s : idx.ScoreTerms(idx.TermsOf(bag.words, tf), 100, nullptr)) out[s.id] = s.score;
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
    for (const auto& s : partition->ScoreTerms(partition->TermsOf(bag.words, tf), 100, nullptr)) out[s.id] = s.score;
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

  index::QueryOptions options;
  options.top_k = 12;
  options.transitive_depth = 0;  // not served by the front yet
  index::QueryOptions plain = options;
  plain.query_expansion = false;
  index::QueryOptions region = options;
  region.region = std::array<float, 4>{40, 30, 260, 200};
  size_t verified = 0;
  for (size_t q = 0; q < queries_->size(); ++q) {
    for (const auto& [name, o] : {std::pair{"qe", options}, std::pair{"plain", plain}, std::pair{"region", region}}) {
      const auto expected = single->Query((*queries_)[q], o);
      const auto got = front->Query((*queries_)[q], o);
      ASSERT_TRUE(expected && got) << (got ? "" : got.error().ToString());
      ExpectSameRanking(*expected, *got, std::string(name) + " query " + std::to_string(q));
      for (const auto& r : got->results) verified += r.verified ? 1 : 0;
    }
  }
  EXPECT_GT(verified, queries_->size()) << "nothing but the queries themselves verified: the test proves little";
  for (const cluster::ReplicaMetrics& m : front->Metrics()) {
    EXPECT_GT(m.calls, 0u) << m.address;
    EXPECT_EQ(m.errors, 0u) << m.address;
  }
}

// Options a front does not serve yet are refused, never silently dropped (an unfiltered answer to a
// filtered search would look valid).
TEST_F(Cluster, FrontRefusesOptionsItDoesNotServe) {
  cluster::ClusterConfig config;
  ASSERT_NO_FATAL_FAILURE(StartCluster(&config));
  const auto front = cluster::ClusterFront::Open(config).value();
  struct AnyImage : index::ImageFilter {
    bool Matches(const index::ImageRecord&) const override { return true; }
  };
  index::QueryOptions filtered;
  filtered.filter = std::make_shared<AnyImage>();
  index::QueryOptions hamming;
  hamming.hamming = true;
  for (const auto& [name, o] : {std::pair{"filter", filtered}, std::pair{"hamming", hamming}}) {
    const auto got = front->Query((*queries_)[0], o);
    ASSERT_FALSE(got) << name;
    EXPECT_EQ(got.error().code, ErrorCode::kInvalidArgument) << name;
    EXPECT_NE(got.error().message.find(name), std::string::npos) << got.error().message;
  }
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
  std::string partitions;
  for (int p = 0; p < kPartitions; ++p) {
    const std::string address = StartShard(p);
    ASSERT_FALSE(address.empty()) << shards_.back()->Log();
    partitions += std::string(p == 0 ? "" : ", ") + "{\"replicas\": [\"" + address + "\"]}";
  }
  const std::string config = dir_->path() + "/cluster-" + std::to_string(started_) + ".json";
  std::ofstream(config) << "{\"vocabulary\": \"v.oxvoc\", \"partitions\": [" << partitions << "]}";
  testing::ServerProcess front({"serve", "--cluster", config, "--port", "0"}, config + ".log");
  ASSERT_TRUE(front.port() > 0 && front.WaitReady()) << front.Log();
  testing::ServerProcess single({"serve", "--index", dir_->path() + "/single", "--port", "0"},
                                dir_->path() + "/single-" + std::to_string(started_++) + ".log");
  ASSERT_TRUE(single.port() > 0 && single.WaitReady()) << single.Log();

  std::ifstream in(dir_->path() + "/images/img5.png", std::ios::binary);
  const std::string image((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const std::string path = "/v1/search?top_k=8&transitive_depth=0";
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
    for (const char* field : {"id", "score", "verified", "inliers", "region", "width", "height"})
      EXPECT_EQ(a[i][field], b[i][field]) << field << " of rank " << i;
  }
  EXPECT_EQ(nlohmann::json::parse(expected->body)["candidates"], nlohmann::json::parse(got->body)["candidates"]);

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
  EXPECT_TRUE(std::regex_search(metrics->body, std::regex(R"(oxbow_shard_errors_total\{partition="2",replica="[^"]+"\} [1-9])")))
      << metrics->body;
  auto list = front.Client().Get("/v1/images");
  ASSERT_TRUE(list);
  EXPECT_EQ(list->status, 501) << list->body;
}

TEST(ClusterConfigFile, ReadsReplicasAndResolvesTheVocabularyBesideIt) {
  api::testing::TempDir dir("oxbow-cluster-config");
  const std::string path = dir.path() + "/cluster.json";
  std::ofstream(path) << R"({"vocabulary": "v.oxvoc", "partitions": [{"replicas": ["a:1", "b:2"]}, {"replicas": ["c:3"]}]})";
  const auto config = cluster::ClusterConfig::Read(path);
  ASSERT_TRUE(config) << config.error().ToString();
  EXPECT_EQ(config->vocabulary, dir.path() + "/v.oxvoc");
  ASSERT_EQ(config->partitions.size(), 2u);
  EXPECT_EQ(config->partitions[0], (std::vector<std::string>{"a:1", "b:2"}));
  std::ofstream(path) << R"({"vocabulary": "v.oxvoc", "partitions": [{"replicas": []}]})";
  EXPECT_EQ(cluster::ClusterConfig::Read(path).error().code, ErrorCode::kInvalidArgument);
}

}  // namespace
}  // namespace oxbow
