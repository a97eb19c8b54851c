// `--mpi` batch work under a real `mpirun --oversubscribe`: the vocabulary, Hamming-embedding parameters
// included, does not depend on the number of ranks, and its parameters are those the single-node code
// learns from the same sample; a stopped training resumes to the same file; a partitioned build puts
// every image in the partition PartitionOf names with the cluster's document frequencies stored beside
// each partition, and stores the Hamming-embedding signatures a single-node build stores. CI runs as root, which Open MPI refuses unless told otherwise: the
// two OMPI_ALLOW_RUN_AS_ROOT variables are set for the mpirun child only.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <map>
#include <regex>
#include <set>

#include <nlohmann/json.hpp>

#include "api/partition.h"
#include "index/image_index.h"
#include "sift/sift.h"
#include "tests/support/samples.h"
// After the project headers: <httplib.h> (through tests/support/e2e.h) defines a `_res` macro that breaks Eigen.
#include "tests/support/e2e.h"
#include "tests/support/temp_dir.h"

namespace oxbow {
namespace {

namespace fs = std::filesystem;
using testing::RunCommand;


std::string Mpirun(int ranks, const std::string& args) {
  std::string command = testing::kMpiChildEnvironment;
  command += "OMPI_MCA_rmaps_base_oversubscribe=1 ";
  command += "mpirun --oversubscribe -np " + std::to_string(ranks);
  command += " " OXBOW_BINARY " " + args + " 2>&1";
  return command;
}

class Mpi : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = std::make_unique<oxbow::testing::TempDir>("oxbow-mpi");
    images_ = dir_->path() + "/images";
    fs::create_directories(images_ + "/sub");
    // Ten small textured pictures (crops of opencv-doc photos, noise without them), one in a sub-folder.
    const char* samples[] = {"graf1.png", "box.png", "baboon.jpg", "fruits.jpg", "building.jpg"};
    for (int i = 0; i < 10; ++i) {
      const std::string name = (i == 3 ? "/sub/img" : "/img") + std::to_string(i) + ".png";
      ASSERT_TRUE(cv::imwrite(images_ + name, testing::Texture(320, 240, samples[i % 5], 40 * (i / 5), 30 * (i / 5))));
    }
  }
  std::string Path(const std::string& name) const { return dir_->path() + "/" + name; }
  std::string Run(const std::string& command) {
    int code = -1;
    std::string out = RunCommand(command, &code);
    EXPECT_EQ(code, 0) << command << "\n" << out;
    return out;
  }

  std::unique_ptr<oxbow::testing::TempDir> dir_;
  std::string images_;
};

TEST_F(Mpi, VocabularyIsTheSameForOneAndThreeRanks) {
  const std::string train =
      "vocab train --mpi --root-sift --images " + images_ + " --words 200 --per-image 600 --threads 1 --out ";
  Run(Mpirun(1, train + Path("np1.oxvoc")));
  Run(Mpirun(3, train + Path("np3.oxvoc")));
  std::string singleton = testing::kMpiChildEnvironment;  // no mpirun: one rank (MPI_Init as a singleton)
  singleton += OXBOW_BINARY " " + train;
  Run(singleton + Path("singleton.oxvoc") + " 2>&1");
  const std::string np1 = testing::FileBytes(Path("np1.oxvoc"));
  ASSERT_GT(np1.size(), 200u * 128u * 4u);
  EXPECT_TRUE(np1 == testing::FileBytes(Path("np3.oxvoc"))) << "np=1 and np=3 vocabularies differ";
  EXPECT_TRUE(np1 == testing::FileBytes(Path("singleton.oxvoc"))) << "mpirun -np 1 and a singleton differ";
  EXPECT_FALSE(fs::exists(Path("np3.oxvoc.checkpoint"))) << "the checkpoint outlives a finished training";
  const std::string info = Run(std::string(OXBOW_BINARY) + " vocab info " + Path("np3.oxvoc") + " 2>&1");
  EXPECT_NE(info.find("hamming      64-bit embedding"), std::string::npos) << "learnt by default:\n" << info;
}

