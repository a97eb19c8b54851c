#include "eval/ground_truth.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <set>

#include "tests/support/shared_data.h"
#include "tests/support/temp_dir.h"

namespace oxbow::eval {
namespace {

namespace fs = std::filesystem;

class GroundTruthTest : public ::testing::Test {
 protected:
  void Write(const std::string& name, const std::string& text) { std::ofstream(dir_ / name) << text; }
  oxbow::testing::TempDir temp_;  // removed with its contents after the test
  fs::path dir_{temp_.path()};
};

TEST_F(GroundTruthTest, ReadsOxfordFolderAndRestricts) {
  Write("tower_1_query.txt", "oxc1_tower_000001 10.5 20 300 400.25\n");
  Write("tower_1_good.txt", "tower_000001\ntower_000002\n");
  Write("tower_1_ok.txt", "tower_000003\r\n");
  Write("tower_1_junk.txt", "tower_000009\n");
  Write("bridge_1_query.txt", "bridge_000001 0 0 50 50\n");
  Write("bridge_1_good.txt", "bridge_000002\n");
  Write("bridge_1_ok.txt", "");
  Write("bridge_1_junk.txt", "");
  auto protocol = LoadOxfordProtocol(dir_.string(), "toy");
  ASSERT_TRUE(protocol) << protocol.error().ToString();
  ASSERT_EQ(protocol->queries.size(), 2u);
  const EvalQuery& tower = protocol->queries[1];
  EXPECT_EQ(tower.name, "tower_1");
  EXPECT_EQ(tower.image, "tower_000001");  // "oxc1_" prefix stripped
  ASSERT_TRUE(tower.bbox);
  EXPECT_FLOAT_EQ(tower.bbox.value()[0], 10.5f);
  EXPECT_FLOAT_EQ(tower.bbox.value()[3], 400.25f);
  EXPECT_EQ(tower.relevance.positives.size(), 3u);
  EXPECT_TRUE(tower.relevance.positives.contains("tower_000003"));  // CR stripped
  EXPECT_TRUE(tower.relevance.junk.contains("tower_000009"));
  EXPECT_EQ(protocol->database.size(), 6u);

  // Present: the tower query image, one good image, the junk one, and an unlisted distractor. The
  // bridge query image is absent, so that query is dropped.
  const Protocol restricted =
      RestrictToImages(*protocol, {"tower_000001", "tower_000002", "tower_000009", "distractor"});
  ASSERT_EQ(restricted.queries.size(), 1u);
  EXPECT_EQ(restricted.queries[0].relevance.positives.size(), 2u);
  EXPECT_EQ(restricted.queries[0].relevance.junk.size(), 1u);
  EXPECT_EQ(restricted.database.size(), 4u);
}

TEST_F(GroundTruthTest, RefusesMalformedQueryFileAndMissingFolder) {
  Write("x_query.txt", "only_a_name\n");
  Write("x_good.txt", "");
  Write("x_ok.txt", "");
  Write("x_junk.txt", "");
  auto bad = LoadOxfordProtocol(dir_.string(), "bad");
  ASSERT_FALSE(bad);
  EXPECT_EQ(bad.error().code, ErrorCode::kCorruptData);
  auto missing = LoadOxfordProtocol((dir_ / "nope").string(), "missing");
  ASSERT_FALSE(missing);
  EXPECT_EQ(missing.error().code, ErrorCode::kNotFound);
}

TEST_F(GroundTruthTest, RevisitedSettingsFollowRadenovic) {
  Write("gnd.json", R"({"imlist": ["a", "b", "c", "d"], "qimlist": ["q1", "q2"],
    "gnd": [{"bbx": [1, 2, 3, 4], "easy": [0], "hard": [1], "junk": [2]},
            {"bbx": [1, 2, 3, 4], "easy": [3], "hard": [], "junk": []}]})");
  const std::string path = (dir_ / "gnd.json").string();
  auto easy = LoadRevisitedProtocol(path, RevisitedSetting::kEasy, "r");
  auto medium = LoadRevisitedProtocol(path, RevisitedSetting::kMedium, "r");
  auto hard = LoadRevisitedProtocol(path, RevisitedSetting::kHard, "r");
  ASSERT_TRUE(easy && medium && hard);
  EXPECT_EQ(easy->name, "r-easy");
  EXPECT_EQ(easy->queries[0].relevance.positives, (std::unordered_set<std::string>{"a"}));
  EXPECT_EQ(easy->queries[0].relevance.junk, (std::unordered_set<std::string>{"b", "c"}));
  EXPECT_EQ(medium->queries[0].relevance.positives, (std::unordered_set<std::string>{"a", "b"}));
  EXPECT_EQ(hard->queries[0].relevance.positives, (std::unordered_set<std::string>{"b"}));
  EXPECT_EQ(hard->queries[0].relevance.junk, (std::unordered_set<std::string>{"a", "c"}));
  EXPECT_EQ(hard->queries.size(), 1u);  // q2 has no hard positive: dropped, as revisitop skips it
  EXPECT_EQ(medium->queries.size(), 2u);

