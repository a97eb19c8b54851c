// The catalogue (storage/catalogue.h) under an index: its write-ahead log copied beside the commits.
#include "index/storage/test_support.h"

#include <gtest/gtest.h>

namespace oxbow::index {
namespace {

using namespace test_support;  // NOLINT(google-build-using-namespace): the tests' shared fixtures

class CatalogueTest : public IndexFixture {};
// Commits do not copy SQLite's write-ahead log into the database file themselves: a thread of the
// catalogue does, beside them, and the log stays bounded (a transaction that finds it over 32 MiB waits
// for a copy of all of it first, and then starts it again from its beginning). 24 rows of 4 MiB, 96 MiB
// in all: the log never passes 32 MiB plus one transaction, the database file receives the rows while
// the catalogue is open, and every row reads back whole after a reopen.
TEST_F(CatalogueTest, TheCatalogueLogIsCopiedBesideTheCommitsAndStaysBounded) {
  fs::create_directories(dir_);
  const std::string path = (dir_ / kCatalogueFile).string();
  CatalogueMeta meta;
  meta.vocabulary_size = kWords;
  meta.descriptor_kind = "rootsift";
  meta.extractor_settings = "test-extractor/1";
  constexpr int kRows = 24;
  constexpr size_t kBlob = size_t{4} << 20;
  std::vector<uint8_t> noise(kBlob);  // one random buffer, each row's copy marked with its number
  std::mt19937_64 rng(7);
  for (size_t k = 0; k < kBlob; k += 8) {
    const uint64_t r = rng();
    std::memcpy(noise.data() + k, &r, 8);
  }
  const auto blob_of = [&](int i) {
    std::vector<uint8_t> blob = noise;
    for (size_t k = 0; k < kBlob; k += 4096) blob[k] = static_cast<uint8_t>(i);
    return blob;
  };
  const auto size_of = [](const std::string& file) {
    std::error_code ec;
    const auto size = fs::file_size(file, ec);
    return ec ? uintmax_t{0} : size;
  };
  uintmax_t largest_log = 0;
  {
    auto catalogue = Catalogue::Create(path, meta);
    ASSERT_TRUE(catalogue) << catalogue.error().ToString();
    for (int i = 0; i < kRows; ++i) {
      ImageRecord record;
      record.id = "row" + std::to_string(i);
      record.num_features = 1;
      ASSERT_TRUE((*catalogue)->Insert(record, blob_of(i)));
      largest_log = std::max(largest_log, size_of(path + "-wal"));
    }
    // Copied while open: wait for the database file to hold most of the rows.
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
    while (size_of(path) < (kRows - 9) * kBlob && std::chrono::steady_clock::now() < deadline) {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    EXPECT_GE(size_of(path), (kRows - 9) * kBlob);
  }
  EXPECT_LE(largest_log, (size_t{32} << 20) + 2 * kBlob);  // 32 MiB, then at most one transaction more
  auto reopened = Catalogue::Open(path);
  ASSERT_TRUE(reopened) << reopened.error().ToString();
  int rows = 0;
  ASSERT_TRUE((*reopened)->ForEach([&](CatalogueRow&& row) -> Status {
    EXPECT_EQ(row.record.id, "row" + std::to_string(rows));
    EXPECT_TRUE(row.features == blob_of(rows)) << row.record.id;
    ++rows;
    return Ok();
  }));
  EXPECT_EQ(rows, kRows);
}

}  // namespace
}  // namespace oxbow::index