TEST_F(Mpi, HammingParametersAreTheSingleNodeOnesOnTheSameSample) {
  // With every descriptor in the sample, `vocab hamming` (one process) sees the rows `vocab train --mpi`
  // spread over the ranks: on the same centroids it must write the same file.
  const std::string all_rows = " --images " + images_ + " --per-image 100000 --sample 10000000 --threads 1";
  const std::string train = "vocab train --mpi --words 200" + all_rows;
  Run(Mpirun(3, train + " --out " + Path("he.oxvoc")));
  Run(Mpirun(2, train + " --no-hamming --out " + Path("plain.oxvoc")));
  const std::string info = Run(std::string(OXBOW_BINARY) + " vocab info " + Path("plain.oxvoc") + " 2>&1");
  EXPECT_NE(info.find("hamming      none"), std::string::npos) << info;
  Run(std::string(OXBOW_BINARY) + " vocab hamming --vocab " + Path("plain.oxvoc") + all_rows + " --out " +
      Path("added.oxvoc") + " 2>&1");
  const std::string he = testing::FileBytes(Path("he.oxvoc"));
  ASSERT_FALSE(he.empty());
  EXPECT_TRUE(he == testing::FileBytes(Path("added.oxvoc"))) << "--mpi Hamming parameters differ from the single-node ones";
}

TEST_F(Mpi, StoppedTrainingResumesToTheUninterruptedVocabulary) {
  // ivf assignment (approximate: a row's previous word matters) and empty words to re-seed: random seeding
  // (above 4096 words) over a folder where every picture is there twice puts some centres on identical
  // rows, one of which then stays empty. The checkpoint must carry all of that state.
  fs::copy(images_, Path("copy"), fs::copy_options::recursive);
  fs::rename(Path("copy"), images_ + "/copy");
  const std::string train = "vocab train --mpi --images " + images_ +
                            " --words 4200 --per-image 300 --assignment ivf --iterations 6 --threads 1 --out ";
  const std::string whole = Run(Mpirun(3, train + Path("whole.oxvoc")));
  EXPECT_TRUE(std::regex_search(whole, std::regex("empty [1-9]"))) << "no empty word was re-seeded:\n" << whole;

  const std::string first = Run(Mpirun(2, train + Path("resumed.oxvoc") + " --stop-after-iterations 2"));
  EXPECT_NE(first.find("stopped after iteration 2"), std::string::npos) << first;
  ASSERT_TRUE(fs::exists(Path("resumed.oxvoc.checkpoint")));
  ASSERT_FALSE(fs::exists(Path("resumed.oxvoc")));
  // Resumed on another number of ranks.
  const std::string second = Run(Mpirun(1, train + Path("resumed.oxvoc")));
  EXPECT_NE(second.find("resuming from"), std::string::npos) << second;
  EXPECT_TRUE(testing::FileBytes(Path("whole.oxvoc")) == testing::FileBytes(Path("resumed.oxvoc"))) << "resumed vocabulary differs";
  EXPECT_FALSE(fs::exists(Path("resumed.oxvoc.checkpoint")));

  // A checkpoint of other options is refused, not silently mixed in.
  Run(Mpirun(1, train + Path("other.oxvoc") + " --stop-after-iterations 1"));
  int code = 0;
  const std::string refused = RunCommand(
      Mpirun(2, "vocab train --mpi --images " + images_ + " --words 4200 --per-image 300 --assignment ivf --seed 2 "
                "--threads 1 --out " + Path("other.oxvoc")), &code);
  EXPECT_NE(code, 0) << refused;
  EXPECT_NE(refused.find("belongs to other images"), std::string::npos) << refused;
}

// `index duplicates --mpi`: three ranks open one index read-only, each searches and measures its share,
// and rank 0 writes the report one process writes (pairs, kinds, maps, groups), to the byte but timings.
TEST_F(Mpi, DuplicatesOverRanksEqualOneProcess) {
  const std::string settings = sift::SiftOptions{}.Describe();
  ASSERT_TRUE(testing::RandomVocabulary(settings, 256).value().Write(Path("v.oxvoc")));
  Run(std::string(OXBOW_BINARY) + " -q index build --vocab " + Path("v.oxvoc") + " --images " + images_ +
      " --threads 1 --out " + Path("single") + " 2>&1");
  const std::string args = "-q index duplicates --index " + Path("single") + " --threads 1 --min-coverage 0.1";
  Run(std::string(OXBOW_BINARY) + " " + args + " --out " + Path("one.json") + " 2>&1");
  Run(Mpirun(3, args + " --mpi --out " + Path("ranks.json")));
  auto one = nlohmann::json::parse(testing::FileBytes(Path("one.json")), nullptr, false);
  auto ranks = nlohmann::json::parse(testing::FileBytes(Path("ranks.json")), nullptr, false);
  ASSERT_TRUE(one.is_object() && ranks.is_object());
  ASSERT_GE(one["pairs"].size(), 3u) << one.dump();  // img i and img i+5 crop the same photo
  one.erase("timings_s");
  ranks.erase("timings_s");
  EXPECT_EQ(one, ranks);
  // The index was only read: it opens for writing afterwards, and a writer holding it refuses the ranks.
  const auto writer = index::ImageIndex::Open(Path("single"));
  ASSERT_TRUE(writer) << writer.error().ToString();
  int code = 0;
  const std::string refused = RunCommand(Mpirun(2, args + " --mpi"), &code);
  EXPECT_NE(code, 0) << refused;
  EXPECT_NE(refused.find("open in another process"), std::string::npos) << refused;
}

