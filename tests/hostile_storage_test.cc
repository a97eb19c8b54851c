// The real `oxbow serve` against index folders it must refuse without changing them: a stray or foreign
// catalogue.sqlite-wal beside the catalogue (refused, and the catalogue byte-identical afterwards: a
// read-write connection would checkpoint that WAL into it when the refused open closed it), and
// a folder the server may not write (exit 7, io_error, saying it is a permission problem, not damage),
// and a file size limit (ulimit -f) that a write reaches: an io_error answer or exit 7, never SIGXFSZ.
// And a running server whose checkpoint files are truncated under it while it searches them.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "api/service.h"
#include "tests/support/e2e.h"
#include "tests/support/samples.h"
#include "tests/support/temp_dir.h"

namespace oxbow {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

using testing::FileBytes;

std::vector<uint8_t> Picture(int n) {
  const cv::Mat picture = oxbow::testing::Texture(320, 240, "graf1.png", 10 * n, 5 * n);
  std::vector<uchar> png;
  cv::imencode(".png", picture, png);
  return {png.begin(), png.end()};
}

class HostileStorageTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_FALSE(dir_.path().empty());
    const std::string settings = testing::TestSiftOptions().Describe();
    ASSERT_TRUE(oxbow::testing::RandomVocabulary(settings, 256)->Write(vocab_));
    auto service = api::Service::Open(index_, vocab_, {});
    ASSERT_TRUE(service) << service.error().ToString();
    for (int i = 0; i < kImages; ++i) {
      api::AddImageRequest add;
      add.id = "img" + std::to_string(i);
      const std::vector<uint8_t> picture = Picture(i);
      add.image = picture;
      add.source_name = "http";
      const auto added = (*service)->AddImage(add);
      ASSERT_TRUE(added) << added.error().ToString();
    }
  }
  // A copy of the index folder at `name`.
  std::string CopyIndex(const std::string& name) const {
    std::string copy = dir_.path() + "/" + name;
    fs::copy(index_, copy, fs::copy_options::recursive);
    return copy;
  }
  // Images the server started on `index` lists (-1 when it does not start).
  int ServedImages(const std::string& index) {
    oxbow::testing::ServerProcess server({"serve", "--index", index, "--port", "0"},
                                         dir_.path() + "/serve-" + std::to_string(counter_++) + ".log");
    if (server.port() == 0 || !server.WaitReady()) return -1;
    auto client = server.Client();
    const auto res = client.Get("/v1/images?limit=1000");
    if (!res || res->status != 200) return -1;
    return json::parse(res->body)["total"].get<int>();
  }

  static constexpr int kImages = 4;
  oxbow::testing::TempDir dir_{"oxbow-hostile-storage"};
  const std::string vocab_ = dir_.path() + "/vocab.oxvoc";
  const std::string index_ = dir_.path() + "/index";
  int counter_ = 0;
};

TEST_F(HostileStorageTest, ForeignWalIsRefusedAndTheCatalogueStaysByteIdentical) {
  // The WAL of another index (another vocabulary), taken while it holds a committed, not yet
  // checkpointed add.
  const std::string other_vocab = dir_.path() + "/other.oxvoc";
  ASSERT_TRUE(oxbow::testing::RandomVocabulary(testing::TestSiftOptions().Describe(), 128)->Write(other_vocab));
  std::string foreign_wal;
  {
    auto other = api::Service::Open(dir_.path() + "/other", other_vocab, {});
    ASSERT_TRUE(other) << other.error().ToString();
    api::AddImageRequest add;
    add.id = "foreign";
    const std::vector<uint8_t> picture = Picture(9);
    add.image = picture;
    ASSERT_TRUE((*other)->AddImage(add));
    foreign_wal = FileBytes(dir_.path() + "/other/catalogue.sqlite-wal");
  }
  ASSERT_GT(foreign_wal.size(), 32u);

  const std::string copy = CopyIndex("with-foreign-wal");
  const std::string catalogue = FileBytes(copy + "/catalogue.sqlite");
  std::ofstream(copy + "/catalogue.sqlite-wal", std::ios::binary) << foreign_wal;
  int exit_code = 0;
  const std::string output = oxbow::testing::RunCommand(
      std::string(OXBOW_BINARY) + " serve --index " + copy + " --port 0 2>&1", &exit_code);
  EXPECT_EQ(exit_code, 6) << output;  // incompatible: the WAL's catalogue names another vocabulary
  EXPECT_NE(output.find("does not match"), std::string::npos) << output;
  EXPECT_TRUE(FileBytes(copy + "/catalogue.sqlite") == catalogue) << "the refused start wrote to the catalogue";

  // Without the stray file the copy serves every image.
  fs::remove(copy + "/catalogue.sqlite-wal");
  fs::remove(copy + "/catalogue.sqlite-shm");
  EXPECT_EQ(ServedImages(copy), kImages);
}

