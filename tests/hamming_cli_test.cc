// Hamming embedding through the commands: `vocab train --hamming` and `vocab hamming` write vocabularies
// with the parameters (`vocab info` says so, the input of `vocab hamming` is left alone, and it extracts
// images with the vocabulary's recorded settings), `index build` stores signatures with them, and
// `query --hamming` finds the object; the server takes hamming=true.
#include <gtest/gtest.h>

#include <httplib.h>
#include <nlohmann/json.hpp>

#include <filesystem>
#include <string>
#include <tuple>

#include "tests/support/e2e.h"
#include "tests/support/samples.h"
#include "tests/support/temp_dir.h"

namespace oxbow {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;
using testing::RunCommand;

const fs::path kSamples = "/usr/share/doc/opencv-doc/examples/data";

std::string Oxbow(const std::string& args) { return std::string(OXBOW_BINARY) + " " + args + " 2>&1"; }

TEST(HammingCli, TrainIndexAndSearchWithSignatures) {
  for (const char* name : {"box.png", "graf1.png", "graf3.png", "box_in_scene.png"}) {
    if (!fs::exists(kSamples / name)) GTEST_SKIP() << "opencv-doc sample photos not installed (scripts/install-deps.sh)";
  }
  oxbow::testing::TempDir dir("oxbow-hamming-cli");
  const auto path = [&](const std::string& name) { return dir.path() + "/" + name; };
  fs::create_directories(path("photos"));
  for (const char* name : {"box.png", "graf1.png", "graf3.png"}) fs::copy_file(kSamples / name, path("photos/") + name);
  int rc = 0;
  // The parameters are learnt by default.
  std::string out = RunCommand(Oxbow("vocab train --images " + path("photos") + " --words 1000 --out " +
                                     path("he.oxvoc")),
                               &rc);
  ASSERT_EQ(rc, 0) << out;
  out = RunCommand(Oxbow("vocab info " + path("he.oxvoc")), &rc);
  ASSERT_EQ(rc, 0) << out;
  EXPECT_NE(out.find("hamming      64-bit embedding"), std::string::npos) << out;

  out = RunCommand(
      Oxbow("vocab train --images " + path("photos") + " --words 64 --no-hamming --out " + path("plain.oxvoc")), &rc);
  ASSERT_EQ(rc, 0) << out;
  out = RunCommand(Oxbow("vocab hamming --vocab " + path("plain.oxvoc") + " --images " + path("photos") + " --out " +
                         path("added.oxvoc")),
                   &rc);
  ASSERT_EQ(rc, 0) << out;
  out = RunCommand(Oxbow("vocab info " + path("added.oxvoc")), &rc);
  EXPECT_NE(out.find("hamming      64-bit embedding"), std::string::npos) << out;
  out = RunCommand(Oxbow("vocab info " + path("plain.oxvoc")), &rc);
  EXPECT_NE(out.find("hamming      none"), std::string::npos) << "the input is not modified: " << out;
  // A vocabulary of other extractor settings (upright features, a wider descriptor, the grid sampling)
  // gets its parameters from images too: they are extracted with the settings it records.
  for (const auto& [name, flags, described] :
       {std::tuple{"upright", " --upright --descriptor-magnification 4 --descriptor-row-step 2",
                   "upright=1;magnification=4;row_step=2"},
        std::tuple{"grid", " --descriptor-sampling grid", "keypoints=vlfeat;sampling=grid"}}) {
    const auto vocabulary = [&, name = name](const char* suffix) { return path(std::string(name) + suffix); };
    out = RunCommand(
        Oxbow("vocab train --images " + path("photos") + flags + " --words 64 --no-hamming --out " + vocabulary(".oxvoc")),
        &rc);
    ASSERT_EQ(rc, 0) << out;
    out = RunCommand(Oxbow("vocab hamming --vocab " + vocabulary(".oxvoc") + " --images " + path("photos") + " --out " +
                           vocabulary("-he.oxvoc")),
                     &rc);
    ASSERT_EQ(rc, 0) << out;
    out = RunCommand(Oxbow("vocab info " + vocabulary("-he.oxvoc")), &rc);
    EXPECT_NE(out.find("hamming      64-bit embedding"), std::string::npos) << out;
    EXPECT_NE(out.find(described), std::string::npos) << out;
  }

  out = RunCommand(Oxbow("index build --vocab " + path("he.oxvoc") + " --images " + path("photos") + " --out " +
                         path("index")),
                   &rc);
  ASSERT_EQ(rc, 0) << out;
  const std::string scene = (kSamples / "box_in_scene.png").string();
  // 1000 words for 3 photos: with 64 nearly every word is in every photo (idf 0) and nothing scores.
  out = RunCommand(Oxbow("query --index " + path("index") + " --hamming " + scene), &rc);
  ASSERT_EQ(rc, 0) << out;
  const json query = json::parse(out.substr(out.find('{')));
  ASSERT_FALSE(query["results"].empty()) << out;
  EXPECT_EQ(query["results"][0]["id"], "box") << out;
  EXPECT_TRUE(query["results"][0]["verified"].get<bool>()) << out;
  out = RunCommand(Oxbow("query --index " + path("index") + " --no-hamming " + scene), &rc);
  ASSERT_EQ(rc, 0) << out;

  testing::ServerProcess server({"serve", "--index", path("index"), "--port", "0"}, path("serve.log"));
  ASSERT_GT(server.port(), 0) << server.Log();
  ASSERT_TRUE(server.WaitReady()) << server.Log();
  const std::string bytes = testing::FileBytes(scene);
  httplib::Client client("127.0.0.1", server.port());
  client.set_read_timeout(120);
  auto response = client.Post("/v1/search?hamming=true", bytes, "application/octet-stream");
  ASSERT_TRUE(response);
  ASSERT_EQ(response->status, 200) << response->body;
  const json body = json::parse(response->body);
  ASSERT_FALSE(body["results"].empty()) << response->body;
  EXPECT_EQ(body["results"][0]["id"], "box") << response->body;
  EXPECT_TRUE(body["results"][0]["verified"].get<bool>()) << response->body;
}

}  // namespace
}  // namespace oxbow