  // Restricted to a folder that also holds the query photos: they are indexed, so they are junk (queries
  // are not database images in the revisited protocol).
  const Protocol restricted = RestrictToImages(*medium, {"a", "b", "d", "q1", "q2"});
  ASSERT_EQ(restricted.queries.size(), 2u);
  EXPECT_EQ(restricted.queries[0].relevance.positives, (std::unordered_set<std::string>{"a", "b"}));
  EXPECT_EQ(restricted.queries[0].relevance.junk, (std::unordered_set<std::string>{"q1", "q2"}));
  EXPECT_EQ(restricted.queries[1].relevance.junk, (std::unordered_set<std::string>{"q1", "q2"}));

  Write("broken.json", R"({"imlist": ["a"], "qimlist": ["q"], "gnd": [{"bbx": [], "easy": [7], "hard": [], "junk": []}]})");
  auto broken = LoadRevisitedProtocol((dir_ / "broken.json").string(), RevisitedSetting::kEasy, "r");
  ASSERT_FALSE(broken);
  EXPECT_EQ(broken.error().code, ErrorCode::kCorruptData);
  // Another JSON document: what is missing, without the JSON library's exception prefix.
  Write("other.json", R"({"images": []})");
  auto other = LoadRevisitedProtocol((dir_ / "other.json").string(), RevisitedSetting::kEasy, "r");
  ASSERT_FALSE(other);
  EXPECT_EQ(other.error().code, ErrorCode::kCorruptData);
  EXPECT_NE(other.error().message.find("key 'imlist' not found"), std::string::npos) << other.error().message;
  EXPECT_EQ(other.error().message.find("json.exception"), std::string::npos) << other.error().message;
  // A folder where the file belongs (it opens as a stream, and fails only when read).
  auto folder = LoadRevisitedProtocol(dir_.string(), RevisitedSetting::kEasy, "r");
  ASSERT_FALSE(folder);
  EXPECT_EQ(folder.error().code, ErrorCode::kInvalidArgument);
  EXPECT_NE(folder.error().message.find("is a folder"), std::string::npos) << folder.error().message;
}

TEST_F(GroundTruthTest, GroupsProtocol) {
  for (const char* f : {"groups/mug/m1.jpg", "groups/mug/m2.png", "groups/mug/notes.txt", "groups/shoe/s1.jpg",
                        "groups/shoe/s2.jpg", "groups/shoe/s3.JPG", "groups/lonely/only.jpg", "groups/loose.jpg"}) {
    fs::create_directories((dir_ / f).parent_path());
    Write(f, "x");
  }
  auto protocol = LoadGroupsProtocol((dir_ / "groups").string());
  ASSERT_TRUE(protocol) << protocol.error().ToString();
  EXPECT_EQ(protocol->name, "groups");
  EXPECT_EQ(protocol->ap, ApDefinition::kNonInterpolated);
  // Images directly in the folder belong to no group; a group of one is in the database but queries nothing.
  EXPECT_EQ(protocol->database, (std::vector<std::string>{"lonely__only", "mug__m1", "mug__m2", "shoe__s1",
                                                          "shoe__s2", "shoe__s3"}));
  EXPECT_EQ(protocol->files.at("mug__m2"), (dir_ / "groups/mug/m2.png").string());
  EXPECT_EQ(protocol->distractors, 0u);
  ASSERT_EQ(protocol->queries.size(), 5u);
  const EvalQuery& m1 = protocol->queries[0];
  EXPECT_EQ(m1.image, "mug__m1");
  EXPECT_EQ(m1.group, "mug");
  EXPECT_EQ(m1.relevance.positives, (std::unordered_set<std::string>{"mug__m2"}));
  EXPECT_EQ(m1.relevance.junk, (std::unordered_set<std::string>{"mug__m1"}));
  EXPECT_EQ(protocol->queries[4].relevance.positives, (std::unordered_set<std::string>{"shoe__s1", "shoe__s2"}));
}

TEST_F(GroundTruthTest, GroupsMayReuseFileNamesAndNestFolders) {
  // groups_dev ships two groups that each hold a "03.*": their ids differ by group.
  for (const char* f : {"g/a/03.jpg", "g/a/04.jpg", "g/b/03.png", "g/b/x/03.jpg"}) {
    fs::create_directories((dir_ / f).parent_path());
    Write(f, "x");
  }
  auto protocol = LoadGroupsProtocol((dir_ / "g").string());
  ASSERT_TRUE(protocol) << protocol.error().ToString();
  EXPECT_EQ(protocol->database, (std::vector<std::string>{"a__03", "a__04", "b__03", "b__x__03"}));
  ASSERT_EQ(protocol->queries.size(), 4u);
  EXPECT_EQ(protocol->queries[2].name, "b__03");
  EXPECT_EQ(protocol->queries[2].relevance.positives, (std::unordered_set<std::string>{"b__x__03"}));
  // Two files of one folder with the same name but another extension would share an id: refused.
  Write("g/a/04.png", "x");
  auto ambiguous = LoadGroupsProtocol((dir_ / "g").string());
  ASSERT_FALSE(ambiguous);
  EXPECT_EQ(ambiguous.error().code, ErrorCode::kInvalidArgument);
  EXPECT_NE(ambiguous.error().message.find("a__04"), std::string::npos) << ambiguous.error().message;
}

TEST_F(GroundTruthTest, GroupsDistractorsJoinTheDatabaseOnly) {
  for (const char* f : {"g/a/1.jpg", "g/a/2.jpg", "g/b/1.jpg", "g/b/2.jpg", "d/1.jpg", "d/street/1.jpg",
                        "d/street/night/2.png", "d/readme.md"}) {
    fs::create_directories((dir_ / f).parent_path());
    Write(f, "x");
  }
  auto protocol = LoadGroupsProtocol((dir_ / "g").string(), (dir_ / "d").string());
  ASSERT_TRUE(protocol) << protocol.error().ToString();
  EXPECT_EQ(protocol->name, "groups+distractors");
  EXPECT_EQ(protocol->distractors, 3u);
  EXPECT_EQ(protocol->database.size(), 7u);
  EXPECT_EQ(protocol->files.at("distractor__street__night__2"), (dir_ / "d/street/night/2.png").string());
  ASSERT_EQ(protocol->queries.size(), 4u);  // distractors never query
  for (const EvalQuery& q : protocol->queries) {
    EXPECT_EQ(q.relevance.positives.size(), 1u) << q.name;  // nor count as positives
    for (const std::string& id : q.relevance.positives) EXPECT_FALSE(id.starts_with("distractor")) << id;
  }
  auto missing = LoadGroupsProtocol((dir_ / "g").string(), (dir_ / "nope").string());
  ASSERT_FALSE(missing);
  EXPECT_EQ(missing.error().code, ErrorCode::kNotFound);
}

// The official Paris ground truth restricted to the 250-image subset (tests/support/shared_data.h), when present:
// the counts stated in the data README.
TEST(ParisSubsetSharedData, RestrictedProtocolMatchesDataReadme) {
  const fs::path data = oxbow::testing::SharedDataDir() / "paris6k";
  if (!fs::exists(data / "gt")) GTEST_SKIP() << "Paris data not present at " << data << " (set OXBOW_SHARED_DATA)";
  auto protocol = LoadOxfordProtocol((data / "gt").string(), "paris6k");
  ASSERT_TRUE(protocol) << protocol.error().ToString();
  EXPECT_EQ(protocol->queries.size(), 55u);
  auto ids = ListImageIds((data / "images").string());
  ASSERT_TRUE(ids);
  ASSERT_EQ(ids->size(), 250u);
  const Protocol restricted = RestrictToImages(*protocol, *ids);
  EXPECT_EQ(restricted.queries.size(), 12u);
  EXPECT_EQ(restricted.database.size(), 250u);
  for (const EvalQuery& q : restricted.queries) {
    if (q.name == "defense_4") {
      EXPECT_EQ(q.relevance.positives.size(), 39u);
      EXPECT_EQ(q.relevance.junk.size(), 8u);
    }
    if (q.name == "moulinrouge_2") {
      EXPECT_EQ(q.relevance.positives.size(), 32u);
      EXPECT_EQ(q.relevance.junk.size(), 16u);
    }
  }
}

// groups_dev and groups_hard as shipped (tests/support/shared_data.h), when present: the counts their READMEs state.
TEST(GroupsSharedData, ShippedSetsLoadWithTheirReadmeCounts) {
  const fs::path data = oxbow::testing::SharedDataDir();
  for (const char* set : {"groups_dev", "groups_hard", "distractors"}) {
    if (!fs::exists(data / set)) GTEST_SKIP() << set << " not present in " << data << " (set OXBOW_SHARED_DATA)";
  }
  auto dev = LoadGroupsProtocol((data / "groups_dev").string());
  ASSERT_TRUE(dev) << dev.error().ToString();  // two of its groups each hold a "03.*"
  EXPECT_EQ(dev->database.size(), 187u);
  EXPECT_EQ(dev->queries.size(), 187u);
  std::set<std::string> groups;
  size_t top4_ceiling = 0;
  for (const EvalQuery& q : dev->queries) {
    groups.insert(q.group);
    top4_ceiling += std::min<size_t>(4, q.relevance.positives.size());
  }
  EXPECT_EQ(groups.size(), 36u);
  EXPECT_NEAR(static_cast<double>(top4_ceiling) / 187.0, 3.47, 0.005);  // the ceiling its README states
  auto hard = LoadGroupsProtocol((data / "groups_hard").string(), (data / "distractors").string());
  ASSERT_TRUE(hard) << hard.error().ToString();
  EXPECT_EQ(hard->queries.size(), 126u);
  EXPECT_EQ(hard->distractors, 277u);
  EXPECT_EQ(hard->database.size(), 126u + 277u);
}

}  // namespace
}  // namespace oxbow::eval
