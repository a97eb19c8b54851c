// Checkpoint files (storage/checkpoint.h): mapped and resident files, the check of a whole file.
#include "index/storage/test_support.h"

#include <gtest/gtest.h>

namespace oxbow::index {
namespace {

using namespace test_support;  // NOLINT(google-build-using-namespace): the tests' shared fixtures

// Both ways of holding a checkpoint file give its exact bytes; a missing file is kNotFound.
TEST(CheckpointTest, ResidentAndMappedFilesHoldTheFileBytes) {
  const oxbow::testing::TempDir temp;
  const fs::path dir = temp.path();
  std::string content(3u << 20, '\0');  // over a 2 MB huge page, not a multiple of it
  for (size_t i = 0; i < content.size(); ++i) content[i] = static_cast<char>((i * 2654435761u) >> 13);
  std::ofstream((dir / "f").string(), std::ios::binary) << content;
  std::ofstream((dir / "empty").string(), std::ios::binary).flush();
  for (const MappedFile::Use use : {MappedFile::Use::kRandom, MappedFile::Use::kResident}) {
    auto file = MappedFile::Open((dir / "f").string(), use);
    ASSERT_TRUE(file) << file.error().ToString();
    const auto bytes = (*file)->bytes();
    EXPECT_TRUE(std::string_view(reinterpret_cast<const char*>(bytes.data()), bytes.size()) == content);
    auto empty = MappedFile::Open((dir / "empty").string(), use);
    ASSERT_TRUE(empty) << empty.error().ToString();
    EXPECT_TRUE((*empty)->bytes().empty());
    auto missing = MappedFile::Open((dir / "missing").string(), use);
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().code, ErrorCode::kNotFound);
  }
}

// The check of a checkpoint file leaves the page cache as it found it: pages it held stay, pages it
// did not are not left there (a 16 GB check at 1M images would otherwise push the searches' pages out
// and fill memory; index/README.md). Seen with mincore on a mapping never touched.
TEST(CheckpointTest, TheCheckLeavesThePageCacheAsItWas) {
  // Beside the test binary, not in /tmp: pages of a tmpfs file are always in memory.
  const oxbow::testing::TempDir temp("oxbow-check-cache", fs::current_path());
  const fs::path dir = temp.path();
  std::mt19937_64 rng(5);
  std::vector<uint8_t> bytes((size_t{10} << 20) + 12345);  // more than two 4 MiB reads, a partial page at the end
  for (auto& b : bytes) b = static_cast<uint8_t>(rng());
  auto file = WriteCheckpointFile(dir.string(), "geometry-test.oxck",
                                  [&](const ByteSink& sink) { sink(std::span<const uint8_t>(bytes)); });
  ASSERT_TRUE(file) << file.error().ToString();
  const std::string path = (dir / file->name).string();
  const int fd = ::open(path.c_str(), O_RDONLY);
  ASSERT_GE(fd, 0);
  void* mapping = ::mmap(nullptr, bytes.size(), PROT_READ, MAP_SHARED, fd, 0);
  ASSERT_NE(mapping, MAP_FAILED);
  const auto page = static_cast<size_t>(::sysconf(_SC_PAGESIZE));
  const size_t pages = (bytes.size() + page - 1) / page;
  const auto resident = [&](size_t first, size_t last) {  // of pages [first, last)
    std::vector<unsigned char> in(pages);
    EXPECT_EQ(::mincore(mapping, bytes.size(), in.data()), 0);
    size_t count = 0;
    for (size_t p = first; p < last; ++p) count += in[p] & 1;
    return count;
  };
  ASSERT_EQ(::posix_fadvise(fd, 0, 0, POSIX_FADV_RANDOM), 0);  // this test's reads bring in only what they read
  const auto drop = [&] { ASSERT_EQ(::posix_fadvise(fd, 0, 0, POSIX_FADV_DONTNEED), 0); };
  drop();  // WriteCheckpointFile synced it: clean pages, dropped
  if (resident(0, pages) > pages / 2) {
    ::munmap(mapping, bytes.size());
    ::close(fd);
    GTEST_SKIP() << "the file system of " << dir << " keeps files in memory (posix_fadvise dropped nothing)";
  }
  // Not held: read, checked, and not left in the cache.
  ASSERT_TRUE(VerifyCheckpointFile(dir.string(), *file));
  EXPECT_EQ(resident(0, pages), 0u) << "of " << pages << " pages";
  // Held in part (the first 3 MiB and the last 1 MiB, as a search's reads would leave them): those stay,
  // and only those.
  std::vector<uint8_t> scratch(bytes.size());
  const size_t head = size_t{3} << 20, tail_from = bytes.size() - (size_t{1} << 20);
  ASSERT_EQ(::pread(fd, scratch.data(), head, 0), static_cast<ssize_t>(head));
  ASSERT_EQ(::pread(fd, scratch.data(), bytes.size() - tail_from, static_cast<off_t>(tail_from)),
            static_cast<ssize_t>(bytes.size() - tail_from));
  const size_t held_before = resident(0, pages);
  ASSERT_GE(held_before, (head + bytes.size() - tail_from) / page);
  ASSERT_TRUE(VerifyCheckpointFile(dir.string(), *file));
  // The kernel may evict a few clean pages under memory pressure meanwhile (seen on a loaded CI machine:
  // one page of 2564); a check that dropped what was held would drop them all.
  const auto held = [&](size_t first, size_t last) {
    const size_t expected = last - first;
    const size_t now = resident(first, last);
    return ::testing::AssertionResult(now + expected / 64 >= expected) << now << " of " << expected << " pages held";
  };
  EXPECT_TRUE(held(0, head / page)) << "pages held before the check were dropped";
  EXPECT_TRUE(held(tail_from / page + 1, pages));
  EXPECT_EQ(resident(head / page, tail_from / page), 0u) << "the check left pages it read in the cache";
  EXPECT_LE(resident(0, pages), held_before) << "the check left pages it read in the cache";
  // Held whole: still held, and the check still finds a damaged file.
  ASSERT_EQ(::pread(fd, scratch.data(), bytes.size(), 0), static_cast<ssize_t>(bytes.size()));
  ASSERT_TRUE(VerifyCheckpointFile(dir.string(), *file));
  EXPECT_TRUE(held(0, pages));
  CheckpointFile wrong = *file;
  wrong.checksum ^= 1;
  const Status damaged = VerifyCheckpointFile(dir.string(), wrong);
  ASSERT_FALSE(damaged);
  EXPECT_EQ(damaged.error().code, ErrorCode::kCorruptData);
  ::munmap(mapping, bytes.size());
  ::close(fd);
}

}  // namespace
}  // namespace oxbow::index
