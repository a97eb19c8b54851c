// A tiny end-to-end evaluation in CI: `oxbow eval --protocol groups --distractors` on a dozen opencv-doc
// photos (four pairs of views of one object or scene, named 1.* and 2.* in every group as groups_dev
// reuses names; unrelated photos in a nested distractor folder) trains a vocabulary, builds an index,
// serves it on an ephemeral loopback port, runs every query through the HTTP API and writes the report.
// The full Paris and groups evaluations are commands (README), not tests.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <set>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "tests/support/e2e.h"
#include "tests/support/temp_dir.h"

namespace {

namespace fs = std::filesystem;

const fs::path kSamples = "/usr/share/doc/opencv-doc/examples/data";

int RunShell(const std::string& command, std::string* output) {
  FILE* pipe = popen((command + " 2>&1").c_str(), "r");
  if (pipe == nullptr) return -1;
  char buf[4096];
  size_t n;
  while ((n = fread(buf, 1, sizeof buf, pipe)) > 0) output->append(buf, n);
  const int status = pclose(pipe);
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

// Four groups of two views (box, graf, leuven, aero) under DIR/images and four unrelated photos under
// DIR/distractors (one in a nested folder).
void WriteGroups(const fs::path& dir) {
  const std::vector<std::pair<std::string, std::vector<std::string>>> groups = {
      {"box", {"box.png", "box_in_scene.png"}},
      {"graf", {"graf1.png", "graf3.png"}},
      {"leuven", {"leuvenA.jpg", "leuvenB.jpg"}},
      {"aero", {"aero1.jpg", "aero3.jpg"}},
  };
  for (const auto& [group, files] : groups) {
    fs::create_directories(dir / "images" / group);
    for (size_t i = 0; i < files.size(); ++i) {
      ASSERT_TRUE(fs::exists(kSamples / files[i])) << "opencv-doc sample missing: " << files[i];
      fs::copy_file(kSamples / files[i], dir / "images" / group / (std::to_string(i + 1) + fs::path(files[i]).extension().string()));
    }
  }
  for (const char* file : {"baboon.jpg", "fruits.jpg", "building.jpg", "home.jpg"}) {
    ASSERT_TRUE(fs::exists(kSamples / file)) << "opencv-doc sample missing: " << file;
    const fs::path target = dir / "distractors" / (std::string(file) == "building.jpg" ? "city" : "") / file;
    fs::create_directories(target.parent_path());
    fs::copy_file(kSamples / file, target);
  }
}

TEST(EvalEndToEnd, GroupsProtocolThroughTheHttpServer) {
  const oxbow::testing::TempDir temp;
  const fs::path dir = temp.path();
  ASSERT_NO_FATAL_FAILURE(WriteGroups(dir));
  const std::string base = std::string(OXBOW_BINARY) + " eval --protocol groups --images " +
                           (dir / "images").string() + " --work " + (dir / "work").string() + " --out " +
                           (dir / "report").string() +
                           " --features rootsift --words 400 --sample 60000 --rerank 0,100 --qe off --threads 2";
  const std::string command = base + " --distractors " + (dir / "distractors").string();
  std::string output;
  const int exit_code = RunShell(command, &output);
  ASSERT_EQ(exit_code, 0) << output;

  std::ifstream in(dir / "report" / "results.json");
  ASSERT_TRUE(in) << output;
  const auto results = nlohmann::json::parse(in);
  ASSERT_EQ(results["runs"].size(), 2u);
  const auto& tfidf = results["runs"][0];
  const auto& reranked = results["runs"][1];
  EXPECT_EQ(tfidf["settings"]["rerank"], "0");
  EXPECT_EQ(reranked["settings"]["rerank"], "100");
  EXPECT_EQ(reranked["settings"]["path"], "http");
  EXPECT_EQ(reranked["queries"].size(), 8u);  // every image of the four pairs queries the rest
  EXPECT_EQ(reranked["index"]["images"].get<int>(), 12);
  EXPECT_EQ(reranked["distractors"].get<int>(), 4);
  EXPECT_EQ(reranked["settings"]["distractors"], "4 images from " + (dir / "distractors").string());
  EXPECT_EQ(reranked["ap_definition"], "non-interpolated");
  EXPECT_EQ(reranked["group_ap"].size(), 4u);
  EXPECT_DOUBLE_EQ(reranked["top4_ceiling"].get<double>(), 1.0);  // one positive per query
  // Ids are <group>__<name>: every group's "1" is its own image, and the distractors are listed too.
  std::set<std::string> returned;
  for (const auto& q : reranked["queries"]) {
    for (const auto& id : q["top"]) returned.insert(id.get<std::string>());
  }
  for (const char* id : {"box__1", "graf__1", "leuven__2", "aero__2", "distractor__city__building"}) {
    EXPECT_TRUE(returned.contains(id)) << id << "\n" << output;
  }
  // Each image's other view should rank at or near the top once verified; an unrelated pipeline
  // (random ranking of 11 candidates) scores about 0.27 here.
  EXPECT_GT(reranked["map"].get<double>(), 0.6) << output;
  EXPECT_GE(reranked["map"].get<double>() + 1e-9, tfidf["map"].get<double>() - 0.1);
  EXPECT_TRUE(fs::exists(dir / "report" / "report.md"));
  EXPECT_TRUE(fs::exists(dir / "report" / "plots" / "ap_per_query.png"));
  // A second run reuses the cached vocabulary and index (no rebuild): build times are zero, also with
  // the work folder spelled another way (the database's files are compared, not their paths). With
  // --mode both the HTTP runs come first, then the in-process ones, which open the index only after
  // the server stopped (one process at a time in a folder).
  std::string again;
  std::string respelled = command;
  const std::string work = " --work " + (dir / "work").string() + " ";
  ASSERT_NE(respelled.find(work), std::string::npos);
  respelled.replace(respelled.find(work), work.size(), " --work " + (dir / "images" / ".." / "work").string() + " ");
  ASSERT_EQ(RunShell(respelled + " --mode both", &again), 0) << again;
  std::ifstream in2(dir / "report" / "results.json");
  const auto second = nlohmann::json::parse(in2);
  ASSERT_EQ(second["runs"].size(), 4u) << again;
  EXPECT_EQ(second["runs"][1]["build_index_s"].get<double>(), 0.0);
  EXPECT_EQ(second["runs"][1]["settings"]["path"], "http");
  EXPECT_DOUBLE_EQ(second["runs"][1]["map"].get<double>(), reranked["map"].get<double>());
  EXPECT_EQ(second["runs"][3]["settings"]["path"], "in-process");
  EXPECT_EQ(second["runs"][3]["settings"]["rerank"], "100");
  EXPECT_EQ(second["runs"][3]["queries"].size(), 8u);
  EXPECT_GT(second["runs"][3]["map"].get<double>(), 0.6) << again;
  // The cached index holds the distractors: a run without them must not score it as if it did not.
  std::string without;
  EXPECT_EQ(RunShell(base, &without), 2) << without;
  EXPECT_NE(without.find("use another --work"), std::string::npos) << without;

  // --server: the same evaluation of a running `oxbow serve` over the cached index gives the same mAP;
  // a server that holds other images than the protocol's database is refused, with the list to index.
  {
    oxbow::testing::ServerProcess server(
        {"serve", "--index", (dir / "work" / "rootsift-400" / "index").string(), "--port", "0"}, (dir / "serve.log").string());
    ASSERT_TRUE(server.port() > 0 && server.WaitReady()) << server.Log();
    const std::string url = "http://127.0.0.1:" + std::to_string(server.port());
    const std::string against = std::string(OXBOW_BINARY) + " eval --protocol groups --images " +
                                (dir / "images").string() + " --rerank 100 --qe off --server " + url;
    std::string via;
    ASSERT_EQ(RunShell(against + " --distractors " + (dir / "distractors").string() + " --work " +
                           (dir / "work-server").string() + " --out " + (dir / "report-server").string(),
                       &via),
              0)
        << via;
    std::ifstream in3(dir / "report-server" / "results.json");
    const auto served = nlohmann::json::parse(in3);
    ASSERT_EQ(served["runs"].size(), 1u);
    EXPECT_DOUBLE_EQ(served["runs"][0]["map"].get<double>(), reranked["map"].get<double>());
    EXPECT_EQ(served["runs"][0]["settings"]["path"], "http, a running server: " + url);
    EXPECT_EQ(served["runs"][0]["index"]["vocabulary_words"], 400);
    EXPECT_EQ(served["runs"][0]["index"]["images"], 12);
    std::string other;
    EXPECT_EQ(RunShell(against + " --work " + (dir / "work-other").string() + " --out " + (dir / "report-other").string(),
                       &other),
              2)
        << other;
    EXPECT_NE(other.find("holds 12 images; the protocol's database has 8"), std::string::npos) << other;
    const std::string listed = oxbow::testing::FileBytes(dir / "work-other" / "database.list");
    EXPECT_EQ(std::count(listed.begin(), listed.end(), '\n'), 8) << listed;
  }
  // --server sends only the search settings given to it. A server started with tf-idf ranking alone and
  // no Hamming embedding (--rerank 0 --no-qe --no-hamming) ranks, without settings from eval, as eval's
  // explicit request for the same; eval's own defaults would have asked for Hamming re-scoring, which
  // ranks these images otherwise (eval's tf-idf run above).
  const auto rankings = [](const nlohmann::json& run) {
    std::vector<nlohmann::json> tops;
    for (const auto& q : run["queries"]) tops.push_back(q["top"]);
    return tops;
  };
  {
    oxbow::testing::ServerProcess server({"serve", "--index", (dir / "work" / "rootsift-400" / "index").string(),
                                          "--port", "0", "--rerank", "0", "--no-qe", "--no-hamming"},
                                         (dir / "serve-tfidf.log").string());
    ASSERT_TRUE(server.port() > 0 && server.WaitReady()) << server.Log();
    const std::string url = "http://127.0.0.1:" + std::to_string(server.port());
    const auto evaluate = [&](const std::string& settings, const std::string& out) {
      std::string via;
      EXPECT_EQ(RunShell(std::string(OXBOW_BINARY) + " eval --protocol groups --images " + (dir / "images").string() +
                             " --distractors " + (dir / "distractors").string() + " --server " + url + " --work " +
                             (dir / "work-server").string() + " --out " + (dir / out).string() + settings,
                         &via),
                0)
          << via;
      const auto report = nlohmann::json::parse(oxbow::testing::FileBytes(dir / out / "results.json"));
      EXPECT_EQ(report["runs"].size(), 1u) << via;
      return report["runs"][0];
    };
    const auto asked = evaluate(" --rerank 0 --qe off --hamming off", "report-asked");
    ASSERT_NE(rankings(asked), rankings(tfidf)) << "Hamming re-scoring must reorder some query's results here";
    const auto left = evaluate("", "report-left");
    EXPECT_EQ(rankings(left), rankings(asked));
    EXPECT_DOUBLE_EQ(left["map"].get<double>(), asked["map"].get<double>());
    for (const char* setting : {"rerank", "qe", "transitive", "hamming", "search_defaults"}) {
      EXPECT_EQ(left["settings"][setting], "the server's") << setting;
    }
    EXPECT_EQ(asked["settings"]["rerank"], "0");
    EXPECT_EQ(asked["settings"]["hamming"], "off");
    EXPECT_EQ(asked["settings"]["transitive"], "the server's");
    EXPECT_NE(left["label"].get<std::string>().find("(the server's rerank qe transitive hamming)"), std::string::npos)
        << left["label"];
  }
}

// Hamming-embedding settings to compare: `--hamming off,on` trains the vocabulary with the embedding,
// and every listed threshold (and width) is a run of its own, in process, with its values in the
// report. Threshold 0 matches only identical signatures, 64 every pair in a word: the rankings differ.
TEST(EvalEndToEnd, ComparesHammingThresholdsInProcess) {
  const oxbow::testing::TempDir temp;
  const fs::path dir = temp.path();
  ASSERT_NO_FATAL_FAILURE(WriteGroups(dir));
  const std::string base = std::string(OXBOW_BINARY) + " eval --protocol groups --images " +
                           (dir / "images").string() + " --work " + (dir / "work").string() + " --out " +
                           (dir / "report").string() +
                           " --features rootsift --words 400 --sample 60000 --rerank 0 --qe off --threads 2"
                           " --hamming off,on --hamming-threshold 0,64";
  std::string refused;
  EXPECT_EQ(RunShell(base, &refused), 2) << "the HTTP path cannot set the threshold: " << refused;
  EXPECT_NE(refused.find("--mode in-process"), std::string::npos) << refused;
  std::string output;
  ASSERT_EQ(RunShell(base + " --mode in-process", &output), 0) << output;
  std::ifstream in(dir / "report" / "results.json");
  ASSERT_TRUE(in) << output;
  const auto runs = nlohmann::json::parse(in)["runs"];
  ASSERT_EQ(runs.size(), 3u) << output;
  EXPECT_EQ(runs[0]["settings"]["hamming"], "off");
  EXPECT_EQ(runs[0]["settings"]["hamming_threshold"], "-");
  EXPECT_EQ(runs[1]["settings"]["hamming_threshold"], "0");
  EXPECT_EQ(runs[2]["settings"]["hamming_threshold"], "64");
  for (const auto& run : {runs[1], runs[2]}) {
    EXPECT_EQ(run["settings"]["hamming"], "on");
    EXPECT_EQ(run["settings"]["hamming_sigma"], "16");
    EXPECT_EQ(run["settings"]["path"], "in-process");
  }
  EXPECT_NE(runs[1]["label"].get<std::string>().find("+he0/16"), std::string::npos) << runs[1]["label"];
  bool differ = false;
  for (size_t q = 0; q < runs[1]["queries"].size(); ++q) {
    differ = differ || runs[1]["queries"][q]["top"] != runs[2]["queries"][q]["top"];
  }
  EXPECT_TRUE(differ) << "thresholds 0 and 64 ranked every query alike: the setting did not reach the query";
}

}  // namespace