TEST_F(HostileStorageTest, ReadOnlyIndexFolderIsAnIoErrorExit7) {
  const std::string copy = CopyIndex("read-only");
  const std::string catalogue = FileBytes(copy + "/catalogue.sqlite");
  int exit_code = 0;
  ASSERT_EQ(oxbow::testing::RunCommand("chmod -R a-w " + copy, &exit_code), "");
  ASSERT_EQ(exit_code, 0);
  // Root ignores file permissions: run the server as user nobody then (who may enter the test folder).
  std::string as_user;
  if (geteuid() == 0) {
    fs::permissions(dir_.path(), fs::perms::others_exec, fs::perm_options::add);
    as_user = "setpriv --reuid=65534 --regid=65534 --clear-groups ";
    oxbow::testing::RunCommand(as_user + "test -x " + std::string(OXBOW_BINARY), &exit_code);
    if (exit_code != 0) GTEST_SKIP() << "running as root and cannot run oxbow as user nobody (setpriv, or a build folder nobody cannot reach)";
  }
  const std::string output = oxbow::testing::RunCommand(
      as_user + OXBOW_BINARY + " serve --index " + copy + " --port 0 2>&1", &exit_code);
  int restored = 0;
  oxbow::testing::RunCommand("chmod -R u+w " + copy, &restored);
  EXPECT_EQ(exit_code, 7) << output;
  EXPECT_NE(output.find("io_error"), std::string::npos) << output;
  EXPECT_NE(output.find("permissions"), std::string::npos) << output;
  EXPECT_EQ(output.find("corrupt"), std::string::npos) << output;
  EXPECT_TRUE(FileBytes(copy + "/catalogue.sqlite") == catalogue) << "the catalogue changed";
  EXPECT_EQ(ServedImages(copy), kImages);
}

// Sets the file size limit (RLIMIT_FSIZE, soft) of this process while alive: a server started meanwhile
// inherits it.
class FileSizeLimit {
 public:
  explicit FileSizeLimit(rlim_t bytes) {
    getrlimit(RLIMIT_FSIZE, &saved_);
    rlimit limit = saved_;
    limit.rlim_cur = bytes;
    EXPECT_EQ(setrlimit(RLIMIT_FSIZE, &limit), 0);
  }
  ~FileSizeLimit() { setrlimit(RLIMIT_FSIZE, &saved_); }
  FileSizeLimit(const FileSizeLimit&) = delete;
  FileSizeLimit& operator=(const FileSizeLimit&) = delete;

 private:
  rlimit saved_{};
};

