// Durability under kill -9: a child process adds, replaces and removes images in a loop, printing each
// change to a pipe when it starts and when it is acknowledged; the parent SIGKILLs it as soon as an add
// (even rounds) or a replacement (odd rounds) has started, confirms from the pipe that it was still
// unacknowledged at the kill, reopens the index and checks that every acknowledged change is there,
// nothing half-added, an image being replaced is there in its old or its new version (never neither),
// and the index still answers queries.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <random>
#include <set>
#include <string>

#include "index/image_index.h"
#include "tests/support/temp_dir.h"

namespace oxbow {
namespace {

namespace fs = std::filesystem;
constexpr int kWords = 512;

vocab::Vocabulary MakeVocabulary() {
  std::mt19937_64 rng(42);
  std::normal_distribution<float> g(0, 1);
  std::vector<float> c(static_cast<size_t>(kWords) * 128);
  for (int w = 0; w < kWords; ++w) {
    double n = 0;
    for (int d = 0; d < 128; ++d) n += std::pow(c[w * 128 + d] = g(rng), 2);
    for (int d = 0; d < 128; ++d) c[w * 128 + d] /= static_cast<float>(std::sqrt(n));
  }
  vocab::QuantizerBuildOptions build;
  build.num_threads = 1;
  return *vocab::Vocabulary::FromCentroids(std::move(c), 128, sift::DescriptorKind::kSift, "crash-test/1", build);
}

// Deterministic features for version 1 (added) or 2 (replacement) of image i, so the parent can
// recompute what the child wrote; the two versions differ in their feature count.
sift::FeatureSet ImageFeatures(const vocab::Vocabulary& v, int i, int version = 1) {
  std::mt19937_64 rng(1000 + i + 1000003 * (version - 1));
  sift::FeatureSet f;
  f.image_width = 500;
  f.image_height = 400;
  f.kind = sift::DescriptorKind::kSift;
  const int n = 200 + i % 50 + (version - 1);
  for (int k = 0; k < n; ++k) {
    const uint32_t w = static_cast<uint32_t>(rng() % kWords);
    f.keypoints.push_back({static_cast<float>(rng() % 500), static_cast<float>(rng() % 400),
                           2.0f + static_cast<float>(rng() % 8), static_cast<float>(rng() % 6), 1, 0});
    const auto c = v.centroids().subspan(w * 128, 128);
    f.descriptors.insert(f.descriptors.end(), c.begin(), c.end());
  }
  return f;
}

// Child: add images start.., removing every 4th earlier one and replacing another; prints "+ <id>" /
// "- <id>" / "~ <id>" before each add / removal / replacement and "a <id>" / "r <id>" / "p <id>" once it
// is acknowledged. Never returns.
[[noreturn]] void RunChild(const std::string& dir, int write_fd, int start) {
  const vocab::Vocabulary vocabulary = MakeVocabulary();
  index::IndexOptions options;
  options.num_threads = 1;
  options.quantizer.num_threads = 1;
  auto opened = index::ImageIndex::Open(dir, options);
  if (!opened) _exit(3);
  auto& idx = **opened;
  const auto print = [write_fd](const std::string& line) {
    if (write(write_fd, line.data(), line.size()) != static_cast<ssize_t>(line.size())) _exit(5);
  };
  for (int i = start; i < start + 100000; ++i) {
    const std::string id = "img" + std::to_string(i);
    const sift::FeatureSet features = ImageFeatures(vocabulary, i);
    print("+ " + id + "\n");
    if (!idx.Add(id, features, {})) _exit(4);
    print("a " + id + "\n");
    if (i % 4 == 3) {
      const std::string victim = "img" + std::to_string(i - 2);
      print("- " + victim + "\n");
      if (!idx.Remove(victim)) _exit(6);
      print("r " + victim + "\n");
    }
    if (i % 4 == 1 && i > start) {
      const std::string replaced = "img" + std::to_string(i - 1);
      print("~ " + replaced + "\n");
      if (!idx.Replace(replaced, ImageFeatures(vocabulary, i - 1, 2), {})) _exit(7);
      print("p " + replaced + "\n");
    }
  }
  _exit(0);
}

TEST(CrashSafetyTest, AcknowledgedChangesSurviveSigkill) {
  const oxbow::testing::TempDir temp;
  const fs::path dir = temp / "index";
  const vocab::Vocabulary vocabulary = MakeVocabulary();
  {
    auto created = index::ImageIndex::Create(dir.string(), vocabulary, "crash-test/1");
    ASSERT_TRUE(created) << created.error().ToString();
  }
  std::set<std::string> expected;  // ids acknowledged as added and not acknowledged as removed
  std::set<std::string> removed;
  std::map<std::string, int> version;  // of each id in `expected`
  int start = 0;
  // Several rounds, each killed after a different number of acknowledgements, as soon as the next add
  // (even rounds) or replacement (odd rounds) has started. The kill may land after it returned (the
  // parent was slow to send it); such a round still checks durability but is not counted, and rounds go
  // on until kMidWriteKills were mid-add and as many mid-replacement.
  constexpr int kMidWriteKills = 3;
  int mid_add_kills = 0;
  int mid_replace_kills = 0;
  for (int round = 0; round < 6 * kMidWriteKills && (mid_add_kills < kMidWriteKills || mid_replace_kills < kMidWriteKills);
       ++round) {
    const char target = round % 2 == 0 ? '+' : '~';
    int fds[2];
    ASSERT_EQ(pipe(fds), 0);
    std::fflush(nullptr);
    const pid_t pid = fork();
    ASSERT_GE(pid, 0);
    if (pid == 0) {
      close(fds[0]);
      RunChild(dir.string(), fds[1], start);
    }
    close(fds[1]);
    FILE* in = fdopen(fds[0], "r");
    ASSERT_NE(in, nullptr);
    const int kill_after = 7 + 11 * round;
    int acks = 0;
    char line[256];
    std::string last_line;  // the child's last complete line
    // One line: a change started ("+ ID", "- ID") or acknowledged ("a ID" added, "r ID" removed).
    auto record = [&](std::string s) {
      s.pop_back();
      last_line = s;
      if (s[0] == 'a') {
        expected.insert(s.substr(2));
        version[s.substr(2)] = 1;
        ++acks;
      } else if (s[0] == 'p') {
        version[s.substr(2)] = 2;
        ++acks;
      } else if (s[0] == 'r') {
        expected.erase(s.substr(2));
        removed.insert(s.substr(2));
        ++acks;
      }
    };
    bool killed = false;
    while (std::fgets(line, sizeof(line), in)) {
      record(line);
      if (acks >= kill_after && last_line[0] == target) {
        ASSERT_EQ(kill(pid, SIGKILL), 0);
        killed = true;
        break;
      }
    }
    ASSERT_TRUE(killed) << "child stopped early";
    // Lines written before the kill still count.
    while (std::fgets(line, sizeof(line), in)) {
      const std::string s(line);
      if (s.back() != '\n') break;  // a torn line was never fully written
      record(s);
    }
    std::fclose(in);
    // The change in flight at the kill (started, never acknowledged) may or may not have committed.
    std::string in_flight_add, in_flight_removal, in_flight_replace;
    if (last_line[0] == '+') in_flight_add = last_line.substr(2);
    if (last_line[0] == '-') in_flight_removal = last_line.substr(2);
    if (last_line[0] == '~') in_flight_replace = last_line.substr(2);
    if (!in_flight_add.empty()) ++mid_add_kills;
    if (!in_flight_replace.empty()) ++mid_replace_kills;
    std::printf("round %d: killed after %d acknowledgements, %s\n", round, acks,
                !in_flight_add.empty()       ? ("during the add of " + in_flight_add).c_str()
                : !in_flight_replace.empty() ? ("during the replacement of " + in_flight_replace).c_str()
                                             : "not during an add or a replacement");
    int status = 0;
    ASSERT_EQ(waitpid(pid, &status, 0), pid);
    ASSERT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == SIGKILL) << "child exited with " << status;

    auto reopened = index::ImageIndex::Open(dir.string());
    ASSERT_TRUE(reopened) << "round " << round << ": " << reopened.error().ToString();
    auto& idx = **reopened;
    if (!in_flight_removal.empty() && !idx.Contains(in_flight_removal)) {
      expected.erase(in_flight_removal);
      removed.insert(in_flight_removal);
    }
    // Old or new, never neither.
    if (!in_flight_replace.empty()) {
      const auto found = idx.Get(in_flight_replace);
      ASSERT_TRUE(found) << "image " << in_flight_replace << " lost by a replacement interrupted in round " << round;
      const int i = std::stoi(in_flight_replace.substr(3));
      if (found->num_features == ImageFeatures(vocabulary, i, 2).size()) version[in_flight_replace] = 2;
    }
    for (const std::string& id : expected) {
      const auto found = idx.Get(id);
      ASSERT_TRUE(found) << "acknowledged image " << id << " lost in round " << round;
      const int i = std::stoi(id.substr(3));
      EXPECT_EQ(found->num_features, ImageFeatures(vocabulary, i, version[id]).size()) << id;
    }
    for (const std::string& id : removed) EXPECT_FALSE(idx.Contains(id)) << "acknowledged removal of " << id << " undone";
    // At most the one change in flight may have committed without being acknowledged.
    const auto stats = idx.Stats();
    EXPECT_GE(stats.num_images, expected.size());
    EXPECT_LE(stats.num_images, expected.size() + 1);
    // Whatever is there is whole: each image's stored features find the image itself first.
    const auto all = idx.List(0, 1u << 20);
    ASSERT_TRUE(all);
    for (const auto& stored : *all) {
      const int i = std::stoi(stored.id.substr(3));
      // Adopt an unacknowledged but committed add so later rounds keep checking it.
      if (expected.insert(stored.id).second) version[stored.id] = 1;
      EXPECT_EQ(stored.num_features, ImageFeatures(vocabulary, i, version[stored.id]).size()) << stored.id;
    }
    index::QueryOptions query;
    query.top_k = 1;
    query.rerank_depth = 0;
    const std::string& first = *expected.begin();
    const auto self = idx.Query(ImageFeatures(vocabulary, std::stoi(first.substr(3)), version[first]), query);
    ASSERT_TRUE(self);
    ASSERT_FALSE(self->results.empty());
    EXPECT_EQ(self->results[0].id, *expected.begin());
    start += 1000;
  }
  EXPECT_GE(mid_add_kills, kMidWriteKills) << "too few kills landed while an add was in flight";
  EXPECT_GE(mid_replace_kills, kMidWriteKills) << "too few kills landed while a replacement was in flight";
}

}  // namespace
}  // namespace oxbow