TEST_F(Mpi, PartitionedBuildMatchesASingleNodeBuild) {
  const std::string settings = sift::SiftOptions{}.Describe();
  const vocab::Vocabulary vocabulary = testing::RandomVocabulary(settings, 256).value();
  ASSERT_TRUE(vocabulary.Write(Path("v.oxvoc")));
  Run(std::string(OXBOW_BINARY) + " -q index build --vocab " + Path("v.oxvoc") + " --images " + images_ +
      " --threads 1 --out " + Path("single") + " 2>&1");
  const std::string build = "-q index build --mpi --vocab " + Path("v.oxvoc") + " --images " + images_ +
                            " --partitions 3 --threads 1 --out " + Path("cluster");
  Run(Mpirun(2, build));

  const auto ids_in = [](const std::string& dir) {
    const auto idx = index::ImageIndex::Open(dir).value();
    const std::vector<index::ImageRecord> records = idx->List(0, 100).value();
    std::vector<std::string> ids;
    ids.reserve(records.size());
    for (const auto& r : records) ids.push_back(r.id);
    return ids;
  };
  std::set<std::string> single_ids;
  for (const auto& id : ids_in(Path("single"))) single_ids.insert(id);
  ASSERT_EQ(single_ids.size(), 10u);
  std::set<std::string> cluster_ids;
  std::vector<std::string> frequency_files;
  for (uint32_t p = 0; p < 3; ++p) {
    const std::string dir = api::PartitionFolder(Path("cluster"), p);
    for (const auto& id : ids_in(dir)) {
      EXPECT_EQ(api::PartitionOf(id, 3), p) << id << " is in the wrong partition";
      EXPECT_TRUE(cluster_ids.insert(id).second) << id << " is in two partitions";
    }
    frequency_files.push_back(dir + "/" + std::string(api::kGlobalFrequenciesFile));
  }
  EXPECT_EQ(cluster_ids, single_ids);

  // The document frequencies, computed here from scratch: extract, quantise as `index build` does.
  const sift::SiftExtractor extractor = sift::SiftExtractor::Create(sift::SiftOptions{}).value();
  std::vector<uint32_t> expected(vocabulary.size(), 0);
  const std::vector<std::string> paths = sift::ListImageFiles(images_).value();
  ASSERT_EQ(paths.size(), 10u);
  for (const auto& path : paths) {
    const sift::FeatureSet f = extractor.ExtractFromFile(path).value();
    std::vector<uint32_t> words(f.size());
    vocabulary.Quantize(f.descriptors, words);
    std::set<uint32_t> distinct(words.begin(), words.end());
    for (uint32_t w : distinct) ++expected[w];
  }
  for (uint32_t p = 0; p < 3; ++p) {
    const auto stored = api::ReadGlobalFrequencies(frequency_files[p]);
    ASSERT_TRUE(stored) << stored.error().ToString();
    EXPECT_EQ(stored->partition, p);
    EXPECT_EQ(stored->num_partitions, 3u);
    EXPECT_EQ(stored->num_images, 10u);
    EXPECT_EQ(stored->vocabulary_fingerprint, vocabulary.fingerprint());
    EXPECT_EQ(stored->document_frequency, expected) << "partition " << p;
  }

  // Resumed (here: nothing left to do) on three ranks: every image is known, the frequencies stay.
  const std::string before = testing::FileBytes(frequency_files[1]);
  const std::string again = Run(Mpirun(3, build));
  EXPECT_NE(again.find("\"already_indexed\": 4"), std::string::npos) << again;
  EXPECT_TRUE(testing::FileBytes(frequency_files[1]) == before);

  // Resuming with another number of partitions would misroute images: refused.
  int code = 0;
  const std::string other_p = RunCommand(Mpirun(2, std::regex_replace(build, std::regex("--partitions 3"), "--partitions 2")), &code);
  EXPECT_NE(code, 0) << other_p;
  EXPECT_NE(other_p.find("more than 2 partitions"), std::string::npos) << other_p;
  // Rank 1 sees a fault of its own (partition 1 records 3 partitions); the ranks agree on rank 0's.
  EXPECT_EQ(other_p.find("is a cluster of 3"), std::string::npos) << other_p;

  // A partition whose recorded words do not cover its images is refused rather than counted wrong.
  fs::remove(api::PartitionFolder(Path("cluster"), 2) + "/partition-frequencies.oxdf");
  const std::string refused = RunCommand(Mpirun(2, build), &code);
  EXPECT_NE(code, 0) << refused;
  EXPECT_NE(refused.find("changed outside"), std::string::npos) << refused;
}