TEST_F(HostileStorageTest, AFileSizeLimitIsAnIoErrorNotASignal) {
  constexpr rlim_t kLimit = 64 << 10;
  constexpr rlim_t kSmallLimit = 48 << 10;  // above the 32 KiB of a SQLite -shm file
  // A new index copies the vocabulary (128 KiB): the start fails with exit 7, saying why.
  {
    std::unique_ptr<oxbow::testing::ServerProcess> server;
    {
      const FileSizeLimit limit(kLimit);
      server = std::make_unique<oxbow::testing::ServerProcess>(
          std::vector<std::string>{"serve", "--index", dir_.path() + "/new", "--vocab", vocab_, "--port", "0"},
          dir_.path() + "/limited-new.log");
    }
    EXPECT_EQ(server->Wait(), 7) << server->Log();
    EXPECT_NE(server->Log().find("File too large"), std::string::npos) << server->Log();
  }
  // A running server whose write reaches the limit answers an error and goes on serving.
  const std::string empty = dir_.path() + "/empty";
  ASSERT_TRUE(api::Service::Open(empty, vocab_, {}).has_value());
  std::unique_ptr<oxbow::testing::ServerProcess> server;
  {
    const FileSizeLimit limit(kSmallLimit);
    server = std::make_unique<oxbow::testing::ServerProcess>(
        std::vector<std::string>{"serve", "--index", empty, "--port", "0"}, dir_.path() + "/limited.log");
  }
  ASSERT_TRUE(server->port() > 0 && server->WaitReady()) << server->Log();
  auto client = server->Client();
  std::vector<uchar> png;
  ASSERT_TRUE(cv::imencode(".png", oxbow::testing::Texture(1024, 768), png));
  const std::string image(png.begin(), png.end());
  ASSERT_GT(image.size(), kSmallLimit);
  const auto added = client.Post("/v1/images?id=big", image, "image/png");
  ASSERT_TRUE(added) << "no answer: " << server->Log();
  EXPECT_EQ(added->status, 500) << added->body;
  EXPECT_EQ(json::parse(added->body, nullptr, false)["error"]["code"], "io_error") << added->body;
  const auto health = client.Get("/healthz");
  ASSERT_TRUE(health) << server->Log();
  EXPECT_EQ(health->status, 200);
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

// The geometry files (memory-mapped by the server) truncated to nothing and written back, again and
// again, while `/similar` reads the images in them: the server never dies of SIGBUS, and every answer
// equals the answer before (a damaged file's images are served from the catalogue, never its bytes).
// Each image lies in a file of its own and the server is started several times, so that a read
// between a check of a file and the use of its bytes has many chances to meet a truncation.
TEST_F(HostileStorageTest, GeometryFilesTruncatedUnderSearchesNeverKillTheServerNorChangeAnswers) {
  constexpr int kEach = 8;  // images, and geometry files (at most 8 small files are kept apart)
  constexpr int kRounds = 4;
  constexpr int kQueries = 10;  // per image and round
  const std::string index = dir_.path() + "/one-file-each";
  for (int i = 0; i < kEach; ++i) {  // each close checkpoints the image added since the last
    auto service = api::Service::Open(index, vocab_, {});
    ASSERT_TRUE(service) << service.error().ToString();
    api::AddImageRequest add;
    add.id = "e" + std::to_string(i);
    std::vector<uchar> png;  // larger than Picture's: more features, longer reads of each image
    ASSERT_TRUE(cv::imencode(".png", oxbow::testing::Texture(800, 600, "graf1.png", 10 * i, 5 * i), png));
    const std::vector<uint8_t> picture(png.begin(), png.end());
    add.image = picture;
    ASSERT_TRUE((*service)->AddImage(add));
  }
  std::vector<json> expected;
  for (int round = 0; round < kRounds; ++round) {
    SCOPED_TRACE("round " + std::to_string(round));
    std::vector<std::string> geometry;
    for (const auto& item : fs::directory_iterator(index)) {
      const std::string name = item.path().filename().string();
      if (name.starts_with("geometry-") && name.ends_with(".oxck")) geometry.push_back(item.path().string());
    }
    ASSERT_FALSE(geometry.empty()) << "the index has no checkpoint geometry file";
    if (round == 0) {
      EXPECT_EQ(geometry.size(), size_t{kEach});
    }
    oxbow::testing::ServerProcess server({"serve", "--index", index, "--port", "0"},
                                         dir_.path() + "/truncated-" + std::to_string(round) + ".log");
    ASSERT_TRUE(server.port() > 0 && server.WaitReady()) << server.Log();
    // The background check of the files read them whole before the damage starts.
    ASSERT_TRUE(server.WaitForLog("geometry files of the checkpoint verified")) << server.Log();
    auto client = server.Client();
    const auto similar = [&](int i) -> std::optional<json> {
      const auto res = client.Get("/v1/images/e" + std::to_string(i) + "/similar?top_k=10");
      if (!res || res->status != 200) return std::nullopt;
      return json::parse(res->body)["results"];
    };
    for (int i = 0; round == 0 && i < kEach; ++i) {
      const auto results = similar(i);
      ASSERT_TRUE(results.has_value()) << server.Log();
      ASSERT_FALSE(results->empty());
      expected.push_back(*results);
    }
    std::atomic<bool> stop{false};
    std::atomic<int> truncations{0};
    std::vector<std::thread> truncators;
    truncators.reserve(geometry.size());
    for (const std::string& path : geometry) {
      // The file's last page cut off and written back at once, then left whole for a moment: whole
      // most of the time (so a check usually passes) and cut often (so reads after it meet a cut).
      truncators.emplace_back([&stop, &truncations, path, bytes = FileBytes(path)] {
        const int fd = ::open(path.c_str(), O_WRONLY | O_CLOEXEC);
        if (fd < 0) return;
        const size_t cut = std::min<size_t>(bytes.size() / 2, 4096);
        const auto kept = static_cast<off_t>(bytes.size() - cut);
        while (!stop.load()) {
          if (::ftruncate(fd, kept) != 0) break;
          truncations.fetch_add(1);
          if (::pwrite(fd, bytes.data() + kept, cut, kept) != static_cast<ssize_t>(cut)) break;
          std::this_thread::sleep_for(std::chrono::microseconds(50));
        }
        ::close(fd);  // written back whole
      });
    }
    int answered = 0;
    for (int q = 0; q < kQueries && answered == q * kEach; ++q) {
      for (int i = 0; i < kEach; ++i) {
        const auto results = similar(i);
        if (!results.has_value()) break;
        EXPECT_EQ(*results, expected[i]) << "e" << i;
        ++answered;
      }
    }
    stop = true;
    for (std::thread& t : truncators) t.join();
    EXPECT_GT(truncations.load(), 0);
    EXPECT_EQ(answered, kQueries * kEach) << "the server stopped answering: " << server.Log();
    const auto health = client.Get("/healthz");
    EXPECT_TRUE(health && health->status == 200) << server.Log();
    ASSERT_EQ(server.Stop(), 0) << "128 + 7 (SIGBUS) when the server died of it: " << server.Log();
  }
}

}  // namespace
}  // namespace oxbow