TEST_F(Mpi, PartitionedBuildStoresTheSingleNodeHammingSignatures) {
  Run(Mpirun(2, "vocab train --mpi --images " + images_ + " --words 200 --per-image 600 --threads 1 --out " +
                    Path("he.oxvoc")));
  const vocab::Vocabulary vocabulary = vocab::Vocabulary::Read(Path("he.oxvoc")).value();
  ASSERT_TRUE(vocabulary.has_hamming());
  Run(std::string(OXBOW_BINARY) + " -q index build --vocab " + Path("he.oxvoc") + " --images " + images_ +
      " --threads 1 --out " + Path("single") + " 2>&1");
  Run(Mpirun(2, "-q index build --mpi --vocab " + Path("he.oxvoc") + " --images " + images_ +
                    " --partitions 2 --threads 1 --out " + Path("cluster")));

  // Each partition, scoring with the cluster's statistics, gives its images the Hamming-embedding
  // scores the single index gives them; without signatures they would keep their tf-idf scores.
  const auto single = index::ImageIndex::Open(Path("single")).value();
  const sift::SiftExtractor extractor =
      sift::SiftExtractor::Create(sift::SiftOptions::FromDescription(vocabulary.extractor_settings()).value()).value();
  index::QueryOptions hamming;
  hamming.rerank_depth = 0;
  hamming.query_expansion = false;
  hamming.transitive_depth = 0;
  index::QueryOptions tf_idf = hamming;
  tf_idf.hamming = false;
  size_t compared = 0, rescored = 0;
  for (uint32_t p = 0; p < 2; ++p) {
    const std::string dir = api::PartitionFolder(Path("cluster"), p);
    const auto partition = index::ImageIndex::Open(dir).value();
    ASSERT_TRUE(api::PinClusterStatistics(dir, *partition));
    const std::vector<index::ImageRecord> records = partition->List(0, 100).value();
    for (const index::ImageRecord& record : records) {
      const auto extracted = extractor.ExtractFromFile(record.source_path);
      ASSERT_TRUE(extracted) << record.source_path << ": " << extracted.error().ToString();
      const sift::FeatureSet& query = *extracted;
      const auto on_single = single->Query(query, hamming);
      const auto without = partition->Query(query, tf_idf);
      const auto response = partition->Query(query, hamming);
      for (const auto* r : {&on_single, &without, &response}) ASSERT_TRUE(*r) << record.id << ": " << r->error().ToString();
      std::map<std::string, double> single_scores, tf_idf_scores;
      for (const auto& r : on_single->results) single_scores[r.id] = r.score;
      for (const auto& r : without->results) tf_idf_scores[r.id] = r.score;
      EXPECT_FALSE(response->results.empty()) << record.id;
      for (const auto& r : response->results) {
        ASSERT_EQ(single_scores.count(r.id), 1u) << r.id << " for " << record.id;
        EXPECT_NEAR(r.score, single_scores[r.id], 1e-9) << r.id << " for " << record.id;
        ++compared;
        if (tf_idf_scores.count(r.id) == 1 && std::abs(r.score - tf_idf_scores[r.id]) > 1e-6) ++rescored;
      }
    }
  }
  EXPECT_GE(compared, 10u);
  EXPECT_GT(rescored, 0u) << "no image of a partition has a Hamming-embedding score";
}

}  // namespace
}  // namespace oxbow
